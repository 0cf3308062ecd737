"""`station resume` of sessions it must not continue: a crashed jog session (no procedure file), and journals that
name code (a planted ``procedure_path``): the procedure is found by name where the station's configuration says
procedures live, and runs only with the journaled sha256 (checked before it is compiled)."""

import hashlib
import os
from pathlib import Path

import numpy as np
import pytest
from clirunner import station_proc

from station.kinematics import load_model
from station.robot import Identity, JointSnapshot
from station.tui.session import session_header, technician_session


def test_resume_of_a_crashed_jog_session_is_a_one_line_error(tmp_path):
    ident = Identity(vendor="ROBOTIS", model="omx", serial="OMX-1")
    header = session_header(identity=ident, model_name="omx", serial="OMX-1", identify="offsets",
                            reference="unknown", url="dynamixel:///dev/null?ids=11-14&model=omx")
    s = technician_session(None, header, folder=tmp_path / "jog", model=load_model("omx"))
    s.add_sample(JointSnapshot(np.zeros(4), (2048,) * 4, "tick", 0.0), "A", pose=0,
                 status={"enabled": True, "touch": True})
    # no close(): the station crashed while the technician was jogging
    p = station_proc("resume", tmp_path / "jog", timeout=60)
    assert p.code == 2
    lines = p.err_lines
    assert len(lines) == 1 and lines[0].startswith("station: error:"), p.err
    assert "no procedure file to resume" in lines[0]
    assert (tmp_path / "jog" / "journal.jsonl").read_text().count('"type":"sample"') == 1  # nothing lost


# ---- data never names code: a journal's procedure is found by name where the station's configuration says ------
def _evil(folder: Path) -> tuple[Path, Path, str]:
    """An attacker's procedure file: importing it or running its checklist leaves a marker file."""
    marker = folder / "attacker-code-ran"
    evil = folder / "evil.py"
    evil.write_text(f'"""Evil."""\nopen({str(marker)!r}, "w").write("import")\n'
                    f"def checklist(s):\n    open({str(marker)!r}, 'w').write('checklist')\n")
    return evil, marker, hashlib.sha256(evil.read_bytes()).hexdigest()


def _plant(home: Path, procedure: str, path: Path, sha: str) -> None:
    from station.engine import events as ev
    from station.engine.journal import Journal

    Journal.create(home / "sessions" / "S-1" / "journal.jsonl", ev.Header(
        session="S-1", procedure=procedure, procedure_path=str(path), procedure_sha256=sha, serial="X",
        url="dynamixel:///dev/does-not-exist?model=omx", limits={"path": None, "version": "v", "sha256": "0" * 64}
    )).close()


@pytest.mark.parametrize("name, says", [
    ("evil", "unknown procedure 'evil'"),  # the attacker's own name: found nowhere the station looks
    ("zero_offsets", "sha256 differs"),  # a shipped name: found, but it is not the attacker's file
    ("../../evil", "field procedure: '../../evil' is not a procedure name"),
])
def test_a_planted_journal_naming_a_file_with_its_own_sha256_runs_nothing(tmp_path, name, says):
    """The journal names ``procedure_path: <tmp>/evil.py`` and that file's sha256 (the old check compared the
    file with itself): ``station resume`` refuses in one line before anything is imported; no code of the
    attacker's ran, even with a site procedure folder configured."""
    evil, marker, sha = _evil(tmp_path)
    (tmp_path / "site").mkdir()
    _plant(tmp_path / "home", name, evil, sha)
    env = {"STATION_HOME": str(tmp_path / "home"), "STATION_PROCEDURES": str(tmp_path / "site")}
    p = station_proc("resume", "S-1", timeout=60, env=env)
    lines = p.err_lines
    assert p.code == 2 and len(lines) == 1 and lines[0].startswith("station: error:"), p.err
    assert says in lines[0], lines[0]
    assert not marker.exists()


def test_resume_finds_procedures_by_name_and_runs_only_the_journaled_bytes(tmp_path, monkeypatch):
    from station.engine.procedure import ProcedureError, procedure_for_resume, resolve_procedure

    site = tmp_path / "site"
    site.mkdir()
    proc = site / "site_check.py"
    marker = tmp_path / "ran"
    proc.write_text(f'"""Site check."""\nVERSION = "2.1"\nopen({str(marker)!r}, "a").write("x")\n'
                    "def checklist(s):\n    pass\n")
    sha = hashlib.sha256(proc.read_bytes()).hexdigest()
    monkeypatch.setenv("STATION_PROCEDURES", "relative/ignored" + os.pathsep + str(site))
    assert resolve_procedure("site_check") == proc
    assert resolve_procedure("zero_offsets").parent.name == "procedures"  # a site folder never shadows a shipped one
    (site / "zero_offsets.py").write_text('"""Shadow."""\ndef checklist(s):\n    pass\n')
    assert resolve_procedure("zero_offsets").parent != site
    with pytest.raises(ProcedureError, match="sha256 differs"):
        procedure_for_resume("site_check", "0" * 64)
    assert not marker.exists()  # refused before it was compiled
    p = procedure_for_resume("site_check", sha)
    assert p.name == "site_check" and p.version == "2.1" and p.sha256 == sha and marker.read_text() == "x"
    # the station's own command line may name the file (``station resume --procedure FILE``): same checks
    other = tmp_path / "elsewhere" / "site_check.py"
    other.parent.mkdir()
    other.write_bytes(proc.read_bytes())
    monkeypatch.delenv("STATION_PROCEDURES")
    with pytest.raises(ProcedureError, match="unknown procedure 'site_check'"):
        procedure_for_resume("site_check", sha)
    assert procedure_for_resume("site_check", sha, file=other).path == other
    with pytest.raises(ProcedureError, match="give its file site_check.py"):
        procedure_for_resume("site_check", sha, file=tmp_path / "evil.py")
    other.write_text(other.read_text() + "# changed\n")
    with pytest.raises(ProcedureError, match="sha256 differs"):
        procedure_for_resume("site_check", sha, file=other)
    assert marker.read_text() == "xx"  # ran exactly twice: the two accepted loads
