"""The emulated controller's cycle on a real World, without sockets: world faults reach the controller, the
control-script register handshake drives the world (fast, deterministic: sim time, one tick = 2 ms)."""

from __future__ import annotations

import threading
import time

import numpy as np
from station.mocks.ur import state as S
from station.mocks.ur.controller import URController
from station.mocks.world import World

SCRIPT = "def rtde_control():\n    global reg_offset_int = 0\nend\n"


def make():
    world = World.default("ur5e", seed=5, time_mode="sim")
    ctl = URController(world)
    drops: list[float] = []
    ctl.on_drop = drops.append
    ctl.drop = lambda seconds: drops.append(seconds)  # run the drop in this thread (no server here)
    power_up(ctl)
    ctl.load_program("rtde_control", SCRIPT)
    return world, ctl, drops


def ticks(ctl: URController, n: int) -> None:
    for _ in range(n):
        ctl.tick()


def power_up(ctl: URController) -> None:
    """Dashboard power on, IDLE, brake release, RUNNING, on the controller's own cycles."""
    ctl.power_on()
    ticks(ctl, round(ctl.power_on_s / 0.002) + 1)
    assert ctl.mode == S.ROBOT_MODE_IDLE
    ctl.brake_release()
    ticks(ctl, round(ctl.brake_release_s / 0.002) + 1)
    assert ctl.mode == S.ROBOT_MODE_RUNNING


def links_truth(world):
    """The world's truth as the factory calibration (default ``links``) knows it: joint zeros, mounting and tool
    as the nominal model has them."""
    return world.truth.with_params({n: world.nominal.param(n) for n in world.truth.param_names
                                    if n.startswith(("offset.", "base.", "tcp."))})


def test_boots_power_off_powers_on_to_idle_then_running_after_brake_release():
    """A controller boots with the arm off; power on takes the joints through POWER_ON to IDLE in (controller)
    seconds, brake release works only in IDLE, and only a RUNNING arm starts a program."""
    world = World.default("ur5e", seed=5, time_mode="sim")
    ctl = URController(world)
    ticks(ctl, 10)
    assert ctl.mode == S.ROBOT_MODE_POWER_OFF and ctl.value("robot_mode") == 3
    assert not ctl.robot_status_bits() & S.RS_POWER_ON
    assert not world.enabled().any() and world.brakes.all()  # held by its brakes
    ctl.load_program("rtde_control", SCRIPT)
    assert ctl.runtime_state == S.STOPPED and "not RUNNING" in ctl.messages[-1]
    ctl.brake_release()  # in POWER_OFF: no effect
    ctl.power_on()
    ticks(ctl, 10)
    assert ctl.mode == S.ROBOT_MODE_POWER_ON and ctl.value("joint_mode") == [247] * 6
    ctl.brake_release()  # still booting: no effect either
    ticks(ctl, round(ctl.power_on_s / 0.002))
    assert ctl.mode == S.ROBOT_MODE_IDLE and ctl.robot_status_bits() & S.RS_POWER_ON
    ticks(ctl, round(ctl.brake_release_s / 0.002) + 5)
    assert ctl.mode == S.ROBOT_MODE_IDLE  # the early brake releases were not remembered
    ctl.load_program("rtde_control", SCRIPT)
    assert ctl.runtime_state == S.STOPPED  # brakes on: no program
    ctl.brake_release()
    ticks(ctl, round(ctl.brake_release_s / 0.002) + 1)
    assert ctl.mode == S.ROBOT_MODE_RUNNING and ctl.value("joint_mode") == [253] * 6 and world.enabled().all()
    ctl.load_program("rtde_control", SCRIPT)
    assert ctl.runtime_state == S.PLAYING


def test_power_cycle_keeps_the_calibration_and_installation_and_loses_the_rest():
    world, ctl, _ = make()
    checksum = ctl.factory.checksum
    command(ctl, S.CMD_SET_TCP, [0, 0, 0.3, 0, 0, 0])
    ticks(ctl, 2)
    world.faults.inject("protective_stop", device="ur")
    ticks(ctl, 1)
    assert ctl.safety_mode == S.SAFETY_PROTECTIVE_STOP
    q = world.encoder_q()
    ctl.power_cycle()
    ticks(ctl, 1)
    assert ctl.mode == S.ROBOT_MODE_POWER_OFF and ctl.runtime_state == S.STOPPED and ctl.program is None
    assert ctl.safety_mode == S.SAFETY_NORMAL and not world.protective_stopped
    assert ctl.factory.checksum == checksum and ctl.in_int[0] == 0 and ctl.out_int[0] == 0
    np.testing.assert_allclose(ctl.tcp, ctl.installation_tcp)  # setTcp was volatile
    np.testing.assert_array_equal(world.encoder_q(), q)  # the arm stays where it is (brakes)


def command(ctl: URController, cmd: int, doubles=(), ints=()) -> None:
    names = ["input_int_register_0"] + [f"input_double_register_{i}" for i in range(len(doubles))]
    names += [f"input_int_register_{i + 1}" for i in range(len(ints))]
    ctl.write_inputs(names, [cmd, *doubles, *ints])


