"""The operator's recovery from ERROR, in a real browser (Playwright, Debian's chromium) at a phone's 390 px, a
1280 px station PC and a 1920 px line monitor: a unit on an emulated Dynamixel arm (real dynamixel_sdk on a pty,
the ``World`` in this process is the ground truth) loses its robot three times mid-run (the servos stop
answering, as a pulled cable or a stalled bus does); each time the page shows ERROR — amber, its own word and
icon, never FAIL's red — with the reason in plain words and RESUME / ABORT on the ERROR screen itself; RESUME
asks the operator to confirm the cell before the robot moves again, the stale error is gone from the screen,
and the unit ends PASS with every pose measured exactly once. Every screen is checked for what an operator at a
line needs: nothing wider than the screen, the state and its one action in view. The screenshots are kept in the
test's folder (``error-390.png`` ...)."""

from __future__ import annotations

import time
from io import BytesIO

import numpy as np
import pytest
import yaml
from station.mocks.world import World

from station.cli.run_cmd import demo_world
from station.engine import read_journal
from station.records import open_records
from tests.panel.test_panel_browser import Panel, _sign_in_and_scan, browser, panels  # noqa: F401 - fixtures

WIDTHS = ((390, 844), (1280, 800), (1920, 1080))
MOVE = {"packet": {"addr": 108}}  # a Dynamixel move starts with a sync write from address 108


def _mean_rgb(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(BytesIO(png)).convert("RGB"), dtype=float).reshape(-1, 3).mean(axis=0)


def _fits(page, width: int, height: int, *selectors: str) -> None:
    """Nothing wider than the screen; each selector visible and wholly inside the viewport."""
    over = page.evaluate("() => [document.documentElement.scrollWidth, document.getElementById('verdict').scrollWidth]")
    assert max(over) <= width, (width, over)
    for sel in selectors:
        assert page.is_visible(sel), (width, sel)
        box = page.locator(sel).bounding_box()
        assert box["x"] >= 0 and box["y"] >= 0 and box["x"] + box["width"] <= width + 0.5 and \
            box["y"] + box["height"] <= height + 0.5, (width, sel, box)


def _visible_text(page) -> str:
    return page.evaluate("() => document.body.innerText")


