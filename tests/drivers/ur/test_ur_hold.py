"""Hold-to-run on a UR: the driver's velocity jog (speedJ/speedL under the controller's RTDE watchdog) through
the real ur_rtde client against the UR emulator process. Truth is the world: tool positions come from the
world's true model at the joints the controller reports, times from the controller's own clock (the
emulator's 2 ms cycle drives the world), so a loaded machine slows the world, not the measured speed."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import yaml
from station.mocks.world import World, default_doc

from station.robot import open_robot
from station.robot.capabilities import VelocityJog
from station.tui.controller import HOLD_RELEASE_S, HOLD_TICK_S, JogController
from tests.tui.test_tui_ur import jog_controller

pytestmark = pytest.mark.exclusive  # timing on the wire: run alone, not next to another test (make test)

START = [0.1, -1.45, 1.6, -1.72, -1.5708, 0.2]
WATCHDOG_S = 0.1  # the driver's default jog_watchdog = 10 Hz
TICK_S = 0.002  # the emulated controller's cycle
CAP = 0.25  # m/s: manual jog tool-speed cap
BRAKE_S = 0.015  # 0.2 rad/s braked at the world's 13.96 rad/s^2 joint acceleration limit (14 ms)
SEEN_S = 0.03  # observing standstill: RTDE receive polling and the emulator's tick loop (the test runs alone)


def world_file(tmp_path):
    doc = default_doc("ur5e", seed=11)
    doc["motion"].update(time_mode="sim", start=list(START))
    doc["buses"] = {"ur": {"serial": "20235500011"}}
    path = tmp_path / "world.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path, World.from_file(path)


@pytest.fixture
def ur(tmp_path, emulators):
    path, world = world_file(tmp_path)
    emu = emulators("ur", path)
    robot = open_robot(emu.url)
    try:
        robot.enable()
        yield emu, robot, world
    finally:
        robot.close()


def controller(robot, tmp_path) -> JogController:
    return jog_controller(robot, tmp_path / "s", serial="20235500011")


def sample(robot, world):
    s = robot.joint_positions()
    return s.t_device, world.truth.position(s.q), s.q


def wait_still(robot, timeout=5.0) -> None:
    end = time.monotonic() + timeout
    while robot.status().moving:
        assert time.monotonic() < end, "still moving"
        time.sleep(0.002)


class Observer:
    """An independent RTDE client sampling the controller's clock and joints every ~2 ms in a thread: when the
    arm stood still is read from the controller, not from this process's status reads (on a busy host the
    station's own stop call and reads lag the controller, and that lag is not the arm moving)."""

    def __init__(self, host: str):
        import rtde_receive

        self.recv = rtde_receive.RTDEReceiveInterface(host)
        self.seen: list[tuple[float, np.ndarray]] = []
        self._on = threading.Event()
        self._on.set()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while self._on.is_set():
            self.seen.append((self.recv.getTimestamp(), np.array(self.recv.getActualQ())))
            time.sleep(0.002)

    def close(self) -> None:
        self._on.clear()
        self._thread.join(5)
        self.recv.disconnect()

    def standstill_after(self, t0: float) -> tuple[float, np.ndarray]:
        """Controller time of the first sample after ``t0`` from which the joints no longer move, and where."""
        seen = [(t, q) for t, q in self.seen if t >= t0]
        q_end = seen[-1][1]
        moved = [k for k, (_, q) in enumerate(seen) if np.max(np.abs(q - q_end)) > 1e-7]
        return (seen[moved[-1] + 1][0] if moved else seen[0][0]), q_end


@pytest.mark.timeout(120)
def test_hold_moves_at_override_and_stops_on_release(ur, tmp_path):
    """Hold +x for ~1 s at the 25 mm/s override: the true tool moves straight at 25 mm/s (controller time),
    and stands still within one watchdog period + one controller tick after the UI sees the release."""
    emu, robot, world = ur
    assert isinstance(robot, VelocityJog)
    observer = Observer(emu.host)
    ctl = controller(robot, tmp_path)
    try:
        ctl.set_continuous()
        assert ctl.continuous and ctl.speed_mm_s == pytest.approx(25.0)
        if ctl.mode != "cartesian":
            ctl.toggle_mode()
        t0, p0, _ = sample(robot, world)
        log = [(t0, p0)]
        start = time.monotonic()
        next_key = next_tick = start
        while time.monotonic() - start < 1.0:  # the terminal repeats the key every 35 ms, the UI ticks every 50
            now = time.monotonic()
            if now >= next_key:
                assert ctl.hold(0, +1, now), ctl.message
                next_key += 0.035
            if now >= next_tick:
                ctl.hold_tick(now)
                next_tick += HOLD_TICK_S
            with ctl.io_lock:
                t, p, _ = sample(robot, world)
            log.append((t, p))
            time.sleep(0.005)
        assert ctl.hold_state is not None and "velocity" in ctl.last_jog
        last_key = next_key - 0.035
        # key released: the next tick past HOLD_RELEASE_S stops the arm
        while ctl.hold_state is not None:
            time.sleep(0.005)
            if time.monotonic() >= last_key + HOLD_RELEASE_S:
                t_rel, p_rel, _ = sample(robot, world)
                ctl.hold_tick()
        assert ctl.hold_state is None and "released" in ctl.message
        wait_still(robot)
        time.sleep(0.05)  # the observer's last samples, standing
    finally:
        observer.close()
        ctl.close()
    t_still, q_end = observer.standstill_after(t_rel)
    p_still = world.truth.position(q_end)
    ts = np.array([t for t, _ in log])
    ps = np.array([p for _, p in log])
    keep = np.r_[True, np.diff(ts) > 0]
    ts, ps = ts[keep], ps[keep]
    steady = ts > ts[0] + 0.1  # after the 0.5 m/s^2 ramp (50 ms)
    i, j = np.flatnonzero(steady)[[0, -1]]
    v = (ps[j] - ps[i]) / (ts[j] - ts[i])
    seg = np.linalg.norm(np.diff(ps, axis=0), axis=1) / np.diff(ts)
    print(f"\nhold 25 mm/s: true tool {v * 1e3} mm/s, peak {seg.max() * 1e3:.2f} mm/s (x from the UI loop samples),"
          f" standstill {(t_still - t_rel) * 1e3:.0f} ms (controller) after release, travel after it "
          f"{np.linalg.norm(p_still - p_rel) * 1e3:.2f} mm")
    assert v[0] == pytest.approx(0.025, rel=0.03), v  # commanded speed along base x (nominal model drives it)
    assert np.linalg.norm(v[1:]) < 0.025 * 0.03, v  # straight along x
    assert seg.max() < min(CAP, 0.025 * 1.1), seg.max()  # never above the override, far below 250 mm/s
    assert t_still - t_rel <= WATCHDOG_S + TICK_S, t_still - t_rel  # standstill after release (controller s)
    assert np.linalg.norm(p_still - p_rel) <= 0.025 * (WATCHDOG_S + TICK_S)


