"""correction_map on a parametric calibration WITH the compliance term (``station solve --payload 15kg --identify
offsets,dh,tcp,compliance``): the procedure's model carries the same payload (``station run --payload``), so it has
the calibration's ``compliance.jN`` and deflects its joints under that load; without the payload such a calibration
is refused before anything moves. The payload is journaled: a resume uses it and refuses another one.

arm6 on six emulated CiA 402 drives (python-can virtual channel, real canopen library), the laser-tracker emulator
on loopback TCP; the world hides geometry errors, gravity compliance under a 15 kg payload and gear backlash. The
truth is the world's true tool pose at each held-out reading (approached from below as the procedure does)."""

import hashlib
import json
import re
import uuid

import numpy as np
import pytest
from clirunner import station_proc
from station.mocks.canopen.emulator import CanopenEmulator
from station.mocks.tracker.config import tracker_config
from station.mocks.tracker.server import TrackerServer
from station.mocks.world import World

from station.api import resume
from station.api import run as start
from station.engine import read_journal
from station.kinematics import se3
from station.report import write_report
from station.robot.errors import ConfigError
from station.solver.map import CorrectionMap, MapError
from tests.procedures.test_correction_map_calibration import _true_pose, calibration_file

SIGMA_0, SIGMA_PER_M = 15e-6, 6e-6  # the tracker's specification (docs/hardware.md), 1 sigma per reflector, axis
SERIAL = "A6-0014"
START = np.array([0.0, 0.17, 0.17, 0.0, -0.87, 0.0])  # rad: the bent-elbow work zone
SPAN = np.radians(10.0)
MASS = 15.0  # kg at the tool centre point
JOINTS = {"compliance": {"j2": 2e-5, "j3": 3e-5, "j5": 4e-5}, "backlash": {"j1": 3e-4, "j2": 3e-4, "j3": 3e-4},
          "payload": MASS}  # rad/(N m), rad, kg: as bench/map.py part f
PAYLOAD = {"mass": MASS, "com": [0.0, 0.0, 0.0]}


def _world():
    return World.default("arm6", seed=7, start=START, joints=JOINTS)


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """The world, the tracker's configuration and the calibration file with compliance parameters."""
    tmp = tmp_path_factory.mktemp("payload")
    world = _world()
    cfg = tracker_config({})
    cal = calibration_file(world, cfg, tmp, ("--payload", "15kg", "--identify", "offsets,dh,tcp,compliance"))
    doc = json.loads(cal.read_text())
    params = {n: p["value"] for n, p in doc["parameters"].items() if p["kind"] == "model" and p["identifiable"]}
    assert {"compliance.j2", "compliance.j3"} <= set(params)  # what this test is about (j5: not in this box)
    return world, cfg, cal, params


def _cli(tmp_path, *args):
    return station_proc(*args, "-q", "--db", f"sqlite:///{tmp_path / 'r.db'}", timeout=60,
                        env={"STATION_HOME": str(tmp_path / "home")})


def test_run_refuses_a_compliance_calibration_without_payload_before_the_robot_opens(rig, tmp_path):
    """``station run correction_map --calibration`` with compliance parameters: without ``--payload`` one line, exit
    2, naming the file and the parameter, before the robot URL is even opened (a robot that does not exist); with
    ``--payload 15kg`` the calibration passes and it is the (absent) robot that fails; a bad payload is one line."""
    _, _, cal, _ = rig
    robot = "canopen+socketcand://127.0.0.1:9?channel=can0&model=arm6"
    base = ["run", "correction_map", "--robot", robot, "--serial", "X", "--tracker", "tcp://127.0.0.1:9",
            "--calibration", str(cal)]
    for extra, expect in (([], "compliance."), (["--payload", "15"], "--payload '15'")):
        r = _cli(tmp_path, *base, *extra)
        assert r.code == 2, r.err
        lines = r.err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("station: error: ") and expect in lines[0], lines
        if not extra:
            assert str(cal) in lines[0] and "--payload" in lines[0]
    r = _cli(tmp_path, *base, "--payload", "15kg")
    assert r.code == 2 and "calibration" not in r.err.splitlines()[0] and "compliance" not in r.err, \
        r.err  # past the calibration check: the robot at 127.0.0.1:9 is what fails
    # the result records the load it was solved under; another one is refused, naming both
    assert json.loads(cal.read_text())["settings"]["payload"] == PAYLOAD
    r = _cli(tmp_path, *base, "--payload", "10kg")
    lines = r.err.strip().splitlines()
    assert r.code == 2 and len(lines) == 1 and "settings.payload" in lines[0] and "15 kg" in lines[0] \
        and "10 kg" in lines[0], lines


