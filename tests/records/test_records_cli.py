"""``station records list|show`` and ``station report`` (from a real engine journal)."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import pytest
from clirunner import station_main, station_proc

from station.records import open_records


@pytest.fixture
def db(tmp_path, session_factory):
    url = f"sqlite:///{tmp_path / 'station.db'}"
    with open_records(url) as rec:
        for seed, serial in ((1, "UR5E-A"), (2, "UR5E-A"), (3, "UR5E-B")):
            rec.store_session(session_factory(seed=seed, serial=serial)[0])
    return url


def test_list_robots_and_sessions(db, session_factory):
    code, out, err = station_main("records", "list", "--db", db, columns=200)
    assert code == 0, out
    assert "UR5E-A" in out and "UR5E-B" in out and "Universal Robots" in out
    code, out, err = station_main("records", "list", "--db", db, "--serial", "UR5E-A", columns=200)
    assert code == 0, out
    s1, s2 = session_factory(seed=1, serial="UR5E-A")[0], session_factory(seed=2, serial="UR5E-A")[0]
    assert s1["session"] in out and s2["session"] in out and "UR5E-B" not in out
    rms = s2["result"]["residuals"]["rms_after_m"] * 1e3
    assert f"{rms:.4f}" in out and "PASS" in out


def test_show_latest_session_in_mm_and_deg(db, session_factory):
    code, out, err = station_main("records", "show", "UR5E-A", "--db", db, columns=200)
    assert code == 0, out
    s2 = session_factory(seed=2, serial="UR5E-A")[0]
    j2 = s2["result"]["parameters"]["offset.j2"]
    assert f"{math.degrees(j2['value']):.4f}" in out and f"{math.degrees(j2['std']):.4f}" in out
    assert "not identifiable" in out and "Write-back (applied, verified)" in out and "rms_after" in out
    code, out, err = station_main("records", "show", "UR5E-A", "--db", db, "--session",
                     session_factory(seed=1, serial="UR5E-A")[0]["session"], columns=200)
    assert code == 0 and "Session 20261121-0001-UR5E-A" in out


@pytest.mark.parametrize("args, message", [
    (["records", "show", "NOPE"], "no records for serial 'NOPE'"),
    (["records", "list", "--serial", "NOPE"], "no records for serial 'NOPE'"),
    (["records", "show", "UR5E-A", "--session", "20261121-0003-UR5E-B"], "not a session of robot 'UR5E-A'"),
])
def test_unknown_serial_or_session_exit_2_one_line(db, args, message):
    code, out, err = station_main(*args, "--db", db, columns=200)
    assert code == 2 and not out
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert lines == [f"station: error: {lines[0].split('station: error: ', 1)[1]}"] and message in lines[0]


@pytest.mark.parametrize("url", ["nonsense", "postgresql+psycopg://x@127.0.0.1:1/none"])
def test_bad_db_url_exit_2_one_line(url):
    code, out, err = station_main("records", "list", "--db", url, columns=200)
    assert code == 2 and not out
    assert len(err.strip().splitlines()) == 1 and err.startswith("station: error: ")


def test_installed_command_exit_code_for_unknown_serial(db):
    """Through the installed entry point (``station.cli:main``), as a shell script or EOL line sees it."""
    out = station_proc("records", "show", "NOPE", "--db", db, timeout=60, env={"COLUMNS": "200"})
    assert out.err.strip() == f"station: error: no records for serial 'NOPE' in {db}"
    assert out.code == 2


def _write_journal(folder: Path, session: dict) -> Path:
    from station.engine import events as ev
    from station.engine.journal import Journal

    header = {k: session[k] for k in ("session", "serial", "procedure", "procedure_sha256", "station", "operator",
                                      "robot", "model")}
    path = folder / "journal.jsonl"
    with Journal.create(path, header) as j:
        for s in session["samples"]:
            j.append({k: v for k, v in s.items() if k != "seq"})
        j.append({"type": "result", "result": session["result"]})
        j.append({"type": "verdict", **session["verdict"]})
        wb = session["writeback"]
        j.append(ev.Writeback(phase="pre-image", before=wb["before"], after=wb["after"]))
        j.append(ev.Writeback(phase="written", before=wb["before"], after=wb["after"], readback=wb["after"],
                              applied=True))
        j.append(ev.Writeback(phase="verified", verified=wb["verified"], check={"passed": wb["verified"]}))
        j.append(ev.End(status="completed", passed=session["verdict"]["passed"]))
    return path


def test_report_from_journal(tmp_path, session_factory, monkeypatch):
    session, _ = session_factory(seed=13)
    folder = tmp_path / "sessions" / session["session"]
    _write_journal(folder, session)
    code, out, err = station_main("report", str(folder), columns=200)
    assert code == 0, out
    assert out.strip() == str(folder / "report.html")
    rep = json.loads((folder / "report.json").read_text())
    assert rep["header"]["serial"] == session["serial"] and rep["overall"] == "PASS"
    assert rep["header"]["n_samples"] == len(session["samples"])
    pp = rep["residuals"]["per_pose"]
    n_fit = len(session["result"]["residuals"]["per_sample_after_m"])
    assert pp["after_m"][:n_fit] == pytest.approx(session["result"]["residuals"]["per_sample_after_m"], rel=1e-6)

    out_dir = tmp_path / "elsewhere"
    code, out, err = station_main("report", str(folder / "journal.jsonl"), "--out", str(out_dir), columns=200)
    assert code == 0 and (out_dir / "report.html").is_file()
    # the session id, as station resume takes it: looked up in $STATION_HOME/sessions
    home = tmp_path / "home"
    (home / "sessions").mkdir(parents=True)
    shutil.copytree(folder, home / "sessions" / "S-1")
    monkeypatch.setenv("STATION_HOME", str(home))
    code, out, err = station_main("report", "S-1", "--out", str(tmp_path / "by-id"), columns=200)
    assert code == 0 and (tmp_path / "by-id" / "report.html").is_file(), out


@pytest.mark.parametrize("make, message", [
    (lambda p: p, "no journal at"),
    (lambda p: (p.mkdir(), p)[1], "no journal at"),
    (lambda p: (p.write_text("not json\n"), p)[1], ""),
])
def test_report_bad_input_exit_2(tmp_path, make, message):
    target = make(tmp_path / "x")
    code, out, err = station_main("report", str(target), columns=200)
    assert code == 2 and err.startswith("station: error: ") and message in err
    assert len(err.strip().splitlines()) == 1
