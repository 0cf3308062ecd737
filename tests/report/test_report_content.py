"""Report content (report.json) and the self-contained HTML: numbers checked against the simulated session."""

from __future__ import annotations

import base64
import copy
import json
import math
import re

import numpy as np
import pytest

from station.kinematics import load_model
from station.records import measurement_status, overall_status
from station.report import ReportError, build_report, write_report


@pytest.fixture(scope="module")
def session(session_factory):
    return session_factory(seed=11)[0]


@pytest.fixture(scope="module")
def written(session, tmp_path_factory):
    folder = tmp_path_factory.mktemp("report")
    path = write_report(session, folder)
    return folder, path, json.loads((folder / "report.json").read_text()), path.read_text()


def test_json_is_strict_si_and_complete(written, session):
    folder, path, rep, _ = written
    assert path == folder / "report.html"
    json.loads((folder / "report.json").read_text(), parse_constant=lambda c: pytest.fail(f"non-JSON {c}"))
    assert rep["format"] == "station-report/1" and rep["units"].startswith("SI")
    h = rep["header"]
    for key in ("serial", "procedure", "operator", "station", "started", "finished"):
        assert h[key] == session[key]
    assert h["robot"]["vendor"] == "Universal Robots"
    assert h["duration_s"] == pytest.approx(5 * len(session["samples"]) + 20)
    assert (h["n_fit"], h["n_holdout"]) == (16, 4)
    assert rep["overall"] == overall_status(session["verdict"])
    names = {p["name"]: p for p in rep["parameters"]}
    j2 = session["result"]["parameters"]["offset.j2"]
    assert names["offset.j2"]["correction"] == pytest.approx(j2["value"] - j2["nominal"])
    assert names["offset.j2"]["unit"] == "rad" and names["point.A.x"]["unit"] == "m"
    assert names["point.A.x"]["nominal"] is None  # NaN nominal -> null, not invalid JSON
    assert {u["name"]: u["reason"] for u in rep["unidentifiable"]} == session["result"]["unidentifiable"]
    wb = {w["name"]: w for w in rep["writeback"]["values"]}
    assert wb["offset.j3"]["change"] == pytest.approx(session["result"]["parameters"]["offset.j3"]["value"])
    assert rep["writeback"]["applied"] and rep["writeback"]["verified"]


def test_recovered_offsets_match_hidden_truth_within_reported_uncertainty(written, session_factory):
    _, _, rep, _ = written
    _, hidden = session_factory(seed=11)
    for p in rep["parameters"]:
        if p["name"] in hidden and p["identifiable"]:
            assert abs(p["value"] - hidden[p["name"]]) < 4 * p["std"], p


