"""``station.cli.records_cmd``: how the records tables show times, durations and values."""

from __future__ import annotations

import math

from station.cli.records_cmd import _duration, _human, _mm, _when


def test_durations_times_and_values():
    assert _duration("2026-11-21T08:00:00+00:00", "2026-11-21T08:03:07+00:00") == "3m07s"
    assert _duration("2026-11-21T08:00:00+00:00", None) == "(open)" and _duration("x", "y") == "?"
    assert _when("2026-11-21T08:00:00.123456+00:00") == "2026-11-21 08:00:00"
    assert _mm(0.00012346) == "0.1235" and _mm(None) == "" and _mm(math.nan) == ""
    assert _human(math.radians(0.5), "rad") == "0.5000"  # angles shown in degrees
    assert _human(0.002, "m") == "2.0000"  # lengths in mm
