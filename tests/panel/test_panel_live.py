"""The operator panel during a run, in a real browser (Playwright, Debian's chromium), on an emulated Dynamixel
arm moving in real time (the ``World`` in this process is the ground truth): a validated value prompt refused in
the page and by the API, the manual-touch prompt showing the point's picture from the cell file, the live
residual plot growing with the samples (values checked against the nominal model computed here), and ABORT in
the middle of a move: the world confirms the arm stopped short of its target; the session ends ABORTED,
journaled, resumable."""

from __future__ import annotations

import json
import time
import urllib.error
import urllib.request
from io import BytesIO

import numpy as np
import pytest
import yaml
from station.mocks.world import World

from station.cli.run_cmd import demo_world
from station.engine import read_journal
from station.kinematics import load_model
from tests.panel.test_panel_browser import Panel, _sign_in_and_scan, browser, panels  # noqa: F401 - fixtures

PROCEDURE = '''"""Asks the stylus ball diameter, then touches the socket by hand (a test procedure)."""


def checklist(s):
    s.connect()
    s.check_state()
    s.measure("ball_diameter", s.ask("Stylus ball diameter", "number", unit="mm", low=5, high=7, key="ball"))
    plan = s.plan(s.points("socket"), identify="offsets")
    for pose in s.todo(plan):
        s.approach(pose)
        s.seat(pose)
        s.record(pose)
        s.leave(pose)
    s.solve(identify="offsets")
    s.measure_result()
    s.judge()
'''
LIMITS = ('format: station-limits/1\nversion: "t-live"\nmodels:\n  omx:\n    ask_touch:\n'
          "      ball_diameter: {low: 5.5, high: 6.5, unit: mm}\n")


def _post(base: str, path: str, body: dict) -> tuple[int, dict]:
    with urllib.request.urlopen(base + "/api/csrf", timeout=10) as r:  # a script's state change: its CSRF token
        csrf = json.loads(r.read())["csrf"]
    req = urllib.request.Request(base + path, data=json.dumps(body).encode(), method="POST",
                                 headers={"Content-Type": "application/json", "X-CSRF-Token": csrf})
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def _get(base: str, path: str) -> tuple[int, bytes, str]:
    try:
        with urllib.request.urlopen(base + path, timeout=10) as r:
            return r.status, r.read(), r.headers.get("content-type", "")
    except urllib.error.HTTPError as e:
        return e.code, e.read(), ""


def _wait(pred, timeout: float, what: str):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def _prompt(page, panel: Panel, contains: str) -> dict:
    """Wait until the page shows the prompt whose text contains ``contains``."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    try:
        page.wait_for_function("(t) => document.getElementById('prompt').style.display === 'block' && "
                               "document.getElementById('prompt-text').textContent.includes(t)", arg=contains,
                               timeout=60_000)
    except PlaywrightTimeout:  # say where the session is (an error? another question?), not only that it waited
        st = {k: v for k, v in panel.state().items() if k != "residuals"}
        raise AssertionError(f"no prompt '{contains}' on the page; panel state: {st}") from None
    return panel.state()["prompt"]


def _destination(world: World) -> np.ndarray:
    """Where each joint of the simulated world comes to rest on its present motion profile (the end of the
    move under way; once stopped, where it stopped): ground truth below the wire."""
    return np.array([tr.x_end for tr in world._tracks])


def _remaining(world: World) -> float:
    """World seconds until every joint's present motion profile ends (0: at rest)."""
    return max(0.0, max(tr.t_end for tr in world._tracks) - world.now())


def _picture(tmp_path) -> bytes:
    from PIL import Image

    img = Image.new("RGB", (96, 64), (200, 120, 20))
    buf = BytesIO()
    img.save(buf, format="PNG")
    (tmp_path / "pictures").mkdir()
    (tmp_path / "pictures" / "socket-A.png").write_bytes(buf.getvalue())
    return buf.getvalue()


