"""The operator's words for what ended a unit (``station.panel.reasons``), from errors the station's own code
raises: the serial check, a robot port that cannot be opened, an abort. The words never carry the driver's text
(that goes to ``detail``), the action names RESUME only when the session can continue, and the cause picks the
line's status code (docs/opcua.md). Failing limits read in the operator's names and units."""

from __future__ import annotations

import pytest

from station.engine.runner import Aborted
from station.panel.reasons import explain, plain_failure, where
from station.robot import Identity, StationError, adopt_serial, open_robot


def _raised(fn) -> BaseException:
    with pytest.raises(BaseException) as e:
        fn()
    return e.value


def test_reasons_of_errors_the_station_raises(tmp_path):
    ident = Identity(vendor="v", model="ur5e", serial="20235500000", serial_source="robot")
    wrong = explain(_raised(lambda: adopt_serial(ident, "WRONG-SN")), serial="WRONG-SN")
    assert wrong.text == "The unit in the cell is not WRONG-SN: the robot reports serial 20235500000."
    assert wrong.kind == "serial" and "Scan the label" in wrong.action and "SerialMismatch" in wrong.detail

    port = tmp_path / "ttyUSB-gone"
    err = _raised(lambda: open_robot(f"dynamixel://{port}?model=omx").identity())
    assert isinstance(err, StationError)
    never = explain(err, reached=False)  # refused at connect: nothing to resume
    assert never.text == "The station cannot reach the robot." and "press TRY AGAIN" in never.action
    for resumable, go in ((True, "press RESUME"), (False, "press TRY AGAIN")):  # the same fault mid-run
        r = explain(err, resumable=resumable)
        assert r.kind == "robot" and go in r.action and "RESUME" not in r.action.replace(go, "")
    for r in (never, explain(err, resumable=True)):  # the driver's text only in the technician's line
        assert str(port) not in r.text + r.action and str(port) in r.detail
        assert r.detail.startswith(type(err).__name__ + ": ")

    stopped = explain(Aborted("aborted by the operator; the robot was stopped during approach of pose 3"),
                      resumable=True)
    assert stopped.kind == "operator" and stopped.text.startswith("Aborted by the operator") and \
        "RESUME" in stopped.action
    assert explain(ValueError("x"), resumable=False).kind == "station"


def test_failing_limits_and_progress_in_operator_words():
    assert plain_failure({"name": "fit_rms", "value": 0.0123, "unit": "mm", "high": 0.001}) == \
        "Fit error (rms): 0.0123 mm, above the limit of 0.001 mm"
    assert plain_failure({"name": "samples", "value": 10, "unit": "count", "low": 12}) == \
        "Points measured: 10, below the limit of 12"
    # a limits file in SI still reads in degrees and mm
    assert plain_failure({"name": "offset_abs_max", "value": 0.05, "unit": "rad", "high": 0.0349066}) == \
        "Largest zero offset: 2.865 deg, above the limit of 2 deg"
    assert plain_failure({"name": "holdout_max", "value": 4e-4, "unit": "m", "high": 3e-4}) == \
        "Largest check-point error: 0.4 mm, above the limit of 0.3 mm"
    assert where(4, 14) == "Stopped after 4 of 14 points; all 4 are kept."
    assert where(0, 14) == "Stopped before the first of 14 points was measured."
    assert where(0, 0) == "Stopped before the robot measured anything."
