"""Seating compliance on CiA 402 drives. Profile torque mode commands torque and nothing holds position (Nanotec
PD2-C "Profile Torque"): the emulated joint accelerates or sags under the world's gravity. The driver seats in
profile position mode with torque limits (0x60E0/0x60E1) set from the torque holding takes (0x6077) plus a
margin: the arm neither sags nor pushes hard, and the emulator calls it compliant because those limits let a
socket turn every joint it can reach, not because of a threshold. Truth: the world's joints, torques and
compliance; real canopen + python-can on both sides."""

from __future__ import annotations

import time
import uuid

import canopen
import numpy as np
import pytest
from station.mocks.canopen import eds
from station.mocks.canopen.emulator import CanopenEmulator
from station.mocks.world import World

from station.robot import open_robot

START = [0.3, -0.7, 0.9, 1.0, -0.6, 2.0]


def count(world, i: int) -> float:
    enc = world.nominal.joints[i].encoder
    return 1.0 / abs(enc.counts_per_unit * enc.gear)


@pytest.fixture
def client():
    """Realtime world, emulated drives, a plain canopen client on nodes 1-6."""
    chan = f"c-{uuid.uuid4().hex[:8]}"
    world = World.default(model="arm6", seed=3, start=START, time_mode="realtime")
    emu = CanopenEmulator(world, channel=chan).start()
    net = canopen.Network()
    net.NOTIFIER_CYCLE = 0.05
    net.connect(interface="virtual", channel=chan)
    nodes = {}
    for i in range(1, 7):
        nodes[i] = canopen.BaseNode402(i, str(eds.EDS_PATH))
        net.add_node(nodes[i])
    time.sleep(0.03)
    yield world, emu, net, nodes
    net.disconnect()
    emu.stop()


def _enable(n, mode: int) -> None:
    n.sdo[0x6060].raw = mode
    for cw in (0x06, 0x07, 0x0F):
        n.sdo[0x6040].raw = cw


def test_profile_torque_commands_torque_only(client):
    """50 per mille on the gravity-loaded elbow (a3) and on the unloaded wrist roll (a6): neither holds its
    position; the torque actual value is the commanded torque (the motor applies it)."""
    world, emu, net, nodes = client
    q0 = world.encoder_q().copy()
    for j in (3, 6):
        nodes[j].sdo[0x6071].raw = 50
        _enable(nodes[j], 4)
    time.sleep(0.4)
    q1 = world.encoder_q()
    assert abs(q1[2] - q0[2]) > 0.01, q1 - q0  # sags (or is pushed) well beyond any encoder count
    assert abs(q1[5] - q0[5]) > 0.01, q1 - q0  # nothing loads it: 5 % of rated torque accelerates it
    assert nodes[6].sdo[0x6077].raw == 50


def test_compliance_follows_the_torque_limits_actually_set(client):
    """Stiff (the drives' peak torque) is not compliant; limits of the holding torque plus a small margin are
    (every joint yields to what a socket pushes with), and the arm does not sag; a margin larger than the socket
    can overcome on some joint is not compliant."""
    world, emu, net, nodes = client
    for n in nodes.values():
        _enable(n, 1)
    time.sleep(0.05)
    assert not world.compliant
    hold = {i: n.sdo[0x6077].raw for i, n in nodes.items()}

    def limits(margin):
        for i, n in nodes.items():
            n.sdo[0x60E0].raw = max(hold[i], 0) + margin
            n.sdo[0x60E1].raw = max(-hold[i], 0) + margin
        time.sleep(0.05)  # applied at the drives' next control cycle (the SYNCs of the client below)

    sync = net.sync
    sync.start(0.004)
    try:
        q0 = world.encoder_q().copy()
        limits(30)
        assert world.compliant and np.all(np.isfinite(world.torque_limit()))
        time.sleep(0.3)
        assert np.all(np.abs(world.encoder_q() - q0) <= 2 * np.array([count(world, i) for i in range(6)]))
        assert not any("sags" in text for _, text in world.events)
        limits(2000)
        assert not world.compliant  # 2000 per mille beyond holding: more than a socket overcomes
        for i in nodes:
            nodes[i].sdo[0x60E0].raw = nodes[i].sdo[0x60E1].raw = eds.DEFAULT_TORQUE_LIMIT
        time.sleep(0.05)
        assert not world.compliant and np.all(np.isinf(world.torque_limit()))
    finally:
        sync.stop()


def test_driver_seats_in_position_mode_without_sag_and_restores_its_limits():
    """``set_compliant(True)`` over a socket: the tip seats, every drive is still in profile position mode, its
    torque limits are the holding torque plus the margin (no bare torque set-point), and the arm stays where it
    settled; off: the drives' own limits are back and the arm stays in the socket."""
    chan = f"c-{uuid.uuid4().hex[:8]}"
    world = World.default(model="arm6", seed=7, start=START, time_mode="realtime")
    with CanopenEmulator(world, channel=chan) as emu, open_robot(f"canopen+virtual://{chan}?nodes=1-6&model=arm6") \
            as robot:
        robot.enable()
        above = world.points["A"].position + np.array([0, 0, 0.003])
        q_above = world.truth.ik(above, np.array([0, -0.5, 0.5, 0, 0.5, 0]), position_only=True).q[0]
        robot.move_joints(q_above, speed=1.5)
        hold = [d.torque_actual() for d in emu.drives.values()]
        robot.set_compliant(True)
        assert world.compliant and world.seated == "A" and robot.touch() is True
        for i, d in enumerate(emu.drives.values()):
            assert d.mode == 1  # profile position: it holds position
            margin = max(30, int(np.ceil(0.1 * abs(hold[i]))))
            assert abs(d.get(0x60E0) - (max(hold[i], 0) + margin)) <= 3, (i, d.get(0x60E0), hold[i])
            assert abs(d.get(0x60E1) - (max(-hold[i], 0) + margin)) <= 3, (i, d.get(0x60E1), hold[i])
        seated = world.encoder_q().copy()
        time.sleep(0.3)
        assert np.all(np.abs(world.encoder_q() - seated) <= 2 * np.array([count(world, i) for i in range(6)]))
        assert not any("sags" in text for _, text in world.events)
        robot.set_compliant(False)
        assert not world.compliant and world.seated == "A"
        assert all(d.get(0x60E0) == d.get(0x60E1) == eds.DEFAULT_TORQUE_LIMIT for d in emu.drives.values())
        time.sleep(0.2)
        assert np.all(np.abs(world.encoder_q() - seated) <= 2 * np.array([count(world, i) for i in range(6)]))
