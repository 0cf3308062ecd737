"""``station.drivers.dynamixel.writepose``: where an OpenManipulator-X may have a servo's torque off for an EEPROM
write: which joints gravity loads, and the measured Newton steps that bring the joints to be written to (almost) no
holding torque, with the torques "measured" on the simulated world's gravity (central differences of its potential
energy, ``station.mocks.world.physics``) read in the servo's current units."""

from __future__ import annotations

import numpy as np
from station.drivers.dynamixel import table as T
from station.drivers.dynamixel.writepose import Balancer, loadable, upright_guess
from station.mocks.world.physics import Gravity

from station.kinematics import load_model

MASSES = {2: (0.14, np.array([0.06, 0.0, 0.0])), 3: (0.13, np.array([0.06, 0.0, 0.0])),
          4: (0.12, np.array([0.05, 0.0, 0.0]))}


def test_which_joints_gravity_loads():
    omx = load_model("omx")
    assert loadable(omx, np.zeros(4)) == [False, True, True, True]  # the waist turns about the vertical


def test_balancer_reaches_a_pose_without_holding_torque():
    omx = load_model("omx")
    world = Gravity(omx, MASSES, (0.0, np.zeros(3)), (0.0, 0.0, -9.81), np.zeros(4))
    stall, amps = T.STALL[1020]
    unit = np.full(4, T.CURRENT_UNIT * stall / amps)  # N m per unit of Present Current (2.69 mA)
    tick = np.full(4, 2 * np.pi / 4096)
    joints, free = [1, 2, 3], [1, 2, 3]
    q = np.array([0.3, -0.6, 0.4, 0.5])
    guess = upright_guess(omx, q, joints, free)
    assert np.abs(world.torque(guess)[joints]).max() < np.abs(world.torque(q)[joints]).max()
    hold = 5 * unit[0]
    b = Balancer(omx.lower, omx.upper, joints, free, hold, unit, tick)
    pose, moves = guess, 0
    while True:
        measured = np.round(world.torque(pose)[joints] / unit[joints]) * unit[joints]  # what the servos read
        nxt = b.next_pose(pose, measured)
        if nxt is None:
            break
        assert np.all(nxt >= omx.lower) and np.all(nxt <= omx.upper) and nxt[0] == pose[0]  # the waist stays
        pose, moves = nxt, moves + 1
    assert np.abs(world.torque(pose)[joints]).max() <= hold + unit[0] and 0 < moves < 40