@pytest.mark.timeout(120)
def test_velocity_jog_is_capped_and_stops_without_refresh(ur):
    """A request far above the manual limits is scaled down (tool <= 250 mm/s, joints <= model limits); a
    jog that is not re-sent is stopped by the controller's watchdog within its period."""
    emu, robot, world = ur
    for mode, axis, velocity in (("cartesian", 0, 2.0), ("joint", 0, 5.0), ("cartesian", 2, -1.0)):
        log = []
        start = time.monotonic()
        while time.monotonic() - start < 0.4:
            robot.jog_velocity(mode, axis, velocity)
            t, p, q = sample(robot, world)
            log.append((t, p, q))
            time.sleep(0.02)
        robot.stop()
        wait_still(robot)
        ts = np.array([x[0] for x in log])
        keep = np.r_[True, np.diff(ts) > 0]
        ps = np.array([x[1] for x in log])[keep]
        qs = np.array([x[2] for x in log])[keep]
        ts = ts[keep]
        tool = np.linalg.norm(np.diff(ps, axis=0), axis=1) / np.diff(ts)
        joint = np.abs(np.diff(qs, axis=0)) / np.diff(ts)[:, None]
        print(f"\n{mode} axis {axis} asked {velocity}: tool peak {tool.max() * 1e3:.1f} mm/s, joint peak "
              f"{joint.max():.3f} rad/s")
        assert tool.max() <= CAP * 1.02, (mode, tool.max())
        assert tool.max() > 0.02, (mode, tool.max())  # it did move
        assert np.all(joint <= robot.model.max_velocity * 1.02)
    # one command, no refresh: the watchdog (not the station) stops it
    observer = Observer(emu.host)
    try:
        robot.jog_velocity("joint", 0, 0.2)
        sent = time.monotonic()
        t_sent = robot.joint_positions().t_device
        time.sleep(0.03)
        assert robot.status().moving
        while robot.status().moving:
            assert time.monotonic() - sent < 2.0, "the watchdog did not stop the arm"
            time.sleep(0.002)
        time.sleep(0.05)  # the observer's last samples, standing
    finally:
        observer.close()
    t_still, _ = observer.standstill_after(t_sent)
    print(f"\nno refresh: standstill {(t_still - t_sent) * 1e3:.0f} ms (controller) after the command")
    assert "RTDE watchdog expired" in emu.dashboard("emulator log")  # the controller stopped it, not us
    assert t_still - t_sent <= WATCHDOG_S + BRAKE_S + TICK_S + SEEN_S, t_still - t_sent


HOLDER = """
import sys, time
from station.robot import open_robot
robot = open_robot(sys.argv[1])
robot.enable()
start = time.monotonic()
said = False
while True:
    robot.jog_velocity("joint", 0, 0.2)
    if not said and time.monotonic() - start > 0.3:
        print("holding", flush=True)
        said = True
    time.sleep(0.04)
"""


@pytest.mark.timeout(120)
def test_station_killed_mid_hold_controller_stops_arm(tmp_path, emulators):
    """The station process dies (SIGKILL) mid-hold: nothing sends a stop, the controller's RTDE watchdog ends
    the program and the arm stands still within the watchdog period (read by an independent RTDE client)."""
    import rtde_receive

    path, _ = world_file(tmp_path)
    emu = emulators("ur", path)
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, emu.url], stdout=subprocess.PIPE, text=True,
                            env=dict(os.environ))
    try:
        assert proc.stdout.readline().strip() == "holding"
        recv = rtde_receive.RTDEReceiveInterface(emu.host)
        try:
            assert abs(recv.getActualQd()[0]) > 0.1
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(10)
            killed = time.monotonic()
            t_kill = recv.getTimestamp()
            while any(abs(v) > 1e-6 for v in recv.getActualQd()):
                assert time.monotonic() - killed < 3.0, "the arm kept moving after the station died"
                time.sleep(0.002)
            t_still = recv.getTimestamp()
            wall = time.monotonic() - killed
        finally:
            recv.disconnect()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    # the last command went out at most ~40 ms before the kill: standstill within one watchdog period of it
    print(f"\nSIGKILL mid-hold: standstill {(t_still - t_kill) * 1e3:.0f} ms (controller), {wall * 1e3:.0f} ms (wall)")
    assert "RTDE watchdog expired" in emu.dashboard("emulator log")
    assert t_still - t_kill <= WATCHDOG_S + BRAKE_S + TICK_S + SEEN_S, (t_still - t_kill, wall)
