"""Limits files: versioned, keyed by robot model, units and marginal bands; one-line errors for bad files."""

import math

import pytest

from station.engine.limits import LimitsError, load_limits


def _write(tmp_path, text):
    p = tmp_path / "limits.yaml"
    p.write_text(text)
    return p


GOOD = """format: station-limits/1
version: "7"
models:
  ur5e:
    zero_offsets:
      fit_rms: {high: 0.10, marginal: 0.06, unit: mm}
      offset_abs_max: {high: 1.0, unit: deg}
      samples: {low: 12, unit: count}
"""


def test_shipped_limits_cover_every_shipped_procedure():
    from station.engine import load_procedure, shipped_names

    lim = load_limits()
    for model in ("ur5e", "arm6", "omx", "scara"):
        for name in shipped_names():
            if name == "tcp_circle" and model in ("omx",):
                continue
            assert lim.for_procedure(model, load_procedure(name).name)


def test_judge_units_and_marginal(tmp_path):
    table = load_limits(_write(tmp_path, GOOD)).for_procedure("ur5e", "zero_offsets")
    m = table["fit_rms"].judge(0.05e-3, "length")
    assert m["passed"] and not m["marginal"] and m["value"] == pytest.approx(0.05) and m["unit"] == "mm"
    assert table["fit_rms"].judge(0.08e-3, "length")["marginal"]
    assert not table["fit_rms"].judge(0.11e-3, "length")["passed"]
    assert table["offset_abs_max"].judge(math.radians(0.5), "angle")["passed"]
    assert not table["offset_abs_max"].judge(math.radians(1.5), "angle")["passed"]
    assert not table["samples"].judge(11, "number")["passed"]
    assert not table["fit_rms"].judge(None, "length")["passed"]  # a limit never measured fails
    with pytest.raises(LimitsError, match="fix the unit"):
        table["fit_rms"].judge(0.01, "angle")  # unit mix-up


@pytest.mark.parametrize("text, match", [
    ("format: station-limits/1\nversion: 1\nmodels: {ur5e: {zero_offsets: {fit_rms: {high: 1, unit: furlong}}}}\n",
     "unit 'furlong'"),
    ("format: station-limits/1\nmodels: {ur5e: {p: {a: {high: 1, unit: mm}}}}\n", "missing 'version'"),
    ("format: other\nversion: 1\n", "format: station-limits/1"),
    ("format: station-limits/1\nversion: 1\nmodels: {ur5e: {p: {a: {low: 2, high: 1, unit: mm}}}}\n", "above high"),
    ("format: station-limits/1\nversion: 1\nmodels: {ur5e: {p: {a: {unit: mm}}}}\n", "needs low and/or high"),
    ("format: station-limits/1\nversion: 1\nmodels: {ur5e: {p: {a: {high: .nan, unit: mm}}}}\n", "finite"),
    ("format: station-limits/1\nversion: 1\nmodels: {ur5e: {p: {a: {high: 1, unit: mm, hihg: 2}}}}\n", "hihg"),
    ("format: station-limits/1\nversion: 1\nmodels: [\n", "not valid YAML"),
])
def test_bad_limits_files_give_one_line_errors(tmp_path, text, match):
    p = _write(tmp_path, text)
    with pytest.raises(LimitsError, match=match) as e:
        load_limits(p)
    assert "\n" not in str(e.value) and str(p) in str(e.value)


def test_unknown_model_or_procedure(tmp_path):
    lim = load_limits(_write(tmp_path, GOOD))
    with pytest.raises(LimitsError, match="no entry for robot model 'omx'"):
        lim.for_procedure("omx", "zero_offsets")
    with pytest.raises(LimitsError, match="no limits for procedure 'verify'"):
        lim.for_procedure("ur5e", "verify")
    with pytest.raises(LimitsError, match="No such file|does not exist|limits file"):
        load_limits(tmp_path / "nope.yaml")
