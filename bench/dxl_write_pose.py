"""DYNAMIXEL write pose: how many moves ``write_pose()`` needs from random start poses before every joint to be
written holds less than ``hold_torque`` (measured by the servos' Present Current through the emulator), and
whether the world's TRUE gravity torque there is below what the joint's friction holds (the joint would stay
put with its torque off).

Run: ``.venv/bin/python bench/dxl_write_pose.py [--trials 20] [--servo xm430|xl430]``. Two worlds: the demo world
of ``station demo dynamixel`` (seed 31) and ``World.default("omx")`` (estimated link masses), instant time."""

from __future__ import annotations

import argparse

import numpy as np
from station.mocks.dynamixel import DynamixelEmulator
from station.mocks.world import World

from station.cli.run_cmd import demo_world
from station.robot import open_robot


def run(world: World, trials: int, servo: str) -> tuple[list[int], int, float]:
    """(moves per trial, failures, worst |gravity torque| / friction over the written joints)."""
    moves, fails, worst = [], 0, 0.0
    values = {f"offset.j{k}": 0.003 * k for k in range(1, world.n_joints + 1)}
    with DynamixelEmulator(world, ids=[11, 12, 13, 14], servo=servo) as emu:
        name = "xl430-w250" if servo == "xl430" else "xm430-w350"
        with open_robot(f"{emu.url}&servo={name}") as robot:
            robot.enable()
            rng = np.random.default_rng(2)
            for _ in range(trials):
                robot.move_joints(rng.uniform(world.nominal.lower + 0.3, world.nominal.upper - 0.3))
                try:
                    n = 0
                    while (q := robot.write_pose(values)) is not None:
                        robot.move_joints(q)
                        n += 1
                    moves.append(n)
                    assert emu.settled()
                    worst = max(worst, float(np.max(np.abs(world.gravity_torque()) / world.dynamics_friction())))
                except Exception as e:  # noqa: BLE001 - counted and shown
                    fails += 1
                    print(f"  failed: {e}")
    return moves, fails, worst


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--servo", default="xm430", choices=("xm430", "xl430"))
    a = ap.parse_args()
    for label, world in (("demo (seed 31)", World.from_dict(demo_world("dynamixel", 31, "instant"))),
                         ("default omx (seed 5)", World.default(model="omx", seed=5))):
        moves, fails, worst = run(world, a.trials, a.servo)
        print(f"{label}, {a.servo}: moves min {min(moves)} median {int(np.median(moves))} max {max(moves)}, "
              f"{fails} failed of {a.trials}; worst true gravity torque / friction at the pose: {worst:.2f}")


if __name__ == "__main__":
    main()
