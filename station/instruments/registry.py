"""Open a measuring instrument by URL: the URL's scheme names a class registered in the ``station.instruments``
entry-point group (``scheme = "module:Class"``, the station's own in pyproject.toml: ``tcp`` is the laser
tracker's line protocol), so a new instrument is a new package, not an edit here. Entry points are read on
first use and a driver module is imported only when its scheme is opened."""

from __future__ import annotations

from typing import TYPE_CHECKING

from station.robot.errors import ConfigError

if TYPE_CHECKING:
    from importlib.metadata import EntryPoint

GROUP = "station.instruments"
_entry_points: dict[str, EntryPoint] | None = None


def _registered() -> dict[str, EntryPoint]:
    global _entry_points
    if _entry_points is None:
        from importlib import metadata

        _entry_points = {ep.name.lower(): ep for ep in metadata.entry_points(group=GROUP)}
    return _entry_points


def schemes() -> list[str]:
    """Every registered instrument URL scheme."""
    return sorted(_registered())


def instrument_class(scheme: str) -> type:
    """The class registered for ``scheme`` (its module imported now)."""
    ep = _registered().get(scheme.lower())
    if ep is None:
        raise ConfigError(f"unknown scheme {scheme!r}; known: {', '.join(schemes()) or 'none'}")
    try:
        return ep.load()
    except ModuleNotFoundError as e:  # a plug-in that did not wrap its own library's import
        if (e.name or "").split(".")[0] == "station":
            raise
        raise ConfigError(f"the {scheme} instrument ({ep.value}) needs the Python module {e.name!r}, which is not "
                          "installed") from None


def url_examples() -> str:
    """How instrument URLs look, one example per registered scheme (``tcp://HOST:PORT``), for messages."""
    out = []
    for s in schemes():
        try:
            out.append(getattr(instrument_class(s), "url_example", f"{s}://..."))
        except ConfigError:
            out.append(f"{s}://...")
    return " or ".join(out) or "URL"


def open_instrument(url: str, **overrides):
    """A connected, identified instrument for ``url``; ``overrides`` go to its ``from_url``."""
    text = str(url)
    scheme = text.split("://", 1)[0].lower() if "://" in text else ""
    try:
        cls = instrument_class(scheme)
    except ConfigError as e:
        raise ConfigError(f"instrument URL {text!r}: {e}") from None
    return cls.from_url(text, **overrides)
