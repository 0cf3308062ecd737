"""Identity check at connect: the model named in the URL (or the default) against what the
controller / devices report, on the real wire (ur_rtde + dashboard socket, dynamixel-sdk on a pty, canopen
SDO over a python-can bus). A mismatch is one ``IdentityMismatch`` line (exit 2) and nothing moved: the
world's joints are where they started (ground truth from the emulator's world)."""

from __future__ import annotations

import re

import numpy as np
import pytest
import yaml
from station.mocks.world import World, default_doc

from station.robot import IdentityMismatch, open_robot

UR_START = [0.1, -1.45, 1.6, -1.72, -1.5708, 0.2]


def _ur_world(tmp_path, model="ur5e", **bus):
    tmp_path = tmp_path / model
    tmp_path.mkdir(exist_ok=True)
    doc = default_doc(model, seed=3)
    doc["motion"].update(time_mode="sim", start=list(UR_START))
    doc["buses"] = {"ur": {"serial": "20235512345", **bus}}
    path = tmp_path / "world.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.mark.parametrize("query, needle", [
    ("model=ur3e", "model ur3e is a UR3 e-Series but the controller reports UR5 e-Series"),
    ("model=ur10e", "model ur10e is a UR10 e-Series but the controller reports UR5"),
    ("model=arm6", "model arm6 does not say which UR arm it is for; the controller is a UR5e: add robot_type=UR5e"),
    ("model=ur5e&robot_type=UR10e", "robot_type=UR10e is a UR10 e-Series"),
])
def test_ur_model_mismatch_refused_before_motion(tmp_path, emulators, query, needle):
    emu = emulators("ur", _ur_world(tmp_path))
    with pytest.raises(IdentityMismatch) as e:
        open_robot(f"ur://{emu.host}?{query}")
    msg = str(e.value)
    assert needle in msg and "\n" not in msg
    # nothing was uploaded or moved: the controller ran no program
    assert "STOPPED" in emu.dashboard("programstate")


def test_ur_cb3_controller_refuses_e_series_model(tmp_path, emulators):
    emu = emulators("ur", _ur_world(tmp_path, polyscope="URSoftware 3.15.7.106331 (Jun 02 2021)"))
    with pytest.raises(IdentityMismatch, match="UR5 e-Series but the controller reports UR5 CB3.*robot_type=UR5\\)"):
        open_robot(f"ur://{emu.host}?model=ur5e")


def test_ur_matching_model_connects_and_reports_arm(tmp_path, emulators):
    emu = emulators("ur", _ur_world(tmp_path))
    with open_robot(f"ur://{emu.host}") as robot:  # default model ur5e
        assert robot.arm == "UR5e"
    emu2 = emulators("ur", _ur_world(tmp_path, model="ur10e"))
    with open_robot(f"ur://{emu2.host}?model=ur10e") as robot:
        assert robot.arm == "UR10e"


# ---- Dynamixel: every joint servo's model number (ping) against the model's servo -------------------------
def _omx_world(tmp_path, **bus):
    doc = default_doc("omx", seed=3)
    doc["buses"] = {"dynamixel": dict(bus)}
    path = tmp_path / "omx.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_dynamixel_wrong_servo_model_refused_before_motion(tmp_path, emulators):
    path = _omx_world(tmp_path, servo="xl430")
    world = World.from_file(path)
    emu = emulators("dynamixel", world)
    q0 = np.array(world.encoder_q(), dtype=float)
    with pytest.raises(IdentityMismatch) as e:
        open_robot(emu.url)
    msg = str(e.value)
    assert "model omx is built from XM430-W350 (model number 1020) servos" in msg
    assert "reports XL430-W250 (model number 1060)" in msg and "\n" not in msg
    assert np.allclose(world.encoder_q(), q0)  # nothing moved


def test_dynamixel_servo_option_accepts_declared_build(tmp_path, emulators):
    emu = emulators("dynamixel", World.from_file(_omx_world(tmp_path, servo="xl430")))
    with open_robot(emu.url + "&servo=XL430-W250") as robot:
        assert {d["model_number"] for d in robot.devices if d["joint"]} == {1060}
    emu2 = emulators("dynamixel", World.from_file(_omx_world(tmp_path)))
    with open_robot(emu2.url) as robot:  # default: omx is XM430-W350
        assert {d["model_number"] for d in robot.devices if d["joint"]} == {1020}


# ---- CANopen: device type 0x1000 (CiA 402) and each rotary drive's scaling 0x608F / 0x6091 ----------------
def _arm6_world(tmp_path, **bus):
    doc = default_doc("arm6", seed=3)
    doc["buses"] = {"canopen": dict(bus)}
    path = tmp_path / "arm6.yaml"
    path.write_text(yaml.safe_dump(doc))
    return World.from_file(path)


def test_canopen_other_arms_model_refused_before_motion(tmp_path, emulators):
    world = _arm6_world(tmp_path)
    emu = emulators("canopen", world)
    q0 = np.array(world.encoder_q(), dtype=float)
    url = re.sub(r"nodes=[^&]*", "nodes=1-4", emu.url.replace("model=arm6", "model=scara"))
    url += "" if "nodes=" in url else "&nodes=1-4"
    with pytest.raises(IdentityMismatch) as e:
        open_robot(url)
    msg = str(e.value)
    enc = world.nominal.joints[0].encoder  # the drive is the world's arm6 joint 1
    assert f"canopen node 1 (joint 1 j1) is scaled {round(enc.counts_per_unit * 2 * np.pi)} counts/motor rev, " \
           f"gear {enc.gear:g}:1" in msg
    assert "model scara" in msg and "\n" not in msg
    assert np.allclose(world.encoder_q(), q0)


def test_canopen_non_402_device_refused(tmp_path, emulators):
    emu = emulators("canopen", _arm6_world(tmp_path, device_type="0x00000191"))  # a CiA 401 I/O module
    with pytest.raises(IdentityMismatch, match=r"not a CiA 402 drive \(device type 0x00000191\)"):
        open_robot(emu.url)

