"""Simulated world, faults: injected faults are consumed exactly once, per device, thread-safe; joint
faults and protective stops halt the robot."""

import threading

import numpy as np
import pytest
from station.mocks.world import FAULT_KINDS, Faults, World


def test_fault_consumed_once():
    f = Faults()
    f.inject("timeout")
    assert not f.take("corrupt")
    assert f.take("timeout", device=3)
    assert not f.take("timeout", device=3)
    assert f.fired == [("timeout", 3)]


def test_fault_device_matching_count_and_after():
    f = Faults()
    f.inject("corrupt", device=12, count=2)
    assert not f.take("corrupt", device=11)
    assert f.peek("corrupt", 12)
    assert f.take("corrupt", device=12) and f.take("corrupt", device="12")  # str/int ids compare equal
    assert not f.take("corrupt", device=12)
    f.inject("disconnect", after=2)
    assert [f.take("disconnect", "hub") for _ in range(4)] == [False, False, True, False]
    f.inject("device_fault", device=2, code=0x20)
    got = f.take_fault("device_fault")  # None device on take matches any armed device
    assert got is not None and got.code == 0x20 and got.device == 2
    f.inject("protective_stop", count=3)
    assert len(f.pending()) == 1 and f.pending()[0].count == 3
    f.clear()
    assert not f.take("protective_stop")


def test_fault_kinds_and_bad_arguments():
    assert set(FAULT_KINDS) == {"timeout", "corrupt", "device_fault", "disconnect", "protective_stop"}
    f = Faults()
    with pytest.raises(ValueError, match="unknown fault kind 'gremlin'"):
        f.inject("gremlin")
    with pytest.raises(ValueError, match="count"):
        f.inject("timeout", count=0)


def test_faults_thread_safe_exact_count():
    f = Faults()
    f.inject("timeout", count=500)
    hits = []

    def worker():
        n = 0
        for _ in range(400):
            n += f.take("timeout", threading.get_ident())
        hits.append(n)

    threads = [threading.Thread(target=worker) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert sum(hits) == 500 and not f.pending()


def test_world_fault_joint_halts_and_disables():
    w = World.default("omx", seed=1, time_mode="sim")
    w.command_q([1.0, 0.5, 0.5, 0.0])
    w.advance(0.2)
    w.fault_joint(2, code=0x04)
    assert w.joint_fault(2) == 0x04
    assert not w.enabled()[2]
    assert w.encoder_qd()[2] == 0.0  # braked at once
    q_fault = w.encoder_q()
    w.run_until_idle()
    q = w.encoder_q()
    assert q[2] == pytest.approx(q_fault[2])
    assert abs(q[0] - 1.0) > 1e-3  # the others decelerated short of their goals
    w.command_q([0, 0, 0, 0])
    w.run_until_idle()
    assert w.encoder_q()[2] == pytest.approx(q_fault[2])  # faulted joint ignores commands
    w.clear_fault(2)
    assert w.joint_fault(2) is None
    w.set_enabled(True, 2)
    w.command_q([0, 0, 0, 0])
    w.run_until_idle()
    np.testing.assert_allclose(w.encoder_q(), 0, atol=1e-12)


def test_protective_stop_refuses_motion_until_cleared():
    w = World.default("ur5e", seed=1, time_mode="sim")
    q0 = w.encoder_q()
    w.command_qd([0.3, 0, 0, 0, 0, 0])
    w.advance(0.5)
    w.protective_stop("test stop")
    assert w.protective_stopped
    w.run_until_idle()
    q_stop = w.encoder_q()
    w.command_q(q0)
    w.run_until_idle()
    np.testing.assert_allclose(w.encoder_q(), q_stop)
    assert any("protective stop" in m for _, m in w.events)
    w.clear_protective_stop()
    w.command_q(q0)
    w.run_until_idle()
    np.testing.assert_allclose(w.encoder_q(), q0, atol=1e-12)


@pytest.mark.exclusive  # realtime world at 50x: a starved thread looks like a race; run alone (make test)
def test_world_is_thread_safe_under_concurrent_use():
    w = World.default("omx", seed=1, time_mode="realtime", time_scale=50.0)
    errors = []

    def commander():
        rng = np.random.default_rng(threading.get_ident() % 1000)
        try:
            for _ in range(200):
                w.command_q(rng.uniform(-0.5, 0.5, 4))
                q = w.encoder_q()
                assert np.all(q >= w.lower - 1e-12) and np.all(q <= w.upper + 1e-12)
                w.contact()
        except Exception as e:  # noqa: BLE001 - collected and asserted below
            errors.append(e)

    threads = [threading.Thread(target=commander) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(20)
    w.halt()
    assert not errors
