"""Robot URLs and their options, declared once per driver.

A driver lists its query options as :class:`Option` values (name, kind, default, doc); :class:`Options`
parses a URL's query against that list (unknown names, missing required ones and bad values are one-line
``ConfigError``s naming the URL and the option) and renders the same list as the table in the driver's
hardware page, so code, message and documentation cannot drift apart.

    OPTIONS = Options(
        Option("model", text(), REQUIRED, "kinematic model (built-in name or model file)"),
        Option("sync_ms", number(0.5, 1000, unit="ms"), 4.0, "SYNC period"),
    )
    values = OPTIONS.parse(url)          # {"model": "arm6", "sync_ms": 4.0}

No numpy here: ``import station.robot`` stays cheap."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any
from urllib.parse import parse_qs, unquote, urlsplit

from station.robot.errors import ConfigError


@dataclass(frozen=True)
class RobotURL:
    raw: str
    scheme: str
    host: str  # host name or channel (lower-cased by urlsplit), "" for dynamixel
    port: int | None
    path: str  # e.g. /dev/ttyUSB0
    query: dict[str, str]

    def get(self, key: str, default: str | None = None) -> str | None:
        return self.query.get(key, default)

    @property
    def netloc(self) -> str:
        """The authority part as written (keeps its case, unlike ``host``)."""
        return urlsplit(self.raw).netloc


def parse_url(url: str) -> RobotURL:
    try:
        parts = urlsplit(url)
    except ValueError as e:  # e.g. "ur://[::1?" (an unclosed IPv6 bracket)
        raise ConfigError(f"robot URL {url!r}: not a URL ({e})") from None
    if not parts.scheme:
        raise ConfigError(f"robot URL {url!r} has no scheme (e.g. ur://HOST, dynamixel:///dev/ttyUSB0)")
    query = {k: v[-1] for k, v in parse_qs(parts.query, keep_blank_values=True).items()}
    try:
        port = parts.port
    except ValueError:
        raise ConfigError(f"robot URL {url!r}: bad port") from None
    return RobotURL(url, parts.scheme.lower(), parts.hostname or "", port, unquote(parts.path), query)


MAX_ID = 255  # bus ids are one byte (Dynamixel 0-252, CANopen nodes 1-127); a bigger one is a typo


def parse_ids(text: str) -> list[int]:
    """``"11-14,20"`` -> ``[11, 12, 13, 14, 20]``."""
    out: list[int] = []
    try:
        for part in text.split(","):
            part = part.strip()
            if not part:
                continue
            if "-" in part:
                lo, hi = (int(x) for x in part.split("-", 1))
                if hi < lo or lo < 0 or hi > MAX_ID:
                    raise ValueError
                out.extend(range(lo, hi + 1))
            else:
                out.append(int(part))
                if not 0 <= out[-1] <= MAX_ID:
                    raise ValueError
            if len(out) > MAX_ID + 1:
                raise ValueError
    except ValueError:
        raise ConfigError(f"bad id list {text!r}: expected ids 0..{MAX_ID}, e.g. '1-6' or '11,12,14'") from None
    return out


# ---- option kinds: parse one query value, say what form they accept ----------------------------------------
@dataclass(frozen=True)
class Kind:
    """``parse(text) -> value`` raises ``ValueError`` for a value outside ``form`` (shown in errors and docs)."""

    form: str
    parse: Callable[[str], Any]


def text() -> Kind:
    def parse(s: str) -> str:
        if not s:
            raise ValueError
        return s
    return Kind("text", parse)


def integer(lo: int | None = None, hi: int | None = None) -> Kind:
    def parse(s: str) -> int:
        v = int(s)
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise ValueError
        return v
    form = "integer" + (f" {lo}..{hi}" if lo is not None and hi is not None else
                        f" >= {lo}" if lo is not None else f" <= {hi}" if hi is not None else "")
    return Kind(form, parse)


def number(lo: float, hi: float | None = None, *, unit: str = "", open_low: bool = False) -> Kind:
    """A finite number in ``[lo, hi]`` (``(lo, hi]`` with ``open_low``; no upper bound with ``hi=None``)."""
    def parse(s: str) -> float:
        v = float(s)
        if not math.isfinite(v) or (hi is not None and v > hi) or v < lo or (open_low and v == lo):
            raise ValueError
        return v
    u = f" {unit}" if unit else ""
    if hi is None:
        return Kind(f"number {'>' if open_low else '>='} {lo:g}{u}", parse)
    return Kind(f"number in {'(' if open_low else '['}{lo:g}, {hi:g}]{u}", parse)


def flag() -> Kind:
    def parse(s: str) -> bool:
        t = s.strip().lower()
        if t in ("1", "true", "yes", "on"):
            return True
        if t in ("0", "false", "no", "off"):
            return False
        raise ValueError
    return Kind("1 or 0", parse)


def id_list() -> Kind:
    def parse(s: str) -> list[int]:
        try:
            ids = parse_ids(s)
        except ConfigError:
            raise ValueError from None
        if not ids:
            raise ValueError
        return ids
    return Kind("id list such as 1-6 or 11,12,14", parse)


def either(*words: str, otherwise: Kind | None = None, none: tuple[str, ...] = ()) -> Kind:
    """One of ``words`` (returned as is), a word of ``none`` (returned as ``None``), else ``otherwise``."""
    def parse(s: str):
        t = s.strip().lower()
        if t in none:
            return None
        if t in words:
            return t
        if otherwise is None:
            raise ValueError
        return otherwise.parse(s)
    forms = [w for w in (*words, *none) if w] + ([otherwise.form] if otherwise else [])
    return Kind(" / ".join(forms), parse)


REQUIRED = object()  # default of an option the URL must give


@dataclass(frozen=True)
class Option:
    name: str
    kind: Kind
    default: Any  # REQUIRED, a value (already parsed), or None (the driver derives it, see ``default_doc``)
    doc: str
    default_doc: str | None = None  # how the default reads in the docs when it is derived or None

    @property
    def default_text(self) -> str:
        if self.default_doc is not None:
            return self.default_doc
        if self.default is REQUIRED:
            return "required"
        if self.default is None:
            return "none"
        if isinstance(self.default, bool):
            return "1" if self.default else "0"
        return f"{self.default:g}" if isinstance(self.default, float) else str(self.default)


class Options:
    """The query options of one URL scheme family, in documentation order."""

    def __init__(self, *options: Option) -> None:
        self.options = {o.name: o for o in options}
        if len(self.options) != len(options):
            raise ValueError("duplicate option name")

    def __iter__(self):
        return iter(self.options.values())

    def names(self) -> list[str]:
        return list(self.options)

    def parse(self, url: RobotURL, what: str = "robot URL") -> dict[str, Any]:
        """``{name: value}`` for every declared option (defaults filled in); one-line ``ConfigError`` else,
        naming the URL as ``what`` (a measuring instrument's options say "instrument URL")."""
        unknown = sorted(set(url.query) - set(self.options))
        if unknown:
            raise ConfigError(f"{what} {url.raw!r}: unknown option(s) {', '.join(unknown)}; "
                              f"known: {', '.join(sorted(self.options))}")
        out: dict[str, Any] = {}
        for name, opt in self.options.items():
            raw = url.query.get(name)
            if raw is None:
                if opt.default is REQUIRED:
                    raise ConfigError(f"{what} {url.raw!r}: add {name}=... ({opt.doc})")
                out[name] = opt.default
                continue
            try:
                out[name] = opt.kind.parse(raw)
            except (ValueError, TypeError):
                raise ConfigError(f"{what} {url.raw!r}: {name}={raw!r} is not a valid value "
                                  f"(expected {opt.kind.form})") from None
        return out

    def markdown(self) -> str:
        """The options as the table in docs/hardware-*.md (tests compare the two)."""
        rows = ["| option | accepts | default | meaning |", "|---|---|---|---|"]
        for o in self:
            rows.append(f"| `{o.name}` | {o.kind.form} | {o.default_text} | {o.doc} |")
        return "\n".join(rows)