def _session(tmp_path, monkeypatch, world, options, progress=None):
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    world.command_q(START)
    channel = f"mp{uuid.uuid4().hex[:8]}"
    emu = CanopenEmulator(world, "virtual", channel).start()
    # contact=none: this cell measures with the tracker and has no touch input wired; subscribed, the emulator would
    # work out the world's true (gravity-deflected) tip for that input's TPDO every 10 ms, ~3/4 of this file's CPU
    url = f"canopen+virtual://{channel}?nodes=1-6&model=arm6&serial={SERIAL}&contact=none"
    db = f"sqlite:///{tmp_path / 'records.db'}"
    try:
        with TrackerServer(world, tracker_config({}), seed=11) as trk:
            out = start("correction_map", url, SERIAL, db=db, report=False, progress=progress,
                        options={"tracker": trk.url, "grid": 1, "span_deg": 10, **options})
            measured = trk.measurements
            if out.status == "interrupted":  # the same tracker and robot: what a technician resumes on
                with pytest.raises(ConfigError, match="was run with 15 kg"):  # another payload: refused
                    resume(out.session, db=db, report=False, payload={"mass": 10.0, "com": [0, 0, 0]})
                out = resume(out.session, db=db, report=False, payload={"mass": 15.0, "com": [0, 0, 0]})
                for _ in range(2):  # a CAN timeout of the shared CI machine: resumed again, as a technician would
                    if out.status != "error" or "canopen" not in str(out.error):
                        break
                    out = resume(out.session, db=db, report=False)
                measured = trk.measurements
    finally:
        emu.stop()
    return out, measured


def test_a_compliance_calibration_is_refused_without_payload_before_motion(rig, tmp_path, monkeypatch):
    """Through the API (no CLI pre-check): the procedure itself refuses it, one line, nothing measured or moved;
    a resume of that session given a payload is refused (it was run without one)."""
    world, _, cal, _ = rig
    out, measured = _session(tmp_path, monkeypatch, world, {"calibration": str(cal)})
    assert out.status == "error" and out.exit_code == 2
    msg = str(out.error)
    assert "\n" not in msg and "compliance." in msg and "--payload" in msg and str(cal) in msg, msg
    assert measured == 0 and np.allclose(world.encoder_q(), START, atol=1e-6)  # the arm did not move
    _, events = read_journal(out.folder / "journal.jsonl")
    assert not [e for e in events if e.type in ("calibration", "instrument", "plan", "sample")]
    with pytest.raises(ConfigError, match="without a payload"):
        resume(out.session, report=False, store=False, payload=PAYLOAD)
    for arg, expect in (("15kg", "was run without a payload"), ("15", "--payload '15'")):  # the CLI: one line
        r = _cli(tmp_path, "resume", out.session, "--payload", arg)
        lines = r.err.strip().splitlines()
        assert r.code == 2 and len(lines) == 1 and lines[0].startswith("station: error: --payload"), r.err
        assert expect in lines[0], lines


