"""Open a robot by URL, python-can style: scheme -> driver class, imported lazily.

``dynamixel:///dev/ttyUSB0?baud=1000000&ids=11-14&model=omx``
``canopen+socketcand://127.0.0.1:29536?channel=can0&nodes=1-6&model=arm6``
``canopen+virtual://chan0?nodes=1-6&model=arm6``
``ur://192.168.0.10?model=ur5e``
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from urllib.parse import parse_qs, unquote, urlsplit

from station.robot.errors import ConfigError

# scheme -> "module:Class"; the class has ``from_url(url: RobotURL) -> Robot``.
BACKENDS: dict[str, str] = {
    "dynamixel": "station.drivers.dynamixel:DynamixelRobot",
    "canopen+virtual": "station.drivers.canopen:CanopenRobot",
    "canopen+socketcand": "station.drivers.canopen:CanopenRobot",
    "ur": "station.drivers.ur:URRobot",
}


@dataclass(frozen=True)
class RobotURL:
    raw: str
    scheme: str
    host: str  # host name or channel, "" for dynamixel
    port: int | None
    path: str  # e.g. /dev/ttyUSB0
    query: dict[str, str]

    def get(self, key: str, default: str | None = None) -> str | None:
        return self.query.get(key, default)


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
                if hi < lo:
                    raise ValueError
                out.extend(range(lo, hi + 1))
            else:
                out.append(int(part))
    except ValueError:
        raise ConfigError(f"bad id list {text!r}: expected e.g. '1-6' or '11,12,14'") from None
    return out


def parse_url(url: str) -> RobotURL:
    parts = urlsplit(url)
    if not parts.scheme:
        raise ConfigError(f"robot URL {url!r} has no scheme; known: {', '.join(sorted(BACKENDS))}")
    query = {k: v[-1] for k, v in parse_qs(parts.query, keep_blank_values=True).items()}
    try:
        port = parts.port
    except ValueError:
        raise ConfigError(f"robot URL {url!r}: bad port") from None
    return RobotURL(url, parts.scheme.lower(), parts.hostname or "", port, unquote(parts.path), query)


def open_robot(url: str, **kwargs):
    """Return a connected ``Robot`` for ``url``."""
    parsed = parse_url(url)
    target = BACKENDS.get(parsed.scheme)
    if target is None:
        raise ConfigError(f"robot URL {url!r}: unknown scheme {parsed.scheme!r}; "
                          f"known: {', '.join(sorted(BACKENDS))}")
    module_name, cls_name = target.split(":")
    module = importlib.import_module(module_name)
    return getattr(module, cls_name).from_url(parsed, **kwargs)
