"""The shipped procedures (``procedures/``) against the engine that runs them: the file ``station run NAME`` loads is
the module imported here, with its defaults and identify group; every step its checklist (and every helper it
calls) asks of the session exists on the engine's session; its identify group names parameters of the models it is
for. The runs themselves: tests/test_e2e_*.py and the procedure tests named after them."""

from __future__ import annotations

import ast
import inspect
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from station.procedures import (
    _calibration,
    correction_map,
    dh_full,
    iso9283,
    tcp_4point,
    tcp_circle,
    two_socket,
    verify,
    zero_offsets,
)

from station.engine.procedure import load_procedure, shipped_names
from station.kinematics import load_model
from station.robot import Identity
from station.solver import select_names
from station.tui.session import session_header, technician_session

SHIPPED = {"correction_map": correction_map, "dh_full": dh_full, "iso9283": iso9283, "tcp_4point": tcp_4point,
           "tcp_circle": tcp_circle, "two_socket": two_socket, "verify": verify, "zero_offsets": zero_offsets}
MODEL_OF = {"zero_offsets": "ur5e", "dh_full": "arm6", "verify": "ur5e", "tcp_4point": "scara", "tcp_circle": "ur5e",
            "two_socket": "ur5e"}


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    ident = Identity(vendor="v", model="ur5e", serial="S", serial_source="robot")
    header = session_header(identity=ident, model_name="ur5e", serial="S", identify="offsets", reference="unknown",
                            url="x")
    return technician_session(None, header, folder=tmp_path_factory.mktemp("s") / "jog", model=load_model("ur5e"))


def test_every_shipped_procedure_is_named_here():
    assert sorted(SHIPPED) == shipped_names()


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_run_by_name_loads_this_module(name):
    module = SHIPPED[name]
    proc = load_procedure(name)
    assert Path(proc.path).resolve() == Path(module.__file__).resolve()
    assert proc.defaults == dict(getattr(module, "DEFAULTS", {}) or {})
    assert proc.identify == getattr(module, "IDENTIFY", None)
    if proc.identify and name in MODEL_OF:
        names = select_names(load_model(MODEL_OF[name]), proc.identify)
        assert names and all(isinstance(n, str) for n in names)


def _session_uses(module: ModuleType) -> set[str]:
    """Attributes of ``s`` (the session) read or called anywhere in the module's functions."""
    tree = ast.parse(inspect.getsource(module))
    used = set()
    for fn in ast.walk(tree):
        if isinstance(fn, ast.FunctionDef) and fn.args.args and fn.args.args[0].arg == "s":
            used |= {n.attr for n in ast.walk(fn) if isinstance(n, ast.Attribute)
                     and isinstance(n.value, ast.Name) and n.value.id == "s"}
    return used


@pytest.mark.parametrize("module", [*SHIPPED.values(), _calibration], ids=lambda m: m.__name__.rsplit(".", 1)[1])
def test_every_step_asked_of_the_session_exists(module, session):
    used = _session_uses(module)
    assert used, module.__name__
    missing = sorted(a for a in used if not hasattr(session, a))
    assert not missing, f"{module.__name__} asks the session for {missing}"


def test_dh_full_asks_for_the_tool_only_when_the_data_need_it():
    """``tool_needed``: the F-test on the two fits' residuals, against the F distribution's critical value."""
    from types import SimpleNamespace

    from scipy.stats import f

    def fit(sigma, dof, trusted=True):
        return SimpleNamespace(noise={"fitted_m": sigma, "dof": dof}, trusted=trusted)

    dof1 = 100
    crit = f.ppf(1 - 1e-3, 3, dof1)  # F at which the tool's 3 unknowns explain more than chance would
    s1 = 20e-6
    for F_value, expect in ((0.5 * crit, False), (2 * crit, True)):
        rss1 = s1**2 * dof1
        rss0 = rss1 + F_value * 3 * rss1 / dof1
        assert dh_full.tool_needed(fit(np.sqrt(rss0 / (dof1 + 3)), dof1 + 3), fit(s1, dof1)) is expect
    assert not dh_full.tool_needed(fit(1e-3, 103), fit(s1, dof1, trusted=False))
