"""Jog safety and guidance on the emulated CiA 402 arm (real canopen + python-can, the simulated World as
truth): keep-out refusals naming link and obstacle, tool-frame Cartesian jogs, queued steps, a step below
one encoder count refused (Dynamixel, 0.088 deg per count), guidance with limits, and the verdict at close."""

from __future__ import annotations

import numpy as np
import pytest
from station.mocks.world import World

from station.engine.cell import cell_from_dict
from station.engine.journal import read_journal
from station.engine.limits import load_limits
from station.engine.session_record import session_from_journal
from station.tui.controller import JogController
from station.tui.session import session_header, technician_session

START = [0.0, -0.5, 0.5, 0.0, 0.6, 0.0]
HIDDEN = {"offset.j1": 0.0009, "offset.j2": -0.0012, "offset.j3": 0.0010, "offset.j4": 0.0015,
          "offset.j5": -0.0011, "offset.j6": 0.0013}
LIMITS = """format: station-limits/1
version: "test-jog-1"
models:
  arm6:
    jog:
      samples:        {low: 8, unit: count}
      identified:     {low: 4, unit: count}
      fit_rms:        {high: 0.05, unit: mm}
      offset_std_max: {high: 0.02, unit: deg}
"""


@pytest.fixture
def rig(tmp_path, robot_rig):
    made = []

    def make(cell=None, limits=None, time_mode="instant"):
        world = World.default(model="arm6", seed=5, start=START, time_mode=time_mode,
                              errors={"explicit": dict(HIDDEN)})
        emu, robot = robot_rig("canopen", world, query="&heartbeat_ms=250")
        header = session_header(identity=robot.identity(), model_name="arm6", serial="SN-C", identify="offsets",
                                reference="unknown", url=emu.url)
        session = technician_session(robot, header, folder=tmp_path / f"s{len(made)}")
        table, version = {}, None
        if limits is not None:
            f = tmp_path / "limits.yaml"
            f.write_text(limits)
            lim = load_limits(f)
            table, version = lim.for_procedure("arm6", "jog"), lim.version
        ctl = JogController(robot, session, identify="offsets", cell=cell, limits=table, limits_version=version)
        made.append(ctl)
        return world, robot, ctl

    yield make
    for ctl in reversed(made):
        ctl.close()


def test_keep_out_refuses_a_jog_naming_link_and_obstacle(rig):
    world, robot, ctl0 = rig()
    tip = world.nominal.position(np.array(START))
    # a fixture 4 mm below the tool tip's envelope: a 10 mm step down must be refused, nothing sent
    cell = cell_from_dict({"format": "station-cell/1", "units": {"length": "m"},
                           "points": [{"label": "A", "position": [0.4, 0, 0.05]}],
                           "keep_out": [{"name": "fixture", "box": {"min": [tip[0] - 0.05, tip[1] - 0.05, 0.0],
                                                                    "max": [tip[0] + 0.05, tip[1] + 0.05,
                                                                            tip[2] - 0.03]},
                                         "clearance": 0.0}]})
    ctl0.close()
    ctl = JogController(robot, technician_session(
        robot, session_header(identity=robot.identity(), model_name="arm6", serial="SN-C", identify="offsets",
                              reference="unknown", url="x"),
        folder=ctl0.session.folder.parent / "ko"), identify="offsets", cell=cell)
    try:
        ctl.toggle_mode()
        ctl.set_step(3)  # 10 mm
        q0 = world.encoder_q().copy()
        for _ in range(3):  # 30 mm down: the first steps are clear, then the tool would enter the fixture
            if not ctl.jog(2, -1):
                break
            robot.move_joints(ctl.last_jog["target"], speed=0.5)  # instant world: done
        assert ctl.message.startswith("refused:") and "fixture" in ctl.message, ctl.message
        assert "tool" in ctl.message or "link" in ctl.message
        q_before = world.encoder_q().copy()
        assert not ctl.jog(2, -1)
        np.testing.assert_array_equal(world.encoder_q(), q_before)  # nothing was sent
        assert np.any(q_before != q0)  # the clear steps did move
        # the true tip never came within the fixture's top
        assert world.truth.position(q_before)[2] > tip[2] - 0.03
    finally:
        ctl.close()


