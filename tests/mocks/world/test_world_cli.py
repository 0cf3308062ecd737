"""``station mock world ...`` through the installed command (subprocess)."""

import math

import pytest
import yaml
from clirunner import station_proc
from station.mocks.world import World


def test_example_show_cell(tmp_path):
    r = station_proc("mock", "world", "example", "--model", "omx", "--seed", "7")
    assert r.code == 0, r.err
    f = tmp_path / "world.yaml"
    f.write_text(r.out)
    w = World.from_file(f)
    assert w.nominal.name == "omx" and w.spec.seed == 7

    r = station_proc("mock", "world", "show", str(f))
    assert r.code == 0, r.err
    out = r.out
    # every perturbed parameter with nominal, true and difference, in mm / deg
    for name, err in w.errors().items():
        line = next(ln for ln in out.splitlines() if ln.split() and ln.split()[0] == name)
        nominal, true, diff = (float(x) for x in line.split()[1:4])
        scale = 1e3 if line.split()[-1] == "mm" else 180 / math.pi
        assert diff == pytest.approx(err * scale, abs=1e-6)
        assert true == pytest.approx(w.truth.param(name) * scale, abs=1e-6)
        assert nominal == pytest.approx(w.nominal.param(name) * scale, abs=1e-6)
    for label in w.points:
        assert any(ln.split()[:1] == [label] for ln in out.splitlines())

    r = station_proc("mock", "world", "cell", str(f), "--out", str(tmp_path / "cell.yaml"))
    assert r.code == 0, r.err
    cell = yaml.safe_load((tmp_path / "cell.yaml").read_text())
    assert cell == w.station_cell()
    r = station_proc("mock", "world", "cell", str(f))
    assert yaml.safe_load(r.out) == cell


def test_freeze_keeps_truth(tmp_path):
    f = tmp_path / "w.yaml"
    f.write_text(station_proc("mock", "world", "example", "--model", "scara").out)
    r = station_proc("mock", "world", "freeze", str(f), "--out", str(tmp_path / "frozen.yaml"))
    assert r.code == 0, r.err
    a, b = World.from_file(f), World.from_file(tmp_path / "frozen.yaml")
    assert b.spec.random == []
    assert b.hidden() == pytest.approx(a.hidden(), abs=1e-9)


def test_errors_exit_2_with_one_line(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: station-world/1\nunits: {length: mm, angle: deg}\nnoise: {seating: -1}\n")
    for args in (("show", str(bad)), ("cell", str(bad)), ("show", str(tmp_path / "missing.yaml")),
                 ("example", "--model", "nosuchrobot"), ("show", str(bad), "--length", "inch")):
        r = station_proc("mock", "world", *args)
        assert r.code == 2, (args, r.out, r.err)
        lines = r.err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("station: error: "), r.err
    assert "noise.seating" in station_proc("mock", "world", "show", str(bad)).err
