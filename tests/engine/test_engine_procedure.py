"""Procedure files: shipped ones load and read like checklists; broken files give one-line errors, also from
the command line (exit 2, ``station: error: ...``)."""


import pytest
from clirunner import station_proc

from station.engine import ProcedureError, load_procedure, shipped_names


def test_shipped_procedures_load():
    names = shipped_names()
    for want in ("zero_offsets", "tcp_4point", "tcp_circle", "dh_full", "verify"):
        assert want in names
        p = load_procedure(want)
        assert p.title and len(p.sha256) == 64 and callable(p.module.checklist)


@pytest.mark.parametrize("text, match", [
    ('"""doc"""\ndef checklist(s):\n    s.connect(\n', r"line \d+"),
    ('"""doc"""\nX = 1\n', "defines no checklist"),
    ("def checklist(s):\n    pass\n", "needs a docstring"),
    ('"""doc"""\nimport nonexistent_module_xyz\ndef checklist(s):\n    pass\n', "line 2: ModuleNotFoundError"),
])
def test_bad_procedure_files(tmp_path, text, match):
    p = tmp_path / "proc.py"
    p.write_text(text)
    with pytest.raises(ProcedureError, match=match) as e:
        load_procedure(str(p))
    assert "\n" not in str(e.value)


def test_unknown_procedure_name():
    with pytest.raises(ProcedureError, match="unknown procedure 'zero_ofsets'; shipped: "):
        load_procedure("zero_ofsets")


def test_cli_bad_procedure_and_limits_files_exit_2_with_one_line(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text('"""doc"""\ndef checklist(s)\n    pass\n')
    r = station_proc("run", str(bad), "--robot", "ur://127.0.0.1", "--serial", "X")
    assert r.code == 2
    assert r.err.strip().count("\n") == 0
    assert r.err.startswith("station: error: procedure") and "line 2" in r.err
    lim = tmp_path / "limits.yaml"
    lim.write_text("format: station-limits/1\nversion: 1\nmodels: {ur5e: {zero_offsets: {fit_rms: {high: 1}}}}\n")
    r = station_proc("run", "zero_offsets", "--robot", "ur://127.0.0.1", "--serial", "X", "--limits", str(lim))
    assert r.code == 2
    assert r.err.strip().count("\n") == 0 and "fit_rms: unit '(missing)'" in r.err