def test_tool_frame_cartesian_jog_moves_along_the_tool_axis(rig):
    world, robot, ctl = rig()
    ctl.toggle_mode()
    ctl.toggle_frame()
    ctl.set_step(2)  # 1 mm
    T0 = world.nominal.fk(world.encoder_q())
    assert ctl.jog(0, +1)  # tool X +1 mm
    T1 = world.nominal.fk(world.encoder_q())
    np.testing.assert_allclose(T1[:3, 3] - T0[:3, 3], T0[:3, 0] * 1e-3, atol=3e-6)
    np.testing.assert_allclose(T1[:3, :3], T0[:3, :3], atol=3e-5)
    assert abs(T0[2, 0]) > 0.1 or abs(T0[1, 0]) > 0.1  # the tool x axis is not the base x axis here
    # rotation about the tool's own z axis keeps the TCP where it is
    assert ctl.jog(5, +1)  # 1 deg
    T2 = world.nominal.fk(world.encoder_q())
    np.testing.assert_allclose(T2[:3, 3], T1[:3, 3], atol=3e-6)
    np.testing.assert_allclose(T2[:3, 2], T1[:3, 2], atol=3e-5)


def test_a_step_pressed_during_motion_is_queued_not_dropped(rig):
    world, robot, ctl = rig(time_mode="realtime")
    ctl.set_step(2)  # 1 deg
    ctl.change_speed(-3)  # 1 %: 2.5 mm/s, a slow step
    q0 = world.encoder_q().copy()
    assert ctl.jog(0, +1)
    import time

    time.sleep(0.1)
    assert robot.status().moving
    assert ctl.jog(0, +1)  # pressed while moving: extends the move by one step
    np.testing.assert_allclose(ctl.last_jog["target"][0] - q0[0], np.deg2rad(2.0), atol=1e-4)
    # a held step key (terminal repeats): at most one step queued, so release does not leave travel behind
    assert not ctl.jog(0, +1) and "queued" in ctl.message
    np.testing.assert_allclose(ctl.last_jog["target"][0] - q0[0], np.deg2rad(2.0), atol=1e-4)
    robot.stop()


def test_guidance_and_verdict_against_jog_limits(rig):
    world, robot, ctl = rig(limits=LIMITS)
    assert ctl.guide.status == "waiting" and ctl.guide.needed == 8
    rng = np.random.default_rng(1)
    target = world.points["N"].position
    statuses = []
    n = 0
    while n < 14:
        q0 = np.array(START) + rng.uniform(-1, 1, 6) * np.array([0.3, 0.3, 0.3, 1.3, 0.9, 1.3])
        r = world.truth.ik(target, q0, position_only=True)
        if not (r.ok[0] and world.truth.within_limits(r.q[0], 0.05)[0]):
            continue
        robot.move_joints(r.q[0], speed=1.0)
        assert ctl.record(point="N") is not None, ctl.message
        n += 1
        statuses.append(ctl.guide.status)
    assert statuses[0] == "not yet" and statuses[-1] == "good enough", statuses
    assert all(s == "not yet" for s in statuses[:7])  # fewer samples than the limit: never good enough
    checks = {c.name: c for c in ctl.guide.checks}
    assert checks["samples"].ok and checks["offset_std_max"].ok
    # the indicator's sigma is honest against the hidden truth: every identified offset within 4 sigma
    for name, p in ctl.solve_state.result.parameters.items():
        if name.startswith("offset.") and p.identifiable:
            sd = max(p.std, ctl.predicted.get(name) or 0.0)
            assert abs(p.value - HIDDEN[name]) <= 4 * sd + 2e-5, (name, p.value, HIDDEN[name], sd)
    folder = ctl.session.folder
    ctl.close()
    assert ctl.verdict_text == "PASS"
    rec = session_from_journal(folder)
    assert rec["verdict"]["passed"] is True and rec["verdict"].get("status") is None
    assert [m["name"] for m in rec["verdict"]["measurements"] if m.get("low") is not None or m.get("high")
            is not None] == ["samples", "forced_samples", "identified", "fit_rms", "offset_std_max"]
    # no sample was forced: the built-in rule (a forced sample is no touch) passes with 0
    forced = {m["name"]: m for m in rec["verdict"]["measurements"]}["forced_samples"]
    assert forced["value"] == 0 and forced["high"] == 0 and forced["passed"]


