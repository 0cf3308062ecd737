"""One sample builder: no module of the station builds a journal sample itself. ``events.Sample.from_snapshot``
builds every sample and ``Session.add_sample`` journals it (the engine's ``record`` and ``measure_pose``, every
procedure, the jog UI), checked over the source's syntax tree so that a new writer cannot slip in."""

import ast
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
SOURCES = [p for d in ("station", "procedures", "drivers", "mocks") for p in (ROOT / d).rglob("*.py")]


def _calls(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            yield node, (f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else "")


def _sample_dicts(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for k, v in zip(node.keys, node.values, strict=True):
                if isinstance(k, ast.Constant) and k.value == "type" and isinstance(v, ast.Constant) \
                        and v.value == "sample":
                    yield node


def test_only_the_builder_makes_a_sample_and_only_the_session_journals_one():
    built, from_snapshot, dicts = [], [], []
    for path in SOURCES:
        tree = ast.parse(path.read_text(), str(path))
        rel = str(path.relative_to(ROOT))
        for node, name in _calls(tree):
            if name == "Sample":
                built.append(f"{rel}:{node.lineno}")
            elif name == "from_snapshot":
                from_snapshot.append(rel)
        dicts += [f"{rel}:{n.lineno}" for n in _sample_dicts(tree)]
    assert built == [], f"a Sample built outside events.Sample.from_snapshot: {built}"
    assert dicts == [], f"a sample journaled as a dict: {dicts}"
    assert sorted(set(from_snapshot)) == ["station/engine/session.py"]  # Session.add_sample, the one writer


def test_the_builder_takes_what_each_taker_knows():
    from station.engine.events import Sample
    from station.instruments import PoseReading
    from station.robot import JointSnapshot

    snap = JointSnapshot(q=np.array([0.1, -0.2]), raw=(10, -20), raw_unit="count", t=5.0,
                         t_device=1.5)
    s = Sample.from_snapshot(snap, "A", pose=3, set="holdout", status={"touch": True})
    assert (s.q, s.raw, s.raw_unit, s.t_read, s.t_device, s.point, s.pose, s.set) == (
        [0.1, -0.2], [10, -20], "count", 5.0, 1.5, "A", 3, "holdout")
    assert s.status == {"touch": True} and s.measured is None and s.measured_rotation is None
    r = Sample.from_snapshot(snap, "G3", reading=PoseReading((1.0, 2.0, 3.0), (0.0, 0.1, 0.2), 7.0),
                             instrument="T-1", status={"series": "grid"})
    assert r.measured == [1.0, 2.0, 3.0] and r.measured_rotation == [0.0, 0.1, 0.2]
    assert r.status == {"instrument": "T-1", "t_instrument": 7.0, "series": "grid"}
    assert Sample.from_snapshot(snap, "A", measured=(0.5, 0.5, 0.5)).measured == [0.5, 0.5, 0.5]
