"""Operator prompts: the engine's one prompt API (``s.ask(Question)``) validated by every front end and again by
the engine (the terminal of ``station run`` here; the panel in tests/panel/test_panel_live.py), a point's picture
from the cell file (inside the cell's folder only) and the generated sketch of where a point is."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml
from clirunner import station_proc

from station.engine.cell import CellError, load_cell
from station.engine.procedure import BadAnswer, Question
from station.panel.controller import Controller, PanelConfig, PanelError, PromptRefused

ASK = '''"""Asks the stylus ball diameter, then judges it (a test procedure)."""


def checklist(s):
    s.connect()
    s.check_state()
    d = s.ask("Stylus ball diameter printed on the tool", "number", unit="mm", low=5, high=7, key="ball")
    s.measure("ball_diameter", d)
    s.judge()
'''
LIMITS = ('format: station-limits/1\nversion: "t-ask"\nmodels:\n  omx:\n    ask_length:\n'
          "      ball_diameter: {low: 5.5, high: 6.5, unit: mm}\n")


@pytest.mark.parametrize(("kw", "good", "bad"), [
    ({"kind": "number", "unit": "mm", "low": 80, "high": 95},
     {"87.5": 0.0875, "80": 0.080, "95 mm": 0.095, "0.09 m": 0.09, " 9.1cm ": 0.091},
     ["abc", "", "79.99", "95.01", "5 kg", "1e400", "nan", "87,5"]),
    ({"kind": "number", "unit": "deg", "low": -5, "high": 5},
     {"-4.5": -4.5 * 3.141592653589793 / 180, "0.05 rad": 0.05},
     ["6", "0.1 rad", "3 mm"]),
    ({"kind": "number", "unit": "N", "low": 0},
     {"12.5": 12.5, "0 N": 0.0},
     ["-1", "12 kg"]),
    ({"kind": "text", "pattern": r"[A-Z]{3}-\d{4}"},
     {"ABC-1234": "ABC-1234"},
     ["abc-1234", "ABC-123", "ABC-12345", ""]),
    ({"kind": "choice", "choices": ["left", "right"]},
     {"left": "left", "RIGHT": "right"},
     ["up", ""]),
])
def test_question_accepts_and_refuses(kw, good, bad):
    q = Question("value?", **kw)
    for answer, value in good.items():
        got = q.check(answer)
        assert got == pytest.approx(value, rel=1e-12) if isinstance(value, float) else got == value, answer
    for answer in bad:
        with pytest.raises(BadAnswer) as e:
            q.check(answer)
        assert "\n" not in str(e.value) and str(e.value), answer


def test_question_is_its_text_and_refuses_bad_specs():
    q = Question("Confirm the socket is clean", point="A")
    assert q == "Confirm the socket is clean" and "socket" in q and q.check("") == "ok" and q.point == "A"
    with pytest.raises(BadAnswer):
        q.check("maybe")
    for kw in ({"kind": "slider"}, {"kind": "choice"}, {"kind": "text", "pattern": "(["},
               {"kind": "number", "low": 5, "high": 1}):
        with pytest.raises(Exception) as e:
            Question("x", **kw)
        assert type(e.value).__name__ in ("ConfigError",)


def _run_asker(tmp_path: Path, emulators, seed: int, stdin: str):
    """``station run`` of the asking procedure on an emulated arm, stdin piped: (completed process, events)."""
    from station.mocks.world import World

    from station.cli.run_cmd import demo_world
    from station.engine import read_journal

    (tmp_path / "world.yaml").write_text(yaml.safe_dump(demo_world("dynamixel", seed, "instant")))
    world = World.from_file(tmp_path / "world.yaml")
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(world.station_cell()))
    (tmp_path / "ask_length.py").write_text(ASK)
    (tmp_path / "limits.yaml").write_text(LIMITS)
    serial = f"DXL-ASK-{seed}"
    emu = emulators("dynamixel", world, serial=serial)
    out = station_proc("run", tmp_path / "ask_length.py", "--robot", emu.url + "&latency=100", "--serial", serial,
                       "--cell", tmp_path / "cell.yaml", "--limits", tmp_path / "limits.yaml", "--db",
                       f"sqlite:///{tmp_path / 'r.db'}", "--quiet", stdin=stdin, timeout=120,
                       env={"STATION_HOME": str(tmp_path / "home")})
    (journal,) = (tmp_path / "home" / "sessions").glob("*/journal.jsonl")
    return out, read_journal(journal)[1]


def test_station_run_in_a_terminal_asks_until_the_value_is_valid(tmp_path, emulators):
    out, events = _run_asker(tmp_path, emulators, 71, "abc\n20\n5 kg\n0.6 cm\n")
    assert out.code == 0, out.err
    err = out.err
    assert "station: 'abc' is not a number" in err and "station: 20 mm is out of range" in err
    assert "station: '5 kg': the unit must be mm" in err
    assert out.out.count("Stylus ball diameter") == 4  # asked again after each refusal
    (ans,) = [e for e in events if e["type"] == "answer"]
    assert ans["key"] == "ball" and ans["value"] == pytest.approx(0.006, abs=1e-12) and ans["unit"] == "mm"
    (m,) = [e for e in events if e["type"] == "measurement" and e["name"] == "ball_diameter"]
    assert m["value"] == pytest.approx(6.0) and m["passed"] is True


def test_station_run_without_an_answer_stops_resumable(tmp_path, emulators):
    out, events = _run_asker(tmp_path, emulators, 72, "1000\n")
    assert out.code == 130, out.err  # stdin closed before a valid answer: interrupted, never a PASS
    assert events[-1]["type"] == "end" and events[-1]["status"] == "interrupted"
    assert not [e for e in events if e["type"] == "answer"]


# ---- pictures and sketches --------------------------------------------------------------------------------
def _cell(tmp_path: Path, image: str | None, make: str | None = None) -> Path:
    doc = {"format": "station-cell/1", "units": {"length": "mm"},
           "points": [{"label": "A", "kind": "socket", "position": [200, 0, 30], **({"image": image} if image else {})},
                      {"label": "N", "kind": "needle", "position": [180, 80, 50]},
                      {"label": "F", "kind": "socket", "position": [-150, -220, 10]}]}
    if make:
        (tmp_path / make).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / make).write_bytes(b"\x89PNG\r\n\x1a\n")
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_point_image_must_stay_in_the_cell_folder(tmp_path):
    cell = load_cell(_cell(tmp_path, "pictures/A.png", make="pictures/A.png"))
    assert cell.points["A"].image == str((tmp_path / "pictures" / "A.png").resolve())
    assert cell.points["N"].image is None
    (tmp_path / "outside.png").write_bytes(b"x")
    sub = tmp_path / "sub"
    sub.mkdir()
    for image, why in (("../outside.png", "stay inside"), (str(tmp_path / "outside.png"), "stay inside"),
                       ("pictures/missing.png", "no such file"), ("notes.txt", "picture")):
        (tmp_path / "notes.txt").write_text("x")
        path = _cell(tmp_path, image)
        with pytest.raises(CellError) as e:
            load_cell(path)
        assert why in str(e.value) and "points[0].image" in str(e.value) and "\n" not in str(e.value)
    (tmp_path / "link.png").symlink_to(tmp_path.parent)  # a link out of the folder is refused too
    with pytest.raises(CellError, match="outside"):
        load_cell(_cell(tmp_path, "link.png"))


def test_sketch_puts_the_point_where_the_cell_says(tmp_path):
    from station.panel.sketch import point_sketch

    cell = load_cell(_cell(tmp_path, None))
    for label in ("A", "N", "F"):
        svg = ET.fromstring(point_sketch(cell, label))
        ns = {"s": "http://www.w3.org/2000/svg"}
        scale = float(svg.get("data-scale-px-per-m"))
        base = svg.find("s:rect[@id='base']", ns)
        bx, by = float(base.get("x")) + 9, float(base.get("y")) + 9
        target = svg.find("s:circle[@id='target']", ns)
        x_mm = (float(target.get("cx")) - bx) / scale * 1e3
        y_mm = (by - float(target.get("cy"))) / scale * 1e3  # y up in the cell, down in SVG
        want = {"A": (200, 0), "N": (180, 80), "F": (-150, -220)}[label]
        assert x_mm == pytest.approx(want[0], abs=0.2 / scale * 1e3) and y_mm == pytest.approx(want[1],
                                                                                             abs=0.2 / scale * 1e3)
        size = float(svg.get("width"))
        assert 0 < float(target.get("cx")) < size and 0 < float(target.get("cy")) < size


def test_controller_prompt_names_picture_or_sketch_and_checks_answers(tmp_path):
    path = _cell(tmp_path, "A.png", make="A.png")
    ctl = Controller(PanelConfig(robot="dynamixel:///dev/null?model=omx", cell=str(path)))
    assert ctl.point_urls("A") == {"image": "/api/points/A/image", "sketch": "/api/points/A/sketch.svg"}
    assert ctl.point_urls("N") == {"image": None, "sketch": "/api/points/N/sketch.svg"}
    assert ctl.point_urls("nope") == {"image": None, "sketch": None}
    with pytest.raises(PanelError, match="no question is open"):
        ctl.answer("12")
    ctl._question = Question("length?", "number", unit="mm", low=1, high=2)
    ctl._s["state"], ctl._s["prompt"] = "prompt", {"text": "length?"}
    with pytest.raises(PromptRefused, match="out of range"):
        ctl.answer("3")
    assert not ctl._answered.is_set()  # the question stays open
    ctl.answer("1.5")
    assert ctl._answered.is_set() and ctl._answer == "1.5"
    json.dumps(ctl.snapshot())