def test_a_jog_session_without_limits_ends_no_limits(rig):
    world, robot, ctl = rig()
    robot.move_joints(np.array(START) + 0.05, speed=1.0)
    ctl.record(force=True)
    folder = ctl.session.folder
    assert ctl.guide.status == "NO LIMITS"
    ctl.close()
    assert ctl.verdict_text == "NO LIMITS"
    _, events = read_journal(folder / "journal.jsonl")
    v = [e for e in events if e["type"] == "verdict"][-1]
    assert v["passed"] is None and v["status"] == "NO LIMITS"
    from station.records import overall_status

    assert overall_status(session_from_journal(folder)["verdict"]) == "NO LIMITS"


def test_a_step_below_one_encoder_count_is_refused(tmp_path, robot_rig):
    world = World.default(model="omx", seed=2, start=[0.2, -0.3, 0.4, 0.1])
    _, robot = robot_rig("dynamixel", world, ids=[11, 12, 13, 14])
    header = session_header(identity=robot.identity(), model_name="omx", serial="OMX", identify="offsets",
                            reference="unknown", url="x")
    ctl = JogController(robot, technician_session(robot, header, folder=tmp_path / "s"), identify="offsets")
    q0 = world.encoder_q().copy()
    ctl.set_step(0)  # 0.01 deg < 0.088 deg per count
    assert not ctl.jog(1, +1)
    assert "below one encoder count" in ctl.message and "0.08789 deg" in ctl.message, ctl.message
    ctl.set_step(1)  # 0.1 deg: more than one count, moves
    assert ctl.jog(1, +1)
    ctl.toggle_mode()
    ctl.set_step(0)  # 0.01 mm at the tool moves no joint by a count
    assert not ctl.jog(0, +1) and "encoder count" in ctl.message
    ctl.close()
    assert np.abs(world.encoder_q() - q0)[[0, 2, 3]].max() == 0


def _hold_and_release(world, ctl, axis: int, direction: int, seconds: float) -> tuple[float, float]:
    """Key events every 35 ms (a terminal's repeats) for ``seconds``, the UI's tick in between; then no more
    events. Returns (tool travel during the hold in m, time from the last event to standstill in s)."""
    import time

    from station.tui.controller import HOLD_TICK_S

    p0 = world.truth.position(world.encoder_q()[None])[0]
    t0 = time.monotonic()
    next_key = t0
    while time.monotonic() - t0 < seconds:
        now = time.monotonic()
        if now >= next_key:
            ctl.hold(axis, direction)
            next_key = now + 0.035
        ctl.hold_tick()
        time.sleep(0.01)
    t_last = next_key - 0.035
    p1 = world.truth.position(world.encoder_q()[None])[0]
    last_q, last_change = world.encoder_q(), time.monotonic()
    while time.monotonic() - last_change < 0.2:
        ctl.hold_tick()
        time.sleep(HOLD_TICK_S / 5)
        q = world.encoder_q()
        if np.any(q != last_q):
            last_q, last_change = q, time.monotonic()
    return float(np.linalg.norm(p1 - p0)), last_change - t_last


@pytest.mark.exclusive  # stop-after-release timing: run alone (make test)
@pytest.mark.parametrize("mode,axis", [("joint", 1), ("cartesian", 0)])
def test_hold_to_run_on_canopen(rig, mode, axis):
    from station.tui.controller import HOLD_WATCHDOG_S

    world, robot, ctl = rig(time_mode="realtime")
    if mode == "cartesian":
        ctl.toggle_mode()
    ctl.set_continuous()
    ctl.change_speed(+1)  # 25 %: 62.5 mm/s at the tool
    travel, delay = _hold_and_release(world, ctl, axis, -1, 1.0)
    print(f"canopen hold-to-run {mode}: {travel * 1e3:.1f} mm in 1.0 s at {ctl.speed_mm_s:g} mm/s, "
          f"standstill {delay * 1e3:.0f} ms after the last key event")
    assert ctl.speed_mm_s == 62.5
    assert 0.3 * 62.5e-3 < travel < 1.1 * 62.5e-3 * 1.0  # moving at (not above) the override
    assert delay < HOLD_WATCHDOG_S + 0.1, delay  # margin: the realtime world's decel on a loaded host
    assert not robot.status().moving