def test_per_pose_residuals_recomputed_agree_with_the_fit(written, session):
    """The report recomputes per-pose residuals from samples + model; the session fixture computed its own
    during the fit (independently): they must agree, and holdout poses are included."""
    _, _, rep, _ = written
    pp = rep["residuals"]["per_pose"]
    assert pp["source"].startswith("recomputed")
    res = session["result"]["residuals"]
    n_fit = len(res["per_sample_after_m"])
    np.testing.assert_allclose(pp["before_m"][:n_fit], res["per_sample_before_m"], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(pp["after_m"][:n_fit], res["per_sample_after_m"], rtol=1e-6, atol=1e-9)
    assert pp["set"].count("holdout") == 4
    ho = np.array(pp["after_m"][n_fit:])
    assert math.sqrt(np.mean(ho**2)) == pytest.approx(session["result"]["holdout"]["rms_m"], rel=1e-6)
    assert pp["seq"] == [s["seq"] for s in session["samples"]]


def test_per_pose_from_solver_arrays_when_model_is_unknown(session):
    s = copy.deepcopy(session)
    s["model"] = "no-such-model"
    s["result"]["model"] = "no-such-model"
    s["robot"]["model"] = "no-such-model"
    rep = build_report(s)
    pp = rep["residuals"]["per_pose"]
    assert pp["source"] == "solver" and pp["after_m"] == s["result"]["residuals"]["per_sample_after_m"]
    assert rep["coverage"]["tool"] is None and "could not be loaded" in rep["coverage"]["model_note"]
    assert rep["coverage"]["joints"][0]["lower"] is None


def test_coverage_matches_samples_and_limits(written, session):
    _, _, rep, _ = written
    model = load_model("ur5e")
    q = np.array([s["q"] for s in session["samples"]])
    for i, j in enumerate(rep["coverage"]["joints"]):
        assert j["min"] == pytest.approx(q[:, i].min()) and j["max"] == pytest.approx(q[:, i].max())
        assert j["fraction"] == pytest.approx((q[:, i].max() - q[:, i].min()) / (model.upper[i] - model.lower[i]))
    z = model.fk(q)[:, :3, 2]
    angles = np.degrees(np.arccos(np.clip(z @ z.T, -1, 1)))
    assert rep["coverage"]["tool"]["max_pairwise_deg"] == pytest.approx(angles.max())


@pytest.mark.parametrize("m, status", [
    ({"value": 0.05, "low": None, "high": 0.1, "marginal": 0.02, "passed": True}, "PASS"),
    ({"value": 0.09, "low": None, "high": 0.1, "marginal": 0.02, "passed": True}, "MARGINAL"),
    ({"value": -0.95, "low": -1.0, "high": 1.0, "marginal": 0.1, "passed": True}, "MARGINAL"),
    ({"value": 0.11, "low": None, "high": 0.1, "marginal": 0.02, "passed": False}, "FAIL"),
    ({"value": 0.11, "low": None, "high": 0.1}, "FAIL"),  # no 'passed': judged from the limits
    ({"value": 0.05, "high": 0.1, "marginal": True, "passed": True}, "MARGINAL"),
    ({"value": 0.05, "high": 0.1, "passed": True, "status": "marginal"}, "MARGINAL"),  # engine's word wins
])
def test_measurement_status(m, status):
    assert measurement_status(m) == status


def test_overall_status():
    assert overall_status(None) == "NONE"
    assert overall_status({"passed": False, "measurements": []}) == "FAIL"
    assert overall_status({"passed": True, "measurements": [{"value": 1, "high": 2, "marginal": 1.5,
                                                              "passed": True}]}) == "MARGINAL"


def test_html_is_self_contained_with_decodable_pngs(written):
    _, _, rep, html = written
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", html, re.I)
    assert "<script" not in html.lower() and "@import" not in html and "url(" not in html
    assert "default-src 'none'" in html  # the browser itself refuses anything external
    imgs = re.findall(r'src="data:image/png;base64,([^"]+)"', html)
    assert len(imgs) == 5
    alts = re.findall(r'<img alt="([^"]+)"', html)
    assert alts == ["parameter corrections with error bars", "residual per pose before and after", "error histogram",
                    "joint-space coverage", "tool orientation spread"]
    for b in imgs:
        assert base64.b64decode(b)[:8] == b"\x89PNG\r\n\x1a\n"
    for text in ("offset.j2", "not separable from the unknown reference point position", "rms_after", "PASS",
                 "eol-station-3", "j.doe", "Universal Robots"):
        assert text in html
    # corrections shown in deg for people (the JSON keeps rad)
    j2 = next(p for p in rep["parameters"] if p["name"] == "offset.j2")
    assert f"{math.degrees(j2['correction']):.4f}" in html
    # each sample row carries its own error after calibration (mm), so a bad touch can be found
    pp = rep["residuals"]["per_pose"]
    row = re.search(rf'<td class="n">{pp["seq"][-1]}</td>.*?</tr>', html, re.S).group(0)
    assert f"{pp['after_m'][-1] * 1e3:.4f}" in row and f"{pp['before_m'][-1] * 1e3:.4f}" in row


def test_session_without_result_still_reports(tmp_path, session):
    s = copy.deepcopy(session)
    s.update(result=None, verdict=None, writeback=None, finished=None)
    path = write_report(s, tmp_path / "r")
    html = path.read_text()
    assert "No solver result in this session." in html and "NO VERDICT" in html
    rep = json.loads((tmp_path / "r" / "report.json").read_text())
    assert rep["overall"] == "NONE" and rep["residuals"]["per_pose"]["before_m"] == []
    assert len(rep["coverage"]["joints"]) == 6  # the samples still show their coverage


def test_failing_verdict_is_shown(tmp_path, session):
    s = copy.deepcopy(session)
    s["verdict"]["measurements"][0].update(value=0.5, passed=False)
    s["verdict"]["passed"] = False
    html = write_report(s, tmp_path).read_text()
    assert 'class="banner FAIL"' in html and 'class="st FAIL">FAIL<' in html


@pytest.mark.parametrize("bad", [None, [], {"serial": "X"}])
def test_bad_session_is_a_one_line_error(tmp_path, bad):
    with pytest.raises(ReportError, match="session record must be a dict"):
        write_report(bad, tmp_path)
    assert not (tmp_path / "report.html").exists()


def test_report_with_the_real_solver_result(session, tmp_path):
    """Contract check against station.solver: the report's per-pose residuals reproduce the solver's own
    summary numbers (fit before/after RMS and max, holdout RMS before/after)."""
    from station.solver import Observations, solve

    s = copy.deepcopy(session)
    fit = np.array([x["q"] for x in s["samples"] if x["set"] == "fit"])
    ho = np.array([x["q"] for x in s["samples"] if x["set"] == "holdout"])
    res = solve(load_model("ur5e"), Observations(fit), identify="offsets", holdout=Observations(ho)).to_dict()
    s["result"] = json.loads(json.dumps(res))
    write_report(s, tmp_path)
    rep = json.loads((tmp_path / "report.json").read_text())
    pp = rep["residuals"]["per_pose"]
    b, a, is_fit = np.array(pp["before_m"]), np.array(pp["after_m"]), np.array(pp["set"]) == "fit"

    def rms(x):
        return math.sqrt(np.mean(x**2))

    r = res["residuals"]
    assert rms(b[is_fit]) == pytest.approx(r["rms_before_m"], rel=1e-6)
    assert rms(a[is_fit]) == pytest.approx(r["rms_after_m"], rel=1e-6)
    assert a[is_fit].max() == pytest.approx(r["max_after_m"], rel=1e-6)
    assert rms(a[~is_fit]) == pytest.approx(res["holdout"]["rms_m"], rel=1e-6)
    assert rms(b[~is_fit]) == pytest.approx(res["holdout"]["rms_nominal_m"], rel=1e-6)
    unid = {u["name"] for u in rep["unidentifiable"]}
    assert unid == {n for n, p in res["parameters"].items() if not p["identifiable"]}


def test_report_with_instrument_measurements(session):
    """With an external instrument the report compares the calibrated tip, in the instrument frame the solver
    found, with the measured points: it reproduces the solver's fit residual."""
    from station.solver import Observations, solve

    rng = np.random.default_rng(3)
    nominal = load_model("ur5e")
    truth = nominal.with_params({"offset.j2": 0.002, "offset.j3": -0.001})
    q = np.clip(np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.0]) + rng.uniform(-0.6, 0.6, (24, 6)),
                nominal.lower, nominal.upper)
    c, s = math.cos(0.3), math.sin(0.3)
    rot, shift = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]), np.array([1.0, 0.2, -0.1])
    measured = (truth.position(q) - shift) @ rot + rng.normal(0, 20e-6, (len(q), 3))  # instrument frame
    res = solve(nominal, Observations(q, measured=measured), identify="offsets").to_dict()
    sess = copy.deepcopy(session)
    sess["samples"] = [{"type": "sample", "seq": i, "q": qi.tolist(), "measured": mi.tolist(), "set": "fit",
                        "point": "A", "pose": i} for i, (qi, mi) in enumerate(zip(q, measured, strict=True))]
    sess["result"] = json.loads(json.dumps(res))
    pp = build_report(sess)["residuals"]["per_pose"]
    assert "instrument" in pp["source"]
    after = np.array(pp["after_m"])
    assert math.sqrt(np.mean(after**2)) == pytest.approx(res["residuals"]["rms_after_m"], rel=1e-6)
    assert after.max() == pytest.approx(res["residuals"]["max_after_m"], rel=1e-6)
    assert np.mean(pp["before_m"]) > 3 * np.mean(after)  # the uncalibrated robot is visibly worse


