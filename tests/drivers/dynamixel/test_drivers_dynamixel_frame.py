"""``station.drivers.dynamixel.frame``: Present/Goal Position (the servo's frame, e-Manual: ``Present = Actual +
Homing Offset``, reverse mode turning positions but not the offset, readings reset to within one turn) <-> the
joint reading, for every drive mode, offset and turn the servo may report."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from station.drivers.dynamixel import table as T
from station.drivers.dynamixel.frame import ServoFrame, describe_mode, time_profile

from station.kinematics import load_model

OMX = load_model("omx")


def frame(i, sign=1, offset=0, mode=T.MODE_POSITION):
    j = OMX.joints[i]
    return ServoFrame(j.encoder, OMX.lower[i], OMX.upper[i], sign=sign, stored_offset=offset, mode=mode)


@pytest.mark.parametrize("sign, offset, mode", list(itertools.product([1, -1], [0, 300, -1000, 3000],
                                                                         [T.MODE_POSITION, T.MODE_EXTENDED_POSITION])))
def test_every_reported_turn_unwraps_to_the_joint(sign, offset, mode):
    f = frame(1, sign, offset, mode)
    applied = 0 if (mode == T.MODE_POSITION and abs(offset) > 1024) else offset  # e-Manual: ignored beyond 1024
    assert f.offset == applied
    lo, hi = f.count_range()
    for q in np.linspace(OMX.lower[1], OMX.upper[1], 7):
        c = f.to_reading(q) - sign * applied  # the joint's counts without the offset, model direction
        for k in (-2, 0, 1):
            present = sign * c + T.ONE_TURN * k + applied  # what the servo reports after a reset to turn k
            L = f.reading(present)
            assert c + sign * applied == L and lo - 1 <= L <= hi + 1
            assert f.goal(L) == present  # the goal in the turn the servo is in now
            assert abs(f.to_si(L) - q) < 1e-2  # one tick


def test_offsets_in_si_and_mode_limits():
    f = frame(0, sign=-1)
    ticks = f.offset_from_si(0.01)  # 0.01 rad, stored in the servo's (reversed) frame
    assert ticks == -round(0.01 * 4096 / (2 * np.pi))
    assert f.offset_si(ticks * f.sign) == pytest.approx(0.01, abs=2 * np.pi / 4096)  # within one tick
    assert frame(0).offset_limit() == 1024 and frame(0, mode=T.MODE_EXTENDED_POSITION).offset_limit() == 1_044_479
    assert frame(0).span_fits_one_turn()  # omx joints span less than a servo turn
    assert describe_mode(3) == "3 (position control)" and describe_mode(9) == "9 (unknown)"


def test_time_based_profile():
    assert time_profile(1.5, 0.3) == (300, 1500)
    assert time_profile(1.0, 0.9) == (500, 1000)  # acceleration at most half the move, as the servo enforces
    assert time_profile(0.0, 0.0) == (0, 1)