def test_hold_release_adapts_to_the_terminals_key_repeat(rig):
    """Without key-release events the release is inferred from the autorepeat: the UI measures the repeat
    interval and delay of this terminal (the key-event times are the ground truth, on the controller's
    injected clock) and takes a gap of 2.5 intervals as the release, never more than the 0.1 s UR watchdog
    period; the first press keeps the arm moving through the repeat delay."""
    from station.tui.controller import HOLD_FIRST_S, HOLD_RELEASE_S

    world, robot, ctl = rig()
    ctl.set_continuous()
    # nothing measured yet: a press holds for the longest repeat delay, then stops
    assert ctl.hold(1, -1, now=0.0)
    assert not ctl.hold_check(HOLD_FIRST_S - 0.01) and ctl.hold_state is not None
    assert ctl.hold_check(HOLD_FIRST_S + 0.001) and ctl.hold_state is None
    # a held key: press, 300 ms repeat delay, then a repeat every 30 ms
    t = 10.0
    assert ctl.hold(1, -1, now=t)
    assert not ctl.hold_check(t + 0.29)  # waiting for the first repeat does not stop the arm
    events = [t + 0.3 + 0.03 * k for k in range(12)]
    for e in events:
        assert ctl.hold(1, -1, now=e)
        assert not ctl.hold_check(e + 0.02)
    last = events[-1]
    assert ctl.release_gap() == pytest.approx(2.5 * 0.03)
    assert not ctl.hold_check(last + 0.074)
    assert ctl.hold_check(last + 0.076)  # released 75 ms after the last repeat
    assert ctl.repeat_delay == pytest.approx(0.3)
    # the next press: the first window is the measured delay + a quarter, not the 0.6 s default
    t = 20.0
    assert ctl.hold(1, -1, now=t)
    assert not ctl.hold_check(t + 0.37)
    assert ctl.hold_check(t + 0.376)
    # a slow repeat (60 ms): the gap is capped at the watchdog period, never longer
    t = 30.0
    assert ctl.hold(1, -1, now=t)
    for k in range(20):
        ctl.hold(1, -1, now=t + 0.3 + 0.06 * k)
    assert ctl.release_gap() == HOLD_RELEASE_S == 0.1
    # a double tap (second press 150 ms after the first, then nothing) is not taken as a repeat delay
    ctl.stop_hold()
    ctl.repeat_delay = None
    ctl.hold(1, -1, now=40.0)
    ctl.hold(1, -1, now=40.15)
    assert ctl.hold_check(40.15 + 0.101) and ctl.repeat_delay is None
    robot.stop()


def test_hold_reads_key_times_from_the_terminal_input_thread(rig):
    """A UI busy in a robot call sees key events late and in bunches. The release is inferred from when the
    terminal input thread received them (station.tui.keys.KeyArrivals, fed here by hand on an injected
    clock): queued repeats keep the hold alive, a resumed hold teaches no repeat delay, and a repeat that
    arrived before the release but is read after it does not start the arm again."""
    from station.tui.keys import KeyArrivals

    world, robot, ctl = rig()
    ctl.set_continuous()
    arrivals = KeyArrivals()
    ctl.key_arrivals = lambda axis, d, count: arrivals.since("w" if d > 0 else "s", count)
    t = 10.0
    arrivals.note("s", t)
    assert ctl.hold(1, -1, now=t + 0.05)  # the press, read 50 ms late: its window counts from its arrival
    assert ctl.hold_state["started"] == t
    for k in range(12):
        arrivals.note("s", t + 0.3 + 0.03 * k)
    last = t + 0.3 + 0.03 * 11
    # the UI was stuck for 0.4 s and reads the repeats only now: not a release, the hold goes on
    assert not ctl.hold_check(last + 0.02) and ctl.hold_state is not None
    assert ctl.repeat_delay == pytest.approx(0.3) and ctl.release_gap() == pytest.approx(0.075)
    for _ in range(12):  # the queued events themselves: already counted
        assert ctl.hold(1, -1, now=last + 0.03)
    assert ctl.hold_check(last + 0.076) and ctl.hold_state is None  # 75 ms after the last arrival
    # a repeat read after that stop, which had arrived before it: the key is not held any more
    assert not ctl.hold(1, -1, now=last + 0.08) and ctl.hold_state is None
    # the key still held after a stop: new arrivals resume it; the first gap of a resumed hold (a late repeat,
    # 100 ms, then the 30 ms cadence) is shorter than any terminal's repeat delay: not learned as one
    t = 20.0
    for dt in (0.0, 0.1, 0.13, 0.16):
        arrivals.note("s", t + dt)
    assert ctl.hold(1, -1, now=t + 0.17) and ctl.hold_state is not None
    assert ctl.repeat_delay == pytest.approx(0.3)
    ctl.stop_hold()
    # a tap whose release the input thread handles before the UI reads the press: the press must not start
    # the arm after the key came up
    arrivals.note("s", 30.0)
    ctl.release(1, -1)
    assert not ctl.hold(1, -1, now=30.2) and ctl.hold_state is None
    robot.stop()


