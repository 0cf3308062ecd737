"""``station records list|show`` and ``station report`` (from a real engine journal)."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from station.cli import app
from station.records import open_records

runner = CliRunner()


@pytest.fixture
def db(tmp_path, session_factory):
    url = f"sqlite:///{tmp_path / 'station.db'}"
    with open_records(url) as rec:
        for seed, serial in ((1, "UR5E-A"), (2, "UR5E-A"), (3, "UR5E-B")):
            rec.store_session(session_factory(seed=seed, serial=serial)[0])
    return url


def _run(*args: str):
    result = runner.invoke(app, list(args), env={"COLUMNS": "200"})
    return result.exit_code, result.output


def test_list_robots_and_sessions(db, session_factory):
    code, out = _run("records", "list", "--db", db)
    assert code == 0, out
    assert "UR5E-A" in out and "UR5E-B" in out and "Universal Robots" in out
    code, out = _run("records", "list", "--db", db, "--serial", "UR5E-A")
    assert code == 0, out
    s1, s2 = session_factory(seed=1, serial="UR5E-A")[0], session_factory(seed=2, serial="UR5E-A")[0]
    assert s1["session"] in out and s2["session"] in out and "UR5E-B" not in out
    rms = s2["result"]["residuals"]["rms_after_m"] * 1e3
    assert f"{rms:.4f}" in out and "PASS" in out


def test_show_latest_session_in_mm_and_deg(db, session_factory):
    code, out = _run("records", "show", "UR5E-A", "--db", db)
    assert code == 0, out
    s2 = session_factory(seed=2, serial="UR5E-A")[0]
    j2 = s2["result"]["parameters"]["offset.j2"]
    assert f"{math.degrees(j2['value']):.4f}" in out and f"{math.degrees(j2['std']):.4f}" in out
    assert "not identifiable" in out and "Write-back (applied, verified)" in out and "rms_after" in out
    code, out = _run("records", "show", "UR5E-A", "--db", db, "--session",
                     session_factory(seed=1, serial="UR5E-A")[0]["session"])
    assert code == 0 and "Session 20261121-0001-UR5E-A" in out


@pytest.mark.parametrize("args, message", [
    (["records", "show", "NOPE"], "no records for serial 'NOPE'"),
    (["records", "list", "--serial", "NOPE"], "no records for serial 'NOPE'"),
    (["records", "show", "UR5E-A", "--session", "20261121-0003-UR5E-B"], "not a session of robot 'UR5E-A'"),
])
def test_unknown_serial_or_session_exit_2_one_line(db, args, message):
    code, out = _run(*args, "--db", db)
    assert code == 2
    lines = [ln for ln in out.splitlines() if ln.strip()]
    assert lines == [f"station: error: {lines[0].split('station: error: ', 1)[1]}"] and message in lines[0]


@pytest.mark.parametrize("url", ["nonsense", "postgresql+psycopg://x@127.0.0.1:1/none"])
def test_bad_db_url_exit_2_one_line(url):
    code, out = _run("records", "list", "--db", url)
    assert code == 2
    assert len(out.strip().splitlines()) == 1 and out.startswith("station: error: ")


def test_installed_command_exit_code_for_unknown_serial(db):
    """Through the installed entry point (``station.cli:main``), as a shell script or EOL line sees it."""
    exe = Path(sys.executable).with_name("station")
    out = subprocess.run([str(exe), "records", "show", "NOPE", "--db", db], capture_output=True, text=True,
                         timeout=60, env={**os.environ, "COLUMNS": "200"})
    assert out.stderr.strip() == f"station: error: no records for serial 'NOPE' in {db}"
    assert out.returncode == 2


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
    code, out = _run("report", str(folder))
    assert code == 0, out
    assert out.strip() == str(folder / "report.html")
    rep = json.loads((folder / "report.json").read_text())
    assert rep["header"]["serial"] == session["serial"] and rep["overall"] == "PASS"
    assert rep["header"]["n_samples"] == len(session["samples"])
    pp = rep["residuals"]["per_pose"]
    n_fit = len(session["result"]["residuals"]["per_sample_after_m"])
    assert pp["after_m"][:n_fit] == pytest.approx(session["result"]["residuals"]["per_sample_after_m"], rel=1e-6)

    out_dir = tmp_path / "elsewhere"
    code, out = _run("report", str(folder / "journal.jsonl"), "--out", str(out_dir))
    assert code == 0 and (out_dir / "report.html").is_file()
    # the session id, as station resume takes it: looked up in $STATION_HOME/sessions
    home = tmp_path / "home"
    (home / "sessions").mkdir(parents=True)
    shutil.copytree(folder, home / "sessions" / "S-1")
    monkeypatch.setenv("STATION_HOME", str(home))
    code, out = _run("report", "S-1", "--out", str(tmp_path / "by-id"))
    assert code == 0 and (tmp_path / "by-id" / "report.html").is_file(), out


@pytest.mark.parametrize("make, message", [
    (lambda p: p, "no journal at"),
    (lambda p: (p.mkdir(), p)[1], "no journal at"),
    (lambda p: (p.write_text("not json\n"), p)[1], ""),
])
def test_report_bad_input_exit_2(tmp_path, make, message):
    target = make(tmp_path / "x")
    code, out = _run("report", str(target))
    assert code == 2 and out.startswith("station: error: ") and message in out
    assert len(out.strip().splitlines()) == 1
