"""A lost master (CiA 301 heartbeat consumer 0x1016, CiA 402 abort connection option code 0x6007, 0x1029 error
behaviour): a drive reacts only when its consumer watches the master (Lenze 8400: heartbeat event -> EMCY 0x8130,
Operational -> Pre-operational, the response parameterised, Lenze setting "No response"); the station produces
a heartbeat and configures every drive's consumer, so a killed station process stops the arm within the
consumer time. Truth: the world's joints and the drives' states; a real process killed with SIGKILL."""

from __future__ import annotations

import time
import uuid
from pathlib import Path

import can
import canopen
import numpy as np
import pytest
from clirunner import python_spawn
from station.mocks.canopen import eds
from station.mocks.canopen.emulator import CanopenEmulator
from station.mocks.canopen.hub import SocketcandHub
from station.mocks.world import World

START = [0.3, -0.7, 0.9, 1.0, -0.6, 2.0]
ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture
def client():
    chan = f"b-{uuid.uuid4().hex[:8]}"
    world = World.default(model="arm6", seed=3, start=START, time_mode="realtime")
    emu = CanopenEmulator(world, channel=chan, timeout_silence=3.0).start()
    net = canopen.Network()
    net.NOTIFIER_CYCLE = 0.05
    net.connect(interface="virtual", channel=chan)
    node = canopen.BaseNode402(2, str(eds.EDS_PATH))
    net.add_node(node)
    time.sleep(0.03)
    yield world, emu, net, node
    net.disconnect()
    emu.stop()


def _start_move(node, delta: float, world) -> float:
    """Enable drive 2 and send it on a slow profile position move of ``delta`` rad; returns the target (SI)."""
    enc = world.nominal.joints[1].encoder
    node.nmt.state = "OPERATIONAL"
    node.sdo[0x6060].raw = 1
    for cw in (0x06, 0x07, 0x0F):
        node.sdo[0x6040].raw = cw
    per_rad = abs(enc.counts_per_unit * enc.gear)
    node.sdo[0x6081].raw = int(0.2 * per_rad)  # 0.2 rad/s at the joint
    target = world.encoder_q()[1] + delta
    node.sdo[0x607A].raw = int(round(float(enc.to_counts(target))))
    node.sdo[0x6040].raw = 0x3F
    node.sdo[0x6040].raw = 0x0F
    return target


def test_without_a_consumer_a_cut_off_drive_keeps_going(client):
    """Nobody configured 0x1016: a drive cut off the bus (it neither hears nor answers) finishes its move."""
    world, emu, net, node = client
    target = _start_move(node, 0.2, world)
    time.sleep(0.1)
    world.faults.inject("timeout", device=2)
    time.sleep(1.3)
    assert abs(world.encoder_q()[1] - target) < 1e-4  # arrived: no master, no reaction
    assert emu.drives[2].state == "OPERATION ENABLED"


def test_a_consumer_reacts_with_emcy_preoperational_and_0x6007(client):
    """0x1016 watches node 100 for 300 ms, 0x6007 = 3 (quick stop): when its heartbeat stops, EMCY 0x8130, the
    drive's heartbeat says PRE-OPERATIONAL and the joint stops short of its target; monitoring starts only with
    the first heartbeat seen."""
    world, emu, net, node = client
    node.sdo[0x6007].raw = 3
    node.sdo[0x1016][1].raw = (100 << 16) | 300
    node.sdo[0x1017].raw = 50
    time.sleep(0.5)
    assert emu.drives[2].state == "SWITCH ON DISABLED" and not emu.drives[2].hb_lost  # no heartbeat seen yet: quiet
    with pytest.raises(canopen.SdoAbortedError):
        node.sdo[0x1016][2].raw = (100 << 16) | 500  # a second entry for the same producer
    beat = net.bus.send_periodic(can.Message(arbitration_id=0x700 + 100, data=[5], is_extended_id=False), 0.05)
    target = _start_move(node, 0.4, world)
    time.sleep(0.3)
    assert world.is_moving()
    beat.stop()
    t0 = time.monotonic()
    emcy = node.emcy.wait(0x8130, timeout=2.0)
    assert emcy is not None and 0.25 < time.monotonic() - t0 < 0.6
    end = time.monotonic() + 1.0
    while world.is_moving() and time.monotonic() < end:
        time.sleep(0.01)
    assert not world.is_moving() and abs(world.encoder_q()[1] - target) > 0.05
    assert emu.drives[2].state == "QUICK STOP ACTIVE"
    node.nmt.wait_for_heartbeat(1.0)
    assert node.nmt.state == "PRE-OPERATIONAL"