def test_map_on_a_compliance_calibration_uses_the_payload(rig, tmp_path, monkeypatch):
    """With the payload: the session is interrupted after 20 configurations and resumed (another payload refused,
    the same one accepted); the calibration is applied WITH its compliance deflection: the calibrated-only
    held-out error the procedure judged is what the world's truth gives for the calibrated model under 15 kg, and
    far from what the same parameters give without the deflection."""
    world, cfg, cal, params = rig

    def ctrl_c(done, total, text):
        if done == 20:
            raise KeyboardInterrupt  # the operator's Ctrl-C

    out, measured = _session(tmp_path, monkeypatch, world, {"calibration": str(cal), "payload": PAYLOAD}, ctrl_c)
    assert out.status == "completed", out.error
    rec = out.record
    assert measured == len(rec["samples"]) == 64 + 12  # every configuration measured once, across the resume
    _, events = read_journal(out.folder / "journal.jsonl")
    cal_ev = [e.data for e in events if e.type == "calibration"]
    assert len(cal_ev) == 1 and cal_ev[0]["payload"] == PAYLOAD and cal_ev[0]["parameters"] == params
    stored = rec["correction_map"]
    assert stored["payload"] == PAYLOAD and stored["calibration"]["parameters"] == params
    cmap = CorrectionMap.from_dict(stored["map"])
    assert cmap.calibration["parameters"] == params
    heavy = world.nominal.with_payload(MASS)  # the model the map belongs to carries the payload
    assert {"compliance.j2", "compliance.j3", "compliance.j5"} <= set(cmap.nominal)  # the payload model: all
    with pytest.raises(MapError, match="15 kg.*no payload"):
        cmap.measure(world.nominal, np.array([START]))  # the weightless model is not the map's
    assert cmap.payload == PAYLOAD  # the map records the load it was built under ...
    with pytest.raises(MapError, match="15 kg.*10 kg"):  # ... and another load is not its model either
        cmap.measure(world.nominal.with_payload(10.0), np.array([START]))
    # the same from the command line: station map correct takes the payload the map was built with
    (tmp_path / "map.json").write_text(json.dumps(stored["map"]))
    (tmp_path / "q.csv").write_text("x1,x2,x3,x4,x5,x6\n" + ",".join(str(v) for v in START) + "\n")
    cmd = ["map", "correct", "--model", "arm6", "--map", str(tmp_path / "map.json"), "--joints",
           str(tmp_path / "q.csv"), "--out", str(tmp_path / "poses.csv")]
    for extra, rc in (([], 2), (["--payload", "10kg"], 2), (["--payload", "15kg"], 0)):
        r = station_proc(*cmd, *extra, timeout=60)
        assert r.code == rc, (extra, r.err)
        assert rc == 0 or (len(r.err.strip().splitlines()) == 1 and "payload" in r.err), r.err

    # truth from the world, in the tracker's frame, seen through the session's registration: a replica of the world
    # (same seed, same hidden errors), since the session left the emulated drives disabled
    held = [smp for smp in rec["samples"] if smp["set"] == "holdout"]
    x = np.array([smp["q"] for smp in held])
    replica = _world()
    true_t = se3.invert(cfg.tracker_in_base) @ np.array([_true_pose(replica, q) for q in x])
    floor = np.sqrt(3) * (SIGMA_0 + SIGMA_PER_M * np.linalg.norm(true_t[:, :3, 3], axis=1).max())
    e_read = np.linalg.norm(np.array([smp["measured"] for smp in held]) - true_t[:, :3, 3], axis=1)
    assert np.sqrt(np.mean(e_read ** 2)) < 2 * floor  # the replica is the world the tracker measured
    reg = se3.invert(se3.pose_to_matrix(np.array(stored["registration"]["instrument_in_base"])))
    rigid = {n: v for n, v in params.items() if not n.startswith("compliance.")}

    def rms(model):
        e = np.linalg.norm((reg @ model.fk(x))[:, :3, 3] - true_t[:, :3, 3], axis=1)
        return float(np.sqrt(np.mean(e ** 2)))

    with_c = rms(heavy.with_params(params))
    without_c = rms(world.nominal.with_params(rigid))  # the same parameters, no deflection under the load
    assert without_c > 3 * with_c + 3 * floor, (with_c, without_c, floor)  # the compliance term matters here
    meas = {m["name"]: m for m in rec["verdict"]["measurements"]}
    judged = meas["holdout_calibrated_rms"]["value"] * 1e-3
    assert abs(judged - with_c) < 0.25 * with_c + floor, (judged, with_c, without_c)
    assert meas["calibration_parameters"]["value"] == len(params)

    # the report shows the calibration the map was built on and the held-out rows side by side
    html = write_report(rec, tmp_path / "report").read_text()
    section = html[html.index('<h2>Correction map</h2>'):html.index('<h2>Pose coverage</h2>')]
    sha = hashlib.sha256(cal.read_bytes()).hexdigest()  # of the file as given, computed here
    assert f"<code>{cal.name}</code>" in section and f"<code title=\"{sha}\">{sha[:12]}</code>" in section
    assert f"{len(params)} parameters (" in section and "15 kg at [0, 0, 0] mm" in section
    rows = dict(re.findall(r'<tr><td>([a-z +]+?)(?: <span class="note">\(judged\)</span>)?</td>(.*?)</tr>',
                           section[section.index('id="map-holdout"'):]))
    cells = {k: re.findall(r'<td class="n">([^<]*)</td>', v) for k, v in rows.items()}
    assert list(cells) == ["nominal model", "calibrated only", "calibrated + map"]
    for row, names in (("calibrated only", ("holdout_calibrated_rms", "holdout_calibrated_max",
                                            "holdout_calibrated_rotation_rms")),
                       ("calibrated + map", ("holdout_rms", "holdout_max", "holdout_rotation_rms"))):
        assert cells[row] == [f"{meas[n]['value']:.4f}" for n in names], (row, cells[row])
    assert cells["nominal model"][0] == f"{meas['holdout_nominal_rms']['value']:.4f}"


def test_a_payload_on_a_parallel_robot_is_refused_before_motion(tmp_path, monkeypatch):
    """A hexapod's model has no joint compliance for a payload to load: one line, nothing measured or moved."""
    from station.mocks.launch import launch

    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    world = World.default("hexapod", seed=7)
    q0 = world.encoder_q().copy()
    with launch("canopen", world, serial="HX-0043") as emu, TrackerServer(world, tracker_config({}), seed=11) as trk:
        out = start("correction_map", emu.url, "HX-0043", db=f"sqlite:///{tmp_path / 'r.db'}", report=False,
                    options={"grid": 1, "tracker": trk.url, "payload": PAYLOAD})
        measured = trk.measurements
    assert out.status == "error" and out.exit_code == 2
    assert "\n" not in str(out.error) and "--payload" in str(out.error) and "hexapod" in str(out.error), out.error
    assert measured == 0 and np.array_equal(world.encoder_q(), q0)
