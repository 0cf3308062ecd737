"""correction_map end to end on a serial 6R arm: arm6 on six emulated CiA 402 drives (python-can virtual channel,
real canopen library), the laser-tracker emulator on a loopback TCP socket, the procedure through the engine;
the truth comes from the simulated world (its hidden geometry errors, the tracker's true placement).

Also: a work box that brushes the shoulder singularity (wrist centre within millimetres of axis 1) is refused
before anything moves: there the map fails even from exact, noise-free poses (docs/map.md, "Serial arms")."""

import uuid

import numpy as np
from station.mocks.canopen.emulator import CanopenEmulator
from station.mocks.tracker.config import tracker_config
from station.mocks.tracker.server import TrackerServer
from station.mocks.world import World

from station.api import run as start
from station.kinematics import se3
from station.solver.map import CorrectionMap

SIGMA_0, SIGMA_PER_M = 15e-6, 6e-6  # the tracker's specification (docs/hardware.md), 1 sigma per reflector, axis
SERIAL = "A6-0012"
GOOD = [0.0, 0.17, 0.17, 0.0, -0.87, 0.0]  # rad: elbow bent, wrist centre 0.3 m off axis 1, wrist bent
SHOULDER = [0.3, -0.9, 1.2, -0.8, 1.2, 0.4]  # rad: +-20 deg around it the wrist centre passes ~5 mm from axis 1


def _session(tmp_path, monkeypatch, start_q, options):
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    world = World.default("arm6", seed=7, start=start_q)
    cfg = tracker_config({})
    channel = f"m6{uuid.uuid4().hex[:8]}"
    emu = CanopenEmulator(world, "virtual", channel).start()
    try:
        with TrackerServer(world, cfg, seed=11) as trk:
            # SDO answers widened: the emulator shares this process with the station (seen: "No SDO response" at -n 2)
            out = start("correction_map", f"canopen+virtual://{channel}?nodes=1-6&model=arm6&serial={SERIAL}"
                        "&sdo_timeout_ms=2000&heartbeat_ms=1000",
                        SERIAL, db=f"sqlite:///{tmp_path / 'records.db'}", options={"tracker": trk.url, **options},
                        report=False)
            measured = trk.measurements
    finally:
        emu.stop()
    return world, cfg, out, measured


def test_arm6_map_beats_nominal_on_held_out_configurations(tmp_path, monkeypatch):
    world, cfg, out, measured = _session(tmp_path, monkeypatch, GOOD, {"grid": 1, "span_deg": 10})
    assert out.status == "completed", out.error
    assert out.passed and out.exit_code == 0 and out.stored
    assert measured == len(out.record["samples"]) == 64 + 12  # 2^6 grid nodes + 12 held out, each once
    cmap = CorrectionMap.from_dict(out.record["correction_map"]["map"])
    reg = se3.pose_to_matrix(np.array(out.record["correction_map"]["registration"]["instrument_in_base"]))
    held = [s for s in out.record["samples"] if s["set"] == "holdout"]
    x = np.array([s["q"] for s in held])
    nom = world.nominal
    # ground truth: the TRUE tool pose at each held-out reading (the world's hidden geometry), seen from the
    # tracker, vs what the map and the nominal model predict there, seen through the session's registration
    true_t = se3.invert(cfg.tracker_in_base) @ world.truth.fk(x)
    mapped, _ = cmap.measure(nom, x)
    e_map = np.linalg.norm((se3.invert(reg) @ se3.pose_to_matrix(mapped))[:, :3, 3] - true_t[:, :3, 3], axis=1)
    e_nom = np.linalg.norm((se3.invert(reg) @ nom.fk(x))[:, :3, 3] - true_t[:, :3, 3], axis=1)
    rms_map, rms_nom = (float(np.sqrt(np.mean(e ** 2))) for e in (e_map, e_nom))
    # noise-derived margin: the 3-D RMS of ONE reflector reading at the farthest held-out distance
    floor = np.sqrt(3) * (SIGMA_0 + SIGMA_PER_M * np.linalg.norm(true_t[:, :3, 3], axis=1).max())
    assert rms_nom - rms_map > 3 * floor, (rms_nom, rms_map, floor)  # not something the noise could make
    assert rms_map < 0.35 * rms_nom and rms_map < 2 * floor, (rms_map, rms_nom, floor)
    # what the procedure judged against the noisy tracker agrees with the truth
    meas = {m["name"]: m for m in out.record["verdict"]["measurements"]}
    assert meas["holdout_rms"]["value"] * 1e-3 < 1.3 * np.sqrt(rms_map ** 2 + floor ** 2)
    assert abs(meas["holdout_nominal_rms"]["value"] * 1e-3 - rms_nom) < 0.2 * rms_nom
    assert meas["predicted_residual"]["value"] < 0.2


def test_arm6_box_at_the_shoulder_singularity_is_refused_before_motion(tmp_path, monkeypatch):
    world, _, out, measured = _session(tmp_path, monkeypatch, SHOULDER, {"grid": 1})
    assert out.status == "error" and out.exit_code == 2
    msg = str(out.error)
    assert "\n" not in msg and msg.startswith("correction_map: the work box") and "singularity" in msg
    assert measured == 0  # the tracker measured nothing
    assert np.allclose(world.encoder_q(), SHOULDER, atol=1e-6)  # and the arm did not move