STATION = """
import logging, sys, time
import numpy as np
logging.getLogger("can").setLevel(logging.CRITICAL)
from station.robot import open_robot
robot = open_robot(sys.argv[1])
robot.enable()
q = robot.joint_positions().q
robot.move_joints(q + np.array([0.0, 0.6, 0.0, 0.0, 0.0, 0.0]), speed=0.3, wait=False)
print("moving", flush=True)
time.sleep(30)
"""


@pytest.mark.slow
def test_killing_the_station_mid_move_stops_the_arm_within_the_consumer_time():
    """The station in its own process (python-can socketcand client) starts a 2 s move and is killed with
    SIGKILL: its heartbeat stops, and every drive's consumer (``master_timeout_ms=400``) quick-stops its joint.
    The arm is still within 400 ms + the quick-stop deceleration (+ scheduling slack) of the kill."""
    chan = f"k-{uuid.uuid4().hex[:8]}"
    world = World.default(model="arm6", seed=3, start=START, time_mode="realtime")
    # its own rig: the station runs in another process, so the drives sit behind a socketcand hub (robot_rig's
    # virtual channel reaches this process only)
    with CanopenEmulator(world, channel=chan) as emu, SocketcandHub(chan, port=0) as hub:
        # sdo_timeout_ms: connecting is not what is timed here, and this host may be loaded
        url = (f"canopen+socketcand://127.0.0.1:{hub.port}?channel=can0&nodes=1-6&model=arm6"
               "&master_timeout_ms=400&sdo_timeout_ms=2000")
        # first a station that closes cleanly: it takes its consumer entries back, so its heartbeat stopping is no
        # event (no EMCY 0x8130, no drive left quick-stopped)
        from station.robot import open_robot

        with open_robot(url) as robot:
            robot.enable()
            assert all(d.consumers() for d in emu.drives.values())
        time.sleep(0.8)
        assert not any(d.consumers() or d.hb_lost for d in emu.drives.values())
        assert {d.state for d in emu.drives.values()} == {"READY TO SWITCH ON"}
        # a script, not a command: it must be killed mid-move, which no station command guarantees to be in
        with python_spawn(STATION, url, cwd=ROOT) as proc:
            line = proc.readline()
            assert line.strip() == "moving", line + (proc.wait().err if not proc.running() else "")
            time.sleep(0.3)
            assert world.is_moving()
            q_kill = world.encoder_q().copy()
            proc.kill()
            t_kill = time.monotonic()
            proc.wait(5)
            while world.is_moving() and time.monotonic() - t_kill < 5:
                time.sleep(0.005)
            took = time.monotonic() - t_kill
        amax = world.truth.joints[1].max_acceleration
        decel = 0.3 / amax  # from 0.3 rad/s at the joint's acceleration limit
        assert not world.is_moving() and took < 0.4 + decel + 0.3, took
        assert np.max(np.abs(world.encoder_q() - q_kill)) < 0.3 * (0.4 + decel + 0.3)  # nowhere near its target
        assert {d.state for d in emu.drives.values()} <= {"QUICK STOP ACTIVE", "SWITCH ON DISABLED"}
        print(f"\nstation killed mid-move: arm still after {took * 1e3:.0f} ms (consumer 400 ms)")


def test_no_drive_is_enabled_before_its_consumer_watches_the_station(robot_rig):
    """A consumer watches the station only from the first heartbeat it hears after its 0x1016 entry is written
    (CiA 301): at the moment enable() returns, every drive has heard one, so each would notice the station go
    silent. Truth: the emulated drives' own consumer state; the heartbeat period made long (1 s) so that the
    window is wide open without the wait."""
    world = World.default(model="arm6", seed=3, start=START, time_mode="realtime")
    emu, robot = robot_rig("canopen", world, query="&master_heartbeat_ms=1000&heartbeat_timeout_ms=3500",
                           enable=False)
    robot.enable()
    unwatched = [d.id for d in emu.drives.values() if d.hb_seen.get(127) is None]
    assert not unwatched, f"enabled while their consumers did not watch yet: {unwatched}"
    assert all(d.state == "OPERATION ENABLED" for d in emu.drives.values())