def _screen(page, panel: Panel, selector: str, timeout_ms: int) -> None:
    """Wait for a screen of the page; a timeout says the panel's state (another verdict? still running?)."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    try:
        page.wait_for_selector(selector, timeout=timeout_ms)
    except PlaywrightTimeout:
        st = {k: v for k, v in panel.state().items() if k != "residuals"}
        raise AssertionError(f"no {selector} on the page; panel state: {st}") from None


def _wait(pred, timeout: float, what: str, panel: Panel):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}; panel state: {panel.state()}")


@pytest.mark.slow
def test_error_resume_pass_at_phone_desktop_and_line_monitor(tmp_path, emulators, browser, panels):  # noqa: F811
    doc = demo_world("dynamixel", 81, "realtime")
    doc["motion"]["time_scale"] = 4.0  # world seconds per wall second: a run of a few seconds per pose
    (tmp_path / "world.yaml").write_text(yaml.safe_dump(doc))
    world = World.from_file(tmp_path / "world.yaml")
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(world.station_cell()))
    serial, db = "DXL-OP-81", f"sqlite:///{tmp_path / 'r.db'}"
    emu = emulators("dynamixel", world, serial=serial)
    panel = panels(tmp_path, emu.url + "&latency=100", tmp_path / "cell.yaml", db)  # with the confirm prompt
    page = browser.new_page(viewport={"width": 390, "height": 844})
    page.goto(panel.base + "/")
    _sign_in_and_scan(page, serial)
    page.keyboard.press("Enter")  # START
    _screen(page, panel, "#prompt-text >> visible=true", 30_000)
    _fits(page, 390, 844, "#prompt-ok")
    page.click("#prompt-ok")

    kept: list[list] = []
    sid = None
    for k, (w, h) in enumerate(WIDTHS):
        page.set_viewport_size({"width": w, "height": h})
        # running: the big state and its one action in view
        base = len(kept[-1]) if kept else 0  # the journal's count (a resumed run reports its own soon)
        _wait(lambda n=base + 2: panel.state()["samples"] >= n, 120, "two more samples", panel)
        assert page.inner_text("#state-word") == "CALIBRATING" and "of 14 points measured" in page.inner_text(
            "#samples")
        _fits(page, w, h, "#state-word", "#abort")
        # the plot explains its colours; on a line monitor the page uses its width: state left, plot right
        legend = page.inner_text("#plot-box .legend")
        assert "used to calibrate" in legend and "check point" in legend
        unit, plot = (page.locator(sel).bounding_box() for sel in ("#unit", "#plot-box"))
        if w >= 1400:
            assert plot["x"] > unit["x"] + unit["width"] and plot["x"] + plot["width"] > 0.95 * w, (unit, plot)
        else:
            assert plot["y"] > unit["y"] + unit["height"], (unit, plot)  # one column
        page.screenshot(path=str(tmp_path / f"running-{w}.png"))
        # the servos stop answering at the next move (more lost answers than the driver's retries)
        world.faults.inject("timeout", device=None, count=4, trigger=MOVE)
        _screen(page, panel, "#verdict.error", 60_000)
        st = panel.state()
        sid = sid or st["session"]
        assert st["verdict"] == "ERROR" and st["session"] == sid and st["resumable"] is True, st
        shot = page.screenshot(path=str(tmp_path / f"error-{w}.png"))
        # its own word, icon and colour: amber (red and green high, blue low), not FAIL's red, not PASS's green
        r, g, b = _mean_rgb(shot)
        assert r > 170 and g > 0.55 * r and b < 0.5 * g, (w, r, g, b)
        assert page.inner_text("#verdict-word") == "ERROR" and page.is_visible("#verdict .icon-error")
        assert not page.is_visible("#verdict .icon-fail")
        # the reason in plain words, where it happened, what to do; the technical line only under "details"
        assert page.inner_text("#verdict-reason") == "The robot stopped answering."
        assert f"Stopped after {st['samples']} of 14 points; all {st['samples']} are kept" in page.inner_text(
            "#verdict-where")
        assert "press RESUME" in page.inner_text("#verdict-action")
        assert "ConnectionLost" not in _visible_text(page) and "dynamixel" not in _visible_text(page).lower()
        assert "ConnectionLost" in page.text_content("#verdict-message")
        # RESUME and ABORT on the ERROR screen itself, in view without scrolling; no TRY AGAIN (resumable)
        _fits(page, w, h, "#verdict-word", "#verdict-reason", "#verdict-resume", "#verdict-abort")
        assert not page.is_visible("#verdict-retry")
        kept.append([e["q"] for e in read_journal(tmp_path / "home" / "sessions" / sid / "journal.jsonl")[1]
                     if e["type"] == "sample"])
        assert len(kept[-1]) == st["samples"] >= 2 * (k + 1)
        # RESUME: the operator confirms the cell before the robot moves again (someone may have been inside)
        page.click("#verdict-resume")
        _screen(page, panel, "#prompt-text >> visible=true", 30_000)
        assert "finish the unit" in page.inner_text("#prompt-text") and not page.is_visible("#verdict")
        _fits(page, w, h, "#prompt-ok")
        page.click("#prompt-ok")
        _wait(lambda: panel.state()["state"] == "running", 30, "the resumed run", panel)
        # no stale message: nothing of the error is left on the screen of the resumed run
        page.wait_for_function("() => document.getElementById('state-word').textContent === 'CALIBRATING'")
        text = _visible_text(page)
        assert "stopped answering" not in text and "ERROR" not in text, text
        assert page.inner_text("#notice") == "" and page.inner_text("#message") == ""

    _screen(page, panel, "#verdict.pass", 180_000)
    st = panel.state()
    assert st["verdict"] == "PASS" and st["session"] == sid and st["stored"] is True
    for w, h in reversed(WIDTHS):
        page.set_viewport_size({"width": w, "height": h})
        shot = page.screenshot(path=str(tmp_path / f"pass-{w}.png"))
        r, g, b = _mean_rgb(shot)
        assert g > 100 and g > 1.5 * r and g > 1.5 * b, (w, r, g, b)
        _fits(page, w, h, "#verdict-word", "#verdict .icon-pass", "#next-serial")
        text = _visible_text(page)
        assert "stopped answering" not in text and "ERROR" not in text and "RESUME" not in text, text
        assert page.inner_text("#verdict-reason") == "Every limit is met; the result is stored."

    # the journal: every pose exactly once, the samples kept before each error unchanged, three faults
    _, events = read_journal(tmp_path / "home" / "sessions" / sid / "journal.jsonl")
    samples = [e for e in events if e["type"] == "sample"]
    assert sorted(e["pose"] for e in samples) == list(range(14))
    for before in kept:
        assert [e["q"] for e in samples[:len(before)]] == before
    faults = [e for e in events if e["type"] == "fault"]
    assert [f["error"] for f in faults] == ["ConnectionLost"] * 3
    with open_records(db) as rec:  # the PASS on screen is the record in the database
        stored = rec.session(sid)
    assert stored["verdict"]["passed"] is True and len(stored["samples"]) == 14
    hidden = world.hidden()  # the same engine as station run: the truth recovered across three resumes
    for name, p in stored["result"]["parameters"].items():
        if name.startswith("offset.") and p["identifiable"]:
            assert abs(p["value"] - hidden[name]) <= 4 * p["std"] + np.pi / 4096, name
