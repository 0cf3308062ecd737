"""``station model export --calibration`` from a result JSON, a session's report.json and a session folder: the
same calibrated robot whichever it is given (the report lists its parameters as rows), the model from the
session when no name is given, and one-line errors naming the fix."""

from __future__ import annotations

import json

import numpy as np
from clirunner import station_proc

from station.kinematics import load_model
from station.report import build_report
from station.safeio import dumps_json


def station(*args):
    """``station ARGS`` as a child process: exit code, stdout, stderr lines."""
    r = station_proc(*args)
    return r.code, r.out, r.err_lines


def test_result_report_and_session_give_the_same_calibrated_robot(tmp_path, session_factory):
    session, hidden = session_factory(seed=7)
    result = session["result"]
    folder = tmp_path / "sessions" / session["session"]
    folder.mkdir(parents=True)
    (tmp_path / "result.json").write_text(dumps_json(result))
    (tmp_path / "report.json").write_text(dumps_json(build_report(session)))
    outs = {}
    for name, src in (("result", tmp_path / "result.json"), ("report", tmp_path / "report.json")):
        rc, out, err = station("model", "export", "ur5e", "--calibration", src, "--out", tmp_path / f"{name}.urdf")
        assert rc == 0, err
        outs[name] = load_model(str(tmp_path / f"{name}.urdf"))
    rc, out, err = station("model", "export", "--calibration", tmp_path / "result.json", "--out", tmp_path / "b.yaml")
    assert rc == 0, err  # a bare result of a built-in model: the name comes from the result
    outs["bare"] = load_model(str(tmp_path / "b.yaml"))
    q = np.random.default_rng(1).uniform(-3, 3, size=(50, 6))
    want = load_model("ur5e").with_params({n: p["value"] for n, p in result["parameters"].items()
                                           if p["kind"] == "model" and p["identifiable"]}).position(q)
    for name, m in outs.items():
        np.testing.assert_allclose(m.position(q), want, atol=1e-9, err_msg=name)
    # the identified zeros are the calibration's, and nearer the hidden truth than the nominal zeros
    for n, p in result["parameters"].items():
        if n.startswith("offset.") and p["identifiable"]:
            assert abs(p["value"] - hidden[n]) < 5 * p["std"] < abs(hidden[n])


def test_export_errors_name_the_fix(tmp_path, session_factory):
    session, _ = session_factory(seed=7)
    (tmp_path / "result.json").write_text(dumps_json(session["result"]))
    rc, _, err = station("model", "export", "arm6", "--calibration", tmp_path / "result.json")
    assert rc == 2 and len(err) == 1 and "for model 'ur5e', not 'arm6'" in err[0], err
    report = build_report({**session, "result": None})
    (tmp_path / "report.json").write_text(json.dumps(report))
    rc, _, err = station("model", "export", "ur5e", "--calibration", tmp_path / "report.json")
    assert rc == 2 and len(err) == 1 and "holds no solve result" in err[0], err
    rc, _, err = station("model", "export", "--calibration", "no-such-session")
    assert rc == 2 and len(err) == 1 and "no-such-session" in err[0], err
