"""``station.mocks.franka.scene`` and ``simenv``: the simulated FR3's scene written from a station world (the TRUE
arm as a URDF that, read back by the station's URDF reader, has the world's true forward kinematics), what the
emulator refuses, and the simulator environment's lookup and FCI port checks."""

from __future__ import annotations

import json
import socket

import numpy as np
import pytest
from station.mocks.errors import MockError
from station.mocks.franka.scene import check_world, write_scene
from station.mocks.franka.simenv import FCI_PORT, free_loopback, port_free, sim_python
from station.mocks.world import World

from station.kinematics import load_model


def test_the_scene_carries_the_true_arm(tmp_path):
    world = World.default(model="fr3", seed=4)
    path = write_scene(world, tmp_path, "127.0.0.9")
    scene = json.loads(path.read_text())
    assert scene["format"] == "station-franka-scene/1" and scene["host"] == "127.0.0.9"
    assert {s["label"] for s in scene["sockets"]} == {p.label for p in world.points.values() if p.kind == "socket"}
    true_arm = load_model(scene["true_urdf"], tip_link=scene["tool_link"])
    q = np.asarray(world.encoder_q(), float) + np.random.default_rng(1).uniform(-0.3, 0.3, (5, 7))
    assert np.allclose(true_arm.fk(q)[:, :3, 3], world.truth.fk(q)[:, :3, 3], atol=1e-9)
    assert not np.allclose(world.nominal.fk(q)[:, :3, 3], world.truth.fk(q)[:, :3, 3], atol=1e-5)  # hidden errors


def test_what_the_emulator_refuses(tmp_path):
    with pytest.raises(MockError, match="robot.model must be fr3"):
        check_world(World.default(model="ur5e", seed=1))
    with pytest.raises(MockError, match="franka-sim environment is missing"):
        sim_python(tmp_path / "no-python")


def test_fci_port_checks():
    host = free_loopback()
    assert host.startswith("127.") and port_free(host)
    with socket.socket() as s:
        s.bind((host, FCI_PORT))
        assert not port_free(host)  # an emulator on that address already