def test_prismatic_offset_is_a_length(tmp_path, session):
    s = copy.deepcopy(session)
    s.update(model="scara", samples=[], result=None, verdict=None,
             writeback={"before": {"offset.j1": 0.1, "offset.j3": 0.010}, "after": {"offset.j1": 0.1002,
                                                                                   "offset.j3": 0.0105},
                        "applied": True, "verified": True})
    s["robot"]["model"] = "scara"
    html = write_report(s, tmp_path).read_text()
    rows = {w["name"]: w for w in json.loads((tmp_path / "report.json").read_text())["writeback"]["values"]}
    assert rows["offset.j3"]["unit"] == "m" and rows["offset.j1"]["unit"] == "rad"
    assert "10.5000" in html and "0.5000" in html  # mm
    assert f"{math.degrees(0.1002):.4f}" in html  # deg


def test_informational_measurement_shows_no_limit_not_pass(tmp_path, session):
    """A measurement without low/high was never judged: the table says "— no limit", never PASS; judged
    measurements keep their result and a NO LIMITS session's banner stays NO LIMITS."""
    s = copy.deepcopy(session)
    judged = [m["name"] for m in s["verdict"]["measurements"]]
    s["verdict"]["measurements"].append({"name": "fit_max", "value": 4e-5, "unit": "m", "low": None, "high": None,
                                         "marginal": False, "passed": True, "note": "no limit (informational)"})
    path = write_report(s, tmp_path / "a")
    rep = json.loads((tmp_path / "a" / "report.json").read_text())
    st = {m["name"]: m["status"] for m in rep["verdict"]["measurements"]}
    assert st["fit_max"] == "NO LIMIT"
    assert all(st[n] in ("PASS", "MARGINAL") for n in judged)
    row = re.search(r"<tr><td>fit_max</td>.*?</tr>", path.read_text(), re.S).group(0)
    assert "— no limit" in row and "PASS" not in row
    # a session with no limits at all (every measurement informational)
    s["verdict"] = {"passed": None, "status": "NO LIMITS", "measurements": [
        {**m, "low": None, "high": None, "marginal": False, "passed": True} for m in s["verdict"]["measurements"]]}
    html = write_report(s, tmp_path / "b").read_text()
    table = re.search(r'<table id="verdict">.*?</table>', html, re.S).group(0)
    assert ">PASS<" not in table and table.count("— no limit") == len(s["verdict"]["measurements"])
    assert 'class="banner NO_LIMITS"' in html