def test_a_reported_key_release_stops_at_once(rig):
    world, robot, ctl = rig()
    ctl.set_continuous()
    assert ctl.hold(0, +1)
    ctl.release(0, -1)  # another key's release: still held
    assert ctl.hold_state is not None
    ctl.release(0, +1)
    assert ctl.hold_state is None and ctl.release_events and "released" in ctl.message


def test_shipped_limits_have_a_jog_section_that_judges_jog_sessions(rig):
    """The shipped limits.yaml's ``jog`` section (read by the same reader as every procedure's) is what
    `station jog` judges by default: a few touches are NOT YET and end FAIL, never PASS or NO LIMITS."""
    from station.engine.limits import default_limits, load_limits

    lim = load_limits()
    for model in ("arm6", "ur5e", "omx", "scara"):
        table = lim.for_procedure(model, "jog")
        assert {"samples", "fit_rms", "offset_std_max"} <= set(table), model
        assert table["samples"].low >= 12
    assert lim.for_procedure("omx", "jog")["fit_rms"].high > lim.for_procedure("ur5e", "jog")["fit_rms"].high
    world, robot, ctl = rig(limits=default_limits().read_text())
    assert ctl.limits and ctl.guide.needed == 12
    for dq in (0.05, -0.05, 0.1):
        robot.move_joints(np.array(START) + dq, speed=1.0)
        assert ctl.record(force=True) is not None, ctl.message
    assert ctl.guide.status == "not yet"
    assert not {c.name: c for c in ctl.guide.checks}["samples"].ok
    ctl.close()
    assert ctl.verdict_text == "FAIL"


@pytest.mark.exclusive  # a realtime hold: run alone (make test)
def test_held_cartesian_rotation_turns_at_the_overrides_share(rig):
    """A held Rz turns the true tool at the override's share of 30 deg/s (50 %: 15 deg/s; 10 %: at most
    3 deg/s), measured on the world's true orientation between 0.3 s and 0.8 s of the hold."""
    import time

    from station.kinematics import se3

    world, robot, ctl = rig(time_mode="realtime")
    ctl.toggle_mode()
    ctl.set_continuous()
    rates = {}
    for percent, clicks in ((10, 0), (50, 2)):
        ctl.change_speed(clicks)
        assert ctl.speed_percent == percent
        log = []
        t0 = time.monotonic()
        while not log or log[-1][0] <= 0.85:  # by the samples taken, not the clock: a slow tick must not cut it
            now = time.monotonic()
            ctl.hold(5, +1 if percent == 10 else -1, now)
            ctl.hold_tick(now)
            log.append((now - t0, world.truth.fk(world.encoder_q())[:3, :3]))
            time.sleep(0.03)
        ctl.stop_hold()
        assert log[-1][0] > 0.8, (len(log), log[-1][0], ctl.message)
        (ta, Ra), (tb, Rb) = next(x for x in log if x[0] > 0.3), next(x for x in log if x[0] > 0.8)
        angle = np.linalg.norm(se3.matrix_to_rotvec(Ra.T @ Rb))
        rates[percent] = np.rad2deg(angle / (tb - ta))
        time.sleep(0.3)
    print(f"held Rz: {rates[10]:.2f} deg/s at 10 %, {rates[50]:.2f} deg/s at 50 % (expected 3 and 15)")
    assert rates[50] == pytest.approx(15.0, rel=0.25)
    # at 10 % never faster than 3 deg/s, and clearly scaled down (measured 1.2-1.5 deg/s on a loaded host: the
    # short position targets of a slow hold lose time to the drives' profiles; see docs/jog.md)
    assert 0 < rates[10] <= 3.0 * 1.25 and rates[50] / rates[10] > 3
