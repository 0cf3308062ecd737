"""A stop() from another thread ends a waited move at once with SafetyStop, on every bus."""

import threading
import time

from station.mocks.world import World

from station.robot import SafetyStop, open_robot


def _interrupt_long_move(robot, joint0, idle=lambda: True):
    """Start a slow waited move in a thread, stop() from here; ``joint0()`` reads joint 1 afterwards."""
    q0 = robot.joint_positions().q
    target = q0.copy()
    target[0] += 0.6  # ~several seconds at a slow speed
    err: list[BaseException] = []

    def mover():
        try:
            robot.move_joints(target, speed=0.1, wait=True)
        except BaseException as e:  # noqa: BLE001 - handed to the test thread
            err.append(e)

    t = threading.Thread(target=mover)
    t.start()
    time.sleep(1.0)
    t0 = time.monotonic()
    robot.stop()
    t.join(5.0)
    assert not t.is_alive(), "waited move did not end after stop()"
    assert time.monotonic() - t0 < 2.0
    assert err and isinstance(err[0], SafetyStop), err
    time.sleep(0.5)
    q_stop = joint0()
    assert q0[0] + 0.01 < q_stop < target[0] - 0.1  # stopped part-way, not at the target
    assert idle()


def test_canopen_stop_interrupts_waited_move(emulators):
    world = World.default(model="arm6", seed=3, time_mode="realtime")
    robot = open_robot(emulators("canopen", world).url)
    try:
        robot.enable()
        _interrupt_long_move(robot, lambda: world.encoder_q()[0], lambda: not world.is_moving())
    finally:
        robot.close()


def test_dynamixel_stop_interrupts_waited_move(emulators):
    world = World.default(model="omx", seed=3, time_mode="realtime")
    robot = open_robot(emulators("dynamixel", world).url + "&latency=50")
    try:
        robot.enable()
        _interrupt_long_move(robot, lambda: world.encoder_q()[0], lambda: not world.is_moving())
    finally:
        robot.close()


def test_ur_stop_interrupts_waited_move(tmp_path, emulators):
    import yaml
    from station.mocks.world import default_doc

    doc = default_doc("ur5e", seed=3)
    doc["motion"].update(time_mode="sim", start=[0.1, -1.45, 1.6, -1.72, -1.5708, 0.2])
    path = tmp_path / "world.yaml"
    path.write_text(yaml.safe_dump(doc))
    robot = open_robot(emulators("ur", path).url)
    try:
        _interrupt_long_move(robot, lambda: robot.joint_positions().q[0])
    finally:
        robot.close()
