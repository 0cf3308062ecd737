"""Open a measuring instrument by URL: the URL's scheme names a class registered in the ``station.instruments``
entry-point group (``scheme = "module:Class"``, the station's own in pyproject.toml: ``tcp`` is the laser
tracker's line protocol), so a new instrument is a new package, not an edit here. Entry points are read on
first use and a driver module is imported only when its scheme is opened."""

from __future__ import annotations

from station.plugins import Registry
from station.robot.errors import ConfigError

GROUP = "station.instruments"
REGISTRY = Registry(GROUP, "instrument", ConfigError)


def schemes() -> list[str]:
    """Every registered instrument URL scheme."""
    return REGISTRY.names()


def instrument_class(scheme: str) -> type:
    """The class registered for ``scheme`` (its module imported now)."""
    return REGISTRY.load(scheme)


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