def test_register_handshake_moves_the_world():
    world, ctl, _ = make()
    assert ctl.runtime_state == S.PLAYING and ctl.out_int[0] == S.SCRIPT_READY
    q0 = world.encoder_q()
    target = q0 + 0.1
    command(ctl, S.CMD_MOVEJ, [*target, 1.0, 2.0], [0])  # sync moveJ at 1 rad/s, 2 rad/s^2
    ticks(ctl, 5)
    assert world.is_moving() and ctl.out_int[0] == S.SCRIPT_READY  # still executing: no "done" yet
    ticks(ctl, 300)
    assert ctl.out_int[0] == S.SCRIPT_DONE
    np.testing.assert_allclose(world.encoder_q(), target, atol=1e-12)
    command(ctl, S.CMD_NONE)
    ticks(ctl, 1)
    assert ctl.out_int[0] == S.SCRIPT_READY
    command(ctl, S.CMD_STOP_SCRIPT)
    ticks(ctl, 1)
    assert ctl.runtime_state == S.STOPPED and not ctl.robot_status_bits() & S.RS_PROGRAM_RUNNING


def test_out_of_limit_target_stops_the_program_like_a_script_error():
    world, ctl, _ = make()
    q = world.encoder_q()
    bad = q.copy()
    bad[0] = 8.0
    command(ctl, S.CMD_MOVEJ, [*bad, 1.0, 2.0], [0])
    ticks(ctl, 2)
    assert ctl.runtime_state == S.STOPPED and "outside joint limits" in ctl.messages[-1]
    np.testing.assert_array_equal(world.encoder_q(), q)


def test_world_faults_reach_the_controller():
    world, ctl, drops = make()
    command(ctl, S.CMD_SPEEDJ, [0.1, 0, 0, 0, 0, 0, 1.0, 0.0])
    ticks(ctl, 20)
    assert world.is_moving()
    world.faults.inject("protective_stop", device="ur")
    ticks(ctl, 1)
    assert ctl.safety_mode == S.SAFETY_PROTECTIVE_STOP and ctl.safety_bits & S.SS_PROTECTIVE_STOPPED
    assert ctl.runtime_state == S.PAUSED and world.protective_stopped
    ticks(ctl, 200)
    assert not world.is_moving()
    assert ctl.unlock_protective_stop().startswith("Cannot unlock")  # < 5 s
    ctl.pstop_at -= 5.0
    assert ctl.unlock_protective_stop() == "Protective stop releasing" and not world.protective_stopped
    world.faults.inject("timeout", device="ur")
    world.faults.inject("disconnect", device="ur")
    ticks(ctl, 1)
    assert ctl.stall_until > 0 and drops == [ctl.drop_s]
    world.protective_stop("collision")  # the world itself stopping the arm is a protective stop too
    ticks(ctl, 1)
    assert ctl.safety_mode == S.SAFETY_PROTECTIVE_STOP


def test_contact_bit_and_calibrated_tcp_pose():
    world, ctl, _ = make()
    ticks(ctl, 1)
    pose = np.array(ctl.value("actual_TCP_pose"))  # from the controller's calibrated kinematics
    np.testing.assert_allclose(pose[:3], links_truth(world).position(world.encoder_q()), atol=1e-9)
    assert np.linalg.norm(pose[:3] - world.nominal.position(world.encoder_q())) > 1e-5
    assert ctl.value("actual_digital_input_bits") == 0
    needle = world.points["N"].position
    ik = world.truth.ik(needle[None], world.encoder_q()[None], position_only=True, tol_pos=1e-10)
    world.command_q(ik.q[0])
    world.run_until_idle()
    ticks(ctl, 1)
    assert world.contact() and ctl.value("actual_digital_input_bits") == 1 << S.DEFAULT_CONTACT_BIT




def test_a_cycle_thread_kept_waiting_slips_instead_of_firing_the_watchdog():
    """rtde_set_watchdog at 10 Hz, a client writing every 10 ms, and one controller cycle held up for 0.3 s (the
    emulator's host did not schedule it). Catching up with 150 cycles back to back would compress 0.3 s of
    controller time into a few ms of real time, with at most one write in it: the watchdog fired under a station
    that had written on time (seen under load). The cycle slips instead; a client that stops writing is still
    stopped one period later."""
    world = World.default("ur5e", seed=5, time_mode="sim")
    ctl = URController(world)
    power_up(ctl)
    ctl.load_program("rtde_control", SCRIPT)
    command(ctl, S.CMD_SET_WATCHDOG, [10.0])
    ctl.tick()
    stop, held = threading.Event(), threading.Event()

    def writer() -> None:
        while not stop.is_set():
            command(ctl, S.CMD_NONE)
            time.sleep(0.01)

    advance = world.advance

    def advance_once_late(dt: float) -> None:
        if not held.is_set() and ctl.tick_count > 50:
            held.set()
            time.sleep(0.3)
        advance(dt)

    world.advance = advance_once_late
    threading.Thread(target=writer, daemon=True).start()
    ctl.start()
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 1.0:
            time.sleep(0.05)
            assert ctl.runtime_state == S.PLAYING, ctl.messages
        assert held.is_set()
        stop.set()
        time.sleep(0.3)
        assert ctl.runtime_state == S.STOPPED and "watchdog expired" in ctl.messages[-1]
    finally:
        stop.set()
        ctl.stop()
