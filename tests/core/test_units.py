"""One units module: unit tables every reader shares, conversions that refuse the wrong quantity, and the one
rule for a parameter's quantity, checked against the solver's own (from the kinematic chain) on every
built-in model and every convention."""

import math

import pytest

from station import units
from station.kinematics import load_model
from station.kinematics.catalog import builtin_names


def test_tables_are_shared_not_copied():
    from station import samplesfile
    from station.engine import cell, limits

    assert samplesfile.LENGTH_UNITS is units.LENGTH_UNITS and samplesfile.ANGLE_UNITS is units.ANGLE_UNITS
    assert all(cell.LENGTH[u] == units.LENGTH_UNITS[u] for u in cell.LENGTH)
    assert all(cell.ANGLE[u] == units.ANGLE_UNITS[u] for u in cell.ANGLE)
    assert all(units.quantity_of(u) for u in limits.UNITS)


def test_conversions_and_wrong_quantity():
    assert units.to_si(100.0, "mm") == pytest.approx(0.1)
    assert units.to_si(180.0, "deg", "angle") == pytest.approx(math.pi)
    assert units.from_si(math.pi / 2, "deg") == pytest.approx(90.0)
    assert units.quantity_of("mrad") == "angle" and units.quantity_of("um") == "length"
    assert units.quantity_of("count") == "number"
    with pytest.raises(units.UnitError, match="'deg' measures angle, expected length"):
        units.to_si(1.0, "deg", "length")
    with pytest.raises(units.UnitError, match="unknown unit 'furlong'"):
        units.factor("furlong")
    assert units.human("length") == ("mm", pytest.approx(1e3))
    assert units.human("angle") == ("deg", pytest.approx(180 / math.pi))
    assert units.human_of("rad")[0] == "deg" and units.human_of("m")[0] == "mm" and units.human_of("1") == ("1", 1.0)


def test_parameter_rule_by_name():
    assert units.param_quantity("dh.j2.alpha") == "angle" and units.param_quantity("dh.j2.a") == "length"
    assert units.param_quantity("tcp.rz") == "angle" and units.param_quantity("tcp.z") == "length"
    assert units.param_quantity("point.A.x") == "length" and units.param_quantity("offset.j1") == "angle"
    scara = load_model("scara")
    prismatic = next(i for i, j in enumerate(scara.joints) if not j.revolute) + 1
    assert units.param_unit(f"offset.j{prismatic}", scara) == "m"
    assert units.param_unit("offset.j1", scara) == "rad"


def _models():
    """Every built-in model (DH) plus its POE twin and an MDH table: all three conventions."""
    from station.kinematics.model import from_mdh, from_poe, screws_of

    for name in builtin_names():
        dh = load_model(name)
        if getattr(dh, "kind", "serial") == "parallel":
            continue  # the solver's chain elements do not exist for a closed chain (station map calibrates it)
        yield name, dh
        screws, home = screws_of(dh)
        yield name + "-poe", from_poe(name + "-poe", list(dh.joints), screws, home)
        links = [{"alpha": 0.1 * i, "a": 0.05, "d": 0.02, "theta": 0.0} for i in range(dh.n_joints)]
        yield name + "-mdh", from_mdh(name + "-mdh", list(dh.joints), links)


@pytest.mark.parametrize("name,model", list(_models()), ids=lambda v: v if isinstance(v, str) else "")
def test_parameter_rule_agrees_with_the_solver_and_the_model_reader(name, model):
    """The solver decides a parameter's unit from its chain element (rotation or translation); the one rule
    decides from the name. They must agree for every parameter of every model, else results, reports and
    write-back would convert the same number two ways."""
    from station.kinematics.modelfile import ANGLE_KEYS
    from station.solver.problem import angle_params

    by_rule = {n for n in model.param_names if units.param_quantity(n, model) == "angle"}
    assert by_rule == angle_params(model)
    assert set(ANGLE_KEYS) == set(units.ANGLE_PARAMS)


def test_report_uses_the_rule_where_a_result_gives_no_unit():
    from station.report.content import param_unit

    scara = load_model("scara")
    assert param_unit("offset.j3", {}, scara) == units.param_unit("offset.j3", scara)
    assert param_unit("dh.j1.alpha", {}) == "rad" and param_unit("dh.j1.a", {"unit": "m"}) == "m"