def test_prompts_plot_and_abort_mid_move(tmp_path, emulators, browser, panels):  # noqa: F811 - fixtures
    doc = demo_world("dynamixel", 61, "realtime")
    doc["motion"]["time_scale"] = 0.35  # world seconds per wall second: moves long enough to abort inside one
    (tmp_path / "world.yaml").write_text(yaml.safe_dump(doc))
    world = World.from_file(tmp_path / "world.yaml")
    cell = world.station_cell()
    cell["points"][0]["image"] = "pictures/socket-A.png"  # N (a needle, not in this plan) has no picture
    assert cell["points"][0]["label"] == "A" and cell["points"][1]["label"] == "N"
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(cell))
    png = _picture(tmp_path)
    (tmp_path / "ask_touch.py").write_text(PROCEDURE)
    (tmp_path / "limits.yaml").write_text(LIMITS)
    serial = "DXL-LIVE-61"
    emu = emulators("dynamixel", world, serial=serial)
    # the technician's hand is the touch: no contact input wired in this cell
    url = emu.url.replace("&contact=200", "") + "&latency=100"
    panel = panels(tmp_path, url, tmp_path / "cell.yaml", f"sqlite:///{tmp_path / 'r.db'}", "--no-confirm",
                   "--procedure", str(tmp_path / "ask_touch.py"), "--limits", str(tmp_path / "limits.yaml"),
                   "--touch", "manual")
    # the picture is served under a fixed route by label; nothing else of the disk is
    status, body, ctype = _get(panel.base, "/api/points/A/image")
    assert status == 200 and body == png and ctype == "image/png"
    assert _get(panel.base, "/api/points/N/image")[0] == 404
    for bad in ("/api/points/..%2Fcell.yaml/image", "/api/points/%2E%2E/image", "/api/points/A/../../cell.yaml"):
        assert _get(panel.base, bad)[0] == 404, bad
    status, body, ctype = _get(panel.base, "/api/points/N/sketch.svg")
    assert status == 200 and ctype.startswith("image/svg+xml") and b'id="target"' in body

    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.goto(panel.base + "/")
    _sign_in_and_scan(page, serial)
    page.click("#start")

    # 1. a value: refused in the page as it is typed, refused by the API, accepted once valid
    p = _prompt(page, panel, "Stylus ball diameter")
    assert p["input"]["kind"] == "number" and p["input"]["unit"] == "mm"
    page.fill("#prompt-input", "abc")
    assert "not a number" in page.inner_text("#prompt-error") and page.is_disabled("#prompt-ok")
    page.fill("#prompt-input", "20")
    assert "out of range" in page.inner_text("#prompt-error") and page.is_disabled("#prompt-ok")
    page.press("#prompt-input", "Enter")  # refused in the page: nothing is sent
    time.sleep(0.3)
    assert panel.state()["state"] == "prompt"
    for bad, why in (("20", "out of range"), ("abc", "not a number"), ("6 kg", "unit must be mm")):
        code, reply = _post(panel.base, "/api/prompt", {"answer": bad})
        assert code == 400 and why in reply["error"] and "\n" not in reply["error"], (bad, reply)
        st = panel.state()
        assert st["state"] == "prompt" and st["prompt"]["text"] == p["text"]  # the question stays open
    page.fill("#prompt-input", "0.6 cm")
    assert page.inner_text("#prompt-error") == "" and not page.is_disabled("#prompt-ok")
    page.click("#prompt-ok")

    # 2. manual touch: the prompt shows the point's picture; the plot grows with each sample
    # independent of the panel: the nominal model with the cell's tool, the socket where the cell surveys it (m)
    model = load_model("omx").with_params({f"tcp.{k}": float(v) for k, v in (cell.get("tool") or {}).items()})
    a = np.asarray(cell["points"][0]["position"], float)
    assert cell["units"]["length"] == "m"
    samples_seen = []
    for k in range(2):
        p = _prompt(page, panel, "jog the tool tip onto point A")
        assert p["point"] == "A" and p["image"] == "/api/points/A/image"
        page.wait_for_function("() => { const i = document.getElementById('prompt-image'); "
                               "return i.complete && i.naturalWidth === 96 && i.naturalHeight === 64; }")
        assert page.is_visible("#prompt-image") and page.get_attribute("#prompt-image", "class") == "photo"
        assert len(page.query_selector_all("#residual-plot circle.res")) == k
        page.click("#prompt-ok")
        _prompt(page, panel, "clear of point A")
        page.click("#prompt-ok")
        page.wait_for_function("(n) => document.querySelectorAll('#residual-plot circle.res').length === n",
                               arg=k + 1, timeout=30_000)
        samples_seen.append([float(c.get_attribute("data-mm"))
                             for c in page.query_selector_all("#residual-plot circle.res")])

    # 3. ABORT in the middle of the next move (the approach to pose 3 starts as the second point is plotted;
    # the plot's values are checked after it): the world stops short of the target
    # inside a move with time left (a move's last millimetres end before the world's profile does)
    try:
        _wait(lambda: _remaining(world) > 0.1, 60, "a move of the approach to pose 3 with 0.3 s left")
    except AssertionError as e:  # say where the session is (a fault? ended?), not only that no move came
        raise AssertionError(f"{e}; panel state: {panel.state()}") from None
    going_to = _destination(world)  # where the world's joints are headed (the move under way)
    page.click("#abort")
    t_abort = time.monotonic()
    _wait(lambda: not world.is_moving(), 10, "the arm to stop")
    stopped_after = time.monotonic() - t_abort
    page.wait_for_selector("#verdict.aborted", timeout=30_000)
    q_stop = world.encoder_q().copy()
    sid = panel.state()["session"]
    journal = tmp_path / "home" / "sessions" / sid / "journal.jsonl"
    time.sleep(0.5)
    assert np.allclose(world.encoder_q(), q_stop, atol=1e-3) and not world.is_moving()  # and stays stopped
    _, events = read_journal(journal)
    plan = next(e for e in events if e["type"] == "plan")["plan"]
    (fault,) = [e for e in events if e["type"] == "fault"]
    assert fault["error"] == "Aborted" and "stopped during approach of pose 2" in fault["message"], fault
    short = float(np.max(np.abs(_destination(world) - going_to)))
    # short of it by more than the servo's resolution (4096 counts/rev: 0.0015 rad) and the world's tolerance
    assert short > 0.004, f"the arm went on to its target ({short:.4f} rad short)"
    start = np.asarray(plan["poses"][1]["approach_q"], float)
    assert np.max(np.abs(q_stop - start)) > 0.005, "the arm never left the previous pose"
    assert events[-1]["type"] == "end" and events[-1]["status"] == "interrupted"
    # the stop went out on the bus at once (not at the end of the move: that is seconds away at this speed)
    assert sum(e["type"] == "sample" for e in events) == 2 and stopped_after < 2.0, stopped_after
    print(f"arm stopped {stopped_after:.2f} s after ABORT, {short:.3f} rad short of the move's target")
    # the plot showed each sample's residual against the nominal model, computed here independently
    q = np.array([e["q"] for e in events if e["type"] == "sample"])
    truth_mm = np.linalg.norm(model.position(q) - a, axis=1) * 1e3  # the nominal tip against the surveyed socket
    assert samples_seen[1] == pytest.approx(truth_mm.tolist(), abs=1e-5)
    assert samples_seen[0] == pytest.approx(truth_mm[:1].tolist(), abs=1e-5)
    st = panel.state()
    assert st["verdict"] == "ABORTED" and "stopped during approach" in st["message"]
    assert page.inner_text("#verdict-word") == "ABORTED"
    status, body, _ = _get(panel.base, "/api/resumable")
    assert sid in [r["session"] for r in json.loads(body)]
    assert [e["value"] for e in events if e["type"] == "answer"] == [pytest.approx(0.006)]
