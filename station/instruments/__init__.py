"""Measuring instruments as plugs: a laser tracker (or any instrument that reads the tool pose) opens by URL
through the ``station.instruments`` entry points, shares one lifecycle (close-once, context manager, URL
options: :class:`InstrumentBase`) and one reading type (:class:`PoseReading`), and a session closes the ones it
opened in the runner's teardown (``Session.instrument``). A new instrument is a package under ``drivers/``
with an ``InstrumentBase`` subclass registered as an entry point; no procedure names it.

Cheap to import, like ``station.robot``: no numpy, no driver (imported when its URL is opened); the names below
load from their modules on first use."""

from __future__ import annotations

from station.lazy import lazy_exports

_EXPORTS = {
    "station.instruments.protocol": ("InstrumentIdentity", "PoseInstrument", "PoseReading"),
    "station.instruments.base": ("InstrumentBase",),
    "station.instruments.registry": ("GROUP", "instrument_class", "open_instrument", "schemes", "url_examples"),
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
