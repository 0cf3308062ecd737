"""``station.drivers.franka.limits``: the FR3 position-dependent velocity envelope against the constants libfranka
publishes (rate_limiting.h: ``sqrt(K * (q_max - q))`` with K = 12.0, 5.17, 7.0, 8.0, 34.0, 11.0, 34.0)."""

from __future__ import annotations

import numpy as np
import pytest
from station.drivers.franka.limits import DECEL, DQ_MAX, Q_MAX, Q_MIN, TOLERANCE, V_OFFSET, velocity_envelope


def test_the_envelope_uses_libfrankas_constants():
    assert pytest.approx([12.0, 5.17, 7.0, 8.0, 34.0, 11.0, 34.0]) == 2 * DECEL


def test_the_envelope_at_the_centre_and_at_the_ends():
    mid = (Q_MIN + Q_MAX) / 2
    lo, up = velocity_envelope(mid)
    expect = np.minimum(DQ_MAX, -V_OFFSET + np.sqrt(2 * DECEL * (Q_MAX - mid)))
    assert np.allclose(up, expect - TOLERANCE) and np.allclose(lo, -expect + TOLERANCE)  # symmetric range
    lo, up = velocity_envelope(Q_MAX)
    assert (up < 0).all() and (up == -TOLERANCE).all()  # at the upper end: it may only move away from it
    lo, up = velocity_envelope(Q_MIN)
    assert (lo == TOLERANCE).all()
    # a joint can always stop before its limit: v <= sqrt(2 a d) at every distance d
    q = Q_MAX[None, :] - np.linspace(0, 0.5, 50)[:, None]
    _, up = velocity_envelope(q)
    assert (up <= np.sqrt(2 * DECEL * (Q_MAX - q)) + 1e-12).all()
    assert velocity_envelope(np.zeros((3, 7)))[1].shape == (3, 7)
