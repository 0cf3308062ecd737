"""Measuring instruments the station reads poses from: a laser tracker over its line protocol
(``tcp://HOST:PORT``, docs/map.md "Tracker protocol"), an ``InstrumentBase`` registered as the
``station.instruments`` entry point ``tcp``. A real instrument's CSV export is read by
``station map build --measurements`` (station.cli.map_cmd) and ``station iso9283 --samples``."""

from station.drivers.tracker.client import TrackerClient, open_tracker, parse_url

__all__ = ["TrackerClient", "open_tracker", "parse_url"]
