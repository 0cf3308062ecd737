"""The collision reflex of the Franka emulator: franka-sim acknowledges ``SetCollisionBehavior`` and never
acts on it; the station's simhost keeps the upper thresholds the client set and aborts a motion that pushes
harder with ``cartesian_reflex`` / ``joint_reflex``, as the robot does (libfranka robot.h
``setCollisionBehavior``; errors.h). Seen through the real client (pylibfranka) and the driver."""

from __future__ import annotations

import numpy as np
import pytest
from franka_helpers import SOCKETS, ik_down, write_world
from station.mocks.franka.launch import FrankaEmulator
from station.mocks.world import World

from station.robot.errors import SafetyStop
from station.robot.registry import open_robot

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    folder = tmp_path_factory.mktemp("franka-reflex")
    path = write_world(folder)
    with FrankaEmulator(path) as emu:
        yield emu, World.from_file(path)


def _open(emu):
    import gc

    gc.collect()  # a test's traceback (cycles) may still hold the last connection: the FCI serves one client
    return open_robot(emu.url + "&speed=1.0&press_force=0")


def test_a_stiff_move_into_the_socket_ends_in_the_collision_reflex(sim):
    """Stiff (joint impedance, the driver's async generator) 4 mm below the centre of socket B: the cone stops
    the ball, the arm's spring loads it beyond the driver's 20 N threshold, the robot aborts the motion with the
    reflex latched in the state; the driver raises one line; automatic error recovery clears it."""
    emu, world = sim
    nominal, socket = world.nominal, np.asarray(SOCKETS["B"], float)
    with _open(emu) as r:
        above = ik_down(nominal, socket, r.joint_positions().q, 0.03)
        inside = ik_down(nominal, socket, above, -0.004)
        r.move_joints(above)
        with pytest.raises(SafetyStop, match="collision reflex") as e:
            r.move_joints(inside, speed=0.2)
        assert "\n" not in str(e.value) and ("cartesian_reflex" in str(e.value) or "joint_reflex" in str(e.value))
        state = r._robot.read_once()
        assert "reflex" in str(state.current_errors) and "reflex" in str(state.last_motion_errors)
        F = np.asarray(state.O_F_ext_hat_K)
        # the reflex stopped the push: what the arm still leans on the cone is within a few N of the threshold
        assert np.linalg.norm(F[:3]) < 45.0, F
        st = r.status()
        assert st.faults and not st.enabled
        r.enable()  # automatic error recovery
        assert r.status().enabled and not r.status().faults
        r.move_joints(above)
        assert not r.touch()


def test_a_stiff_move_that_stops_short_of_the_cone_does_not_trip_it(sim):
    """The same approach ended 3 mm above the seated pose: no contact, no reflex."""
    emu, world = sim
    nominal, socket = world.nominal, np.asarray(SOCKETS["B"], float)
    with _open(emu) as r:
        above = ik_down(nominal, socket, r.joint_positions().q, 0.03)
        r.move_joints(above)
        r.move_joints(ik_down(nominal, socket, above, 0.003), speed=0.2)
        assert not r.status().faults
        assert np.linalg.norm(np.asarray(r._robot.read_once().O_F_ext_hat_K)[:3]) < 2.0
        r.move_joints(above)
