"""correction_map on top of a parametric calibration, on a 6R arm whose world has what no geometric model holds:
hidden geometry errors, gravity compliance under a 15 kg payload and gear backlash. arm6 on six emulated CiA 402
drives (python-can virtual channel, real canopen library), the laser-tracker emulator on loopback TCP.

The calibration engineer's flow (docs/map.md, "On top of a parametric calibration"): tracker readings at
configurations of the work box -> ``station solve --identify offsets,dh,tcp`` (instrument frame solved) ->
``station run correction_map --calibration result.json``. A calibration fitted on tracker POSITIONS cannot know
the tool's orientation; the map, built from 6-DoF readings, corrects it: calibrated + map beats the calibration
alone in orientation far beyond the tracker's noise. In position the calibration of this box alone is already
near the noise floor and a Q = 1 map on top adds its interpolation error (bench/map.py part f; near the 0.10 mm
limit, judged as it falls), and the procedure warns that the map is worse in position than the calibration.
The truth is the world's true tool pose, recorded at every tracker reading (compliance and backlash included)."""

import json
import subprocess
import sys
import uuid

import numpy as np
from station.mocks.canopen.emulator import CanopenEmulator
from station.mocks.tracker.config import tracker_config
from station.mocks.tracker.server import TrackerServer
from station.mocks.world import World
from station.mocks.world.tracker import measure_poses

from station.api import resume
from station.api import run as start
from station.engine import read_journal
from station.kinematics import se3
from station.solver.map import CorrectionMap

SIGMA_0, SIGMA_PER_M = 15e-6, 6e-6  # the tracker's specification (issue 12), one sigma per reflector and axis
SERIAL = "A6-0013"
START = np.array([0.0, 0.17, 0.17, 0.0, -0.87, 0.0])  # rad: the bent-elbow work zone (tests/test_correction_map_arm6)
SPAN = np.radians(10.0)
JOINTS = {"compliance": {"j2": 2e-5, "j3": 3e-5, "j5": 4e-5}, "backlash": {"j1": 3e-4, "j2": 3e-4, "j3": 3e-4},
          "payload": 15.0}  # rad/(N m), rad, kg: as bench/map.py


