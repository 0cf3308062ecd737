"""``station.cli.model_cmd``: ``station model list`` names every built-in model with its joints and convention,
read from the model files themselves."""

from __future__ import annotations

from station.cli.model_cmd import list_models
from station.kinematics import builtin_names, load_model


def test_model_list_describes_every_built_in_model(capsys):
    list_models()
    rows = [line.split() for line in capsys.readouterr().out.splitlines()]
    assert [r[0] for r in rows] == list(builtin_names())
    for r in rows:
        m = load_model(r[0])
        assert int(r[1]) == m.n_joints and r[2] == "joints"
        assert r[3] == ("parallel" if getattr(m, "kind", "serial") == "parallel" else m.convention.upper())
