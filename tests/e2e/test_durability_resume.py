"""Resume safety and the end of a run: the procedure file is hashed before it is imported, the header
fields resume acts on are checked; a fault between the last sample and the end is an error, never PASS."""

import hashlib
import json

import pytest
from clirunner import station_proc
from station.mocks.launch import launch

from station.api import run as start
from station.cli.run_cmd import BUS_OPTIONS, write_demo_files
from station.engine import events as ev
from station.engine import read_journal
from station.engine.journal import Journal


def _journal(home, proc_path, sha, **over):
    folder = home / "sessions" / "S-1"
    fields = dict(session="S-1", procedure="planted", procedure_path=str(proc_path), procedure_sha256=sha,
                  serial="X", url="dynamixel:///dev/does-not-exist?model=omx",
                  limits={"path": None, "version": "v", "sha256": "0" * 64})
    fields.update(over)
    Journal.create(folder / "journal.jsonl", ev.Header(**fields)).close()
    return folder


def _resume(home, **env_extra):
    return station_proc("resume", "S-1", env={"STATION_HOME": str(home), **env_extra}, timeout=60)


def test_a_planted_procedure_is_never_imported(tmp_path):
    marker = tmp_path / "ran"
    planted = tmp_path / "planted.py"
    planted.write_text(f'"""Planted."""\nopen({str(marker)!r}, "w").write("imported")\n'
                       "def checklist(s):\n    pass\n")
    _journal(tmp_path / "home", planted, hashlib.sha256(b"the file the session started with").hexdigest())
    r = _resume(tmp_path / "home", STATION_PROCEDURES=str(tmp_path))  # found by name in a configured folder
    assert r.code == 2 and r.err.count("\n") == 1 and "sha256 differs" in r.err, r.err
    assert not marker.exists()  # refused before import: its code never ran


@pytest.mark.parametrize("field, value, says", [
    ("procedure_sha256", "not-a-hash", "field procedure_sha256"),
    ("url", "", "field url"),
    ("procedure_path", "/etc/passwd", "field procedure_path"),
])
def test_header_fields_are_checked_before_anything_is_loaded(tmp_path, field, value, says):
    planted = tmp_path / "p.py"
    planted.write_text('"""P."""\ndef checklist(s):\n    pass\n')
    over = {field: value}
    sha = hashlib.sha256(planted.read_bytes()).hexdigest()
    _journal(tmp_path / "home", planted, sha, **over)
    r = _resume(tmp_path / "home")
    assert r.code == 2 and r.err.count("\n") == 1 and says in r.err and ":1:" in r.err, r.err


def test_fault_after_the_last_sample_is_an_error_never_pass(tmp_path, monkeypatch):
    """The drives go silent after the last sample (during the solve): the teardown cannot switch compliance
    off; the verdict measured before is not shown as PASS: exit 2 with the reason in one line."""
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    world_path, cell_path, serial = write_demo_files("canopen", tmp_path, seed=24, time_mode="instant")
    with launch("canopen", world_path, serial=serial) as emu:
        def progress(done, total, text):
            if done == total:
                emu.world.faults.inject("disconnect", device=3, count=10_000)

        out = start("zero_offsets", emu.url, serial, cell=cell_path, db=f"sqlite:///{tmp_path / 'r.db'}",
                    options=dict(BUS_OPTIONS["canopen"]), progress=progress)
    assert out.status == "error" and out.exit_code == 2 and out.verdict == "ERROR" and out.passed is None
    assert "\n" not in str(out.error)
    events = read_journal(out.folder / "journal.jsonl")[1]
    assert any(e.type == "verdict" for e in events)  # the checklist got to its verdict ...
    fault = next(e for e in events if e.type == "fault")
    assert fault.teardown or "teardown" in fault.message
    end = events[-1]
    assert end.type == "end" and end.status == "error" and end.passed is None  # ... but the session is no PASS
    assert json.dumps(out.record["status"]) == '"error"'
