"""Measuring instruments the station reads poses from: a laser tracker over its line protocol
(``tcp://HOST:PORT``, docs/map.md "Tracker protocol"). A real instrument's CSV export is read by
``station map build --measurements`` (station.cli.map_cmd)."""

from station.drivers.tracker.client import Measurement, TrackerClient, open_tracker, parse_url

__all__ = ["Measurement", "TrackerClient", "open_tracker", "parse_url"]