class RecordingTracker(TrackerServer):
    """The tracker emulator, unchanged on the wire; the test keeps the world's TRUE tool pose at every reading."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.truth: list[tuple[np.ndarray, np.ndarray]] = []

    def measure(self):
        self.truth.append((self.world.encoder_q().copy(), self.world.tip_pose_true().copy()))
        return super().measure()


def _calibration_file(world, cfg, tmp_path):
    """The parametric calibration: 40 tracker readings in the work box (approached from below, as the procedure
    does), solved by the real ``station solve`` with the tracker frame unknown."""
    rng = np.random.default_rng(3)
    trk = TrackerServer(world, cfg, seed=5)  # not started: its measure() is the instrument's reading
    q = START + rng.uniform(-SPAN, SPAN, (40, 6))
    rows = []
    for qi in q:
        world.command_q(qi - np.radians(0.5))
        world.command_q(qi)
        rows.append([*world.encoder_q(), "P", *trk.measure()[:3]])
    world.command_q(START)
    csv = tmp_path / "tracker-samples.csv"
    csv.write_text("q1[rad],q2[rad],q3[rad],q4[rad],q5[rad],q6[rad],point,x[m],y[m],z[m]\n"
                   + "".join(",".join(str(v) for v in r) + "\n" for r in rows))
    out = tmp_path / "result.json"
    r = subprocess.run([sys.executable, "-m", "station.cli", "solve", "--model", "arm6", "--samples", str(csv),
                        "--identify", "offsets,dh,tcp", "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return out


def test_map_on_top_of_a_calibration_beats_the_calibration_alone(tmp_path, monkeypatch):
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    world = World.default("arm6", seed=7, start=START, joints=JOINTS)
    cfg = tracker_config({})
    cal_file = _calibration_file(world, cfg, tmp_path)
    original = cal_file.read_bytes()
    cal_doc = json.loads(original)
    wrong = tmp_path / "ur5e.json"
    wrong.write_text(json.dumps({**cal_doc, "model": "ur5e"}))
    channel = f"m7{uuid.uuid4().hex[:8]}"
    # a slower SYNC and a longer heartbeat consumer time (driver URL options): the CI machine is shared
    url = f"canopen+virtual://{channel}?nodes=1-6&model=arm6&serial={SERIAL}&sync_ms=20&heartbeat_timeout_ms=5000"
    db = f"sqlite:///{tmp_path / 'records.db'}"
    emu = CanopenEmulator(world, "virtual", channel).start()
    try:
        with RecordingTracker(world, cfg, seed=11) as trk:
            # a calibration of another model: one line before the tracker is touched or anything moves
            out = start("correction_map", url, SERIAL, db=db, report=False,
                        options={"tracker": trk.url, "grid": 1, "span_deg": 10, "calibration": str(wrong)})
            assert out.status == "error" and out.exit_code == 2
            assert "\n" not in str(out.error) and "'ur5e', not 'arm6'" in str(out.error), out.error
            assert trk.measurements == 0 and np.allclose(world.encoder_q(), START, atol=1e-6)

            def stop(done, total, text):
                if done == 30:
                    raise KeyboardInterrupt  # Ctrl-C after 30 configurations

            out = start("correction_map", url, SERIAL, db=db, report=False, progress=stop,
                        options={"tracker": trk.url, "grid": 1, "span_deg": 10, "n_holdout": 16,
                                 "calibration": str(cal_file)})
            assert out.status == "interrupted", out.error
            # the file changes under the session: resume refuses it before measuring anything
            cal_file.write_text(json.dumps({**cal_doc, "notes": ["edited"]}))
            again = resume(out.session, db=db, report=False)
            assert again.status == "error" and again.exit_code == 2
            assert "changed since session" in str(again.error) and "\n" not in str(again.error)
            assert trk.measurements == 30
            cal_file.write_bytes(original)  # the file as the session started with it
            again = resume(out.session, db=db, report=False)
    finally:
        emu.stop()
    assert again.status == "completed", again.error
    rec = again.record
    meas = {m["name"]: m for m in rec["verdict"]["measurements"]}
    # judged honestly either way: the map on top of this calibration sits near the 0.10 mm limit (0.086-0.104 mm
    # measured), which is what it is; the verdict and the exit code must say the same
    assert again.stored and again.passed is not None and again.exit_code == (0 if again.passed else 1)
    assert again.passed == (meas["holdout_rms"]["value"] <= 0.10 and meas["holdout_max"]["value"] <= 0.25)
    assert trk.measurements == len(rec["samples"]) == 64 + 16  # every configuration measured once

    # stored with the map: which calibration, and the map sits on exactly its parameters
    stored = rec["correction_map"]
    model_params = {n: p["value"] for n, p in cal_doc["parameters"].items()
                    if p["kind"] == "model" and p["identifiable"]}
    assert stored["calibration"]["parameters"] == model_params and stored["calibration"]["model"] == "arm6"
    cmap = CorrectionMap.from_dict(stored["map"])
    assert cmap.calibration["parameters"] == model_params

    # truth from the world: the true tool pose at each held-out reading, in the tracker's frame; the calibrated
    # model alone and calibrated + map seen through the session's registration
    truth = {tuple(np.round(q, 9)): T for q, T in trk.truth}
    held = [s for s in rec["samples"] if s["set"] == "holdout"]
    x = np.array([s["q"] for s in held])
    true_t = se3.invert(cfg.tracker_in_base) @ np.array([truth[tuple(np.round(q, 9))] for q in x])
    reg = se3.invert(se3.pose_to_matrix(np.array(stored["registration"]["instrument_in_base"])))
    cal = world.nominal.with_params(model_params)
    mapped, _ = cmap.measure(world.nominal, x)
    cal_t, map_t = reg @ cal.fk(x), reg @ se3.pose_to_matrix(mapped)
    e_cal, e_map = (np.linalg.norm(T[:, :3, 3] - true_t[:, :3, 3], axis=1) for T in (cal_t, map_t))
    r_cal, r_map = (np.linalg.norm(se3.orientation_error(true_t[:, :3, :3], T[:, :3, :3]), axis=1)
                    for T in (cal_t, map_t))
    rms = {k: float(np.sqrt(np.mean(v ** 2))) for k, v in
           {"cal": e_cal, "map": e_map, "rcal": r_cal, "rmap": r_map}.items()}
    # noise floors of ONE tracker reading (the world's tracker model, an independent computation): 3-D position
    # RMS at the farthest held-out distance, and the probe's rotation RMS from 2000 readings of one pose
    floor = np.sqrt(3) * (SIGMA_0 + SIGMA_PER_M * np.linalg.norm(true_t[:, :3, 3], axis=1).max())
    pose = np.repeat(cfg.tracker_in_base[None] @ true_t[:1], 2000, axis=0)
    noisy = measure_poses(pose, cfg.reflectors, cfg.tracker_in_base, np.random.default_rng(0))
    rot_floor = float(np.sqrt(np.mean(np.sum(se3.orientation_error(noisy[:, :3, :3], true_t[:1, :3, :3]) ** 2,
                                             axis=1))))
    # orientation: what a position calibration leaves, the map corrects, far beyond the noise
    assert rms["rcal"] - rms["rmap"] > 3 * rot_floor and rms["rmap"] < 0.5 * rms["rcal"], (rms, rot_floor)
    # position: the map on top stays within the limit; both numbers the procedure judged agree with the truth
    assert rms["map"] < 1e-4, rms
    assert abs(meas["holdout_calibrated_rms"]["value"] * 1e-3 - rms["cal"]) < 0.25 * rms["cal"] + floor, rms
    assert meas["holdout_rms"]["value"] * 1e-3 < 1.3 * np.sqrt(rms["map"] ** 2 + floor ** 2), rms
    assert abs(np.radians(meas["holdout_calibrated_rotation_rms"]["value"]) - rms["rcal"]) < 0.25 * rms["rcal"]
    assert meas["calibration_parameters"]["value"] == len(model_params)
    # the engineer is told when the map is worse in position than the calibration alone (and only then)
    _, events = read_journal(again.folder / "journal.jsonl")
    warned = any(e.type == "warning" and "calibration alone" in e.message for e in events)
    assert warned == (meas["holdout_rms"]["value"] > meas["holdout_calibrated_rms"]["value"])
