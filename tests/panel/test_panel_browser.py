"""The operator panel in a real browser: ``station panel`` in its own process, an emulated Dynamixel arm
(Protocol 2.0 on a pty, real dynamixel_sdk) with hidden offsets, Playwright driving Debian's chromium
(``executable_path``; no browser is downloaded). Sign in, scan, START, answer the prompt, see PASS only once
the record is in the database; a unit failing a limit shows FAIL naming it; a panel killed mid-run resumes from
the page; the verdict fills the screen at 1280x800, 1920x1080 and on a 390 px phone; a wrong label scanned is an
ERROR naming both serials, given up with ABORT on the ERROR screen."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import yaml
from clirunner import station_spawn
from station.mocks.world import World

from station.cli.run_cmd import demo_world
from station.engine import read_journal
from station.records import open_records

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
STRICT = ('format: station-limits/1\nversion: "test-strict"\nmodels:\n  omx:\n    zero_offsets:\n'
          "      fit_rms: {high: 0.001, unit: mm}\n")


def _files(tmp_path: Path, seed: int, time_mode: str = "instant", time_scale: float = 1.0):
    from station.mocks.world import World

    doc = demo_world("dynamixel", seed, time_mode)
    doc["motion"]["time_scale"] = time_scale
    world_path, cell_path = tmp_path / "world.yaml", tmp_path / "cell.yaml"
    world_path.write_text(yaml.safe_dump(doc))
    cell_path.write_text(yaml.safe_dump(World.from_file(world_path).station_cell()))
    return world_path, cell_path


def _url(emu) -> str:
    # the SDK's answer timeout with a 100 ms latency term: 2 cores shared by many test processes
    return emu.url + "&latency=100"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Panel:
    """``station panel`` as the operator's PC runs it."""

    def __init__(self, tmp_path: Path, url: str, cell: Path, db: str, *extra: str) -> None:
        self.port = _free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.home = tmp_path / "home"
        self.proc = station_spawn("panel", "--robot", url, "--cell", cell, "--db", db, "--port", self.port,
                                  "--reference", "cell", "--cone", "70", "--poses", "12", "--holdout", "2", *extra,
                                  module=True, env={"STATION_HOME": str(self.home)})
        end = time.monotonic() + 60
        while time.monotonic() < end:
            if not self.proc.running():
                raise AssertionError(self.proc.wait())
            try:
                self.state()
                return
            except urllib.error.HTTPError:  # up, and asking for the token
                return
            except OSError:
                pass
            time.sleep(0.1)
        raise AssertionError("panel did not come up")

    def state(self) -> dict:
        with urllib.request.urlopen(self.base + "/api/state", timeout=5) as r:
            return json.loads(r.read())

    def kill(self) -> None:
        if self.proc.running():
            self.proc.kill()
        self.proc.wait(timeout=10)

    def close(self) -> None:
        if self.proc.running():
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.kill()


@pytest.fixture
def browser():
    if not os.path.exists(CHROMIUM):
        pytest.fail("the panel browser tests need Debian's chromium (apt-get install -y chromium; .ci/run does)",
                    pytrace=False)
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--disable-dev-shm-usage",
                                                                "--disable-gpu"])
        yield b
        b.close()


@pytest.fixture
def panels():
    started: list[Panel] = []

    def make(*a, **kw) -> Panel:
        p = Panel(*a, **kw)
        started.append(p)
        return p

    yield make
    for p in started:
        p.close()


def _sign_in_and_scan(page, serial: str) -> None:
    page.fill("#operator", "a.operator")
    page.press("#operator", "Enter")
    # a keyboard-wedge scanner types the label and Enter into the focused field
    assert page.evaluate("document.activeElement.id") == "serial"
    page.keyboard.type(serial)
    page.keyboard.press("Enter")
    assert page.evaluate("document.activeElement.id") == "start"


def _verdict(page, panel: Panel, expected: str, timeout_ms: int) -> dict:
    """Wait for the full-screen verdict; a different one fails with the panel's one-line reason."""
    page.wait_for_selector("#verdict[class]:not([class=''])", timeout=timeout_ms)
    st = panel.state()
    assert page.get_attribute("#verdict", "class") == expected, (st["verdict"], st["message"])
    return st


def _green_red(png: bytes) -> tuple[float, float, float]:
    from io import BytesIO

    from PIL import Image

    img = np.asarray(Image.open(BytesIO(png)).convert("RGB"), dtype=float)
    return tuple(img.reshape(-1, 3).mean(axis=0))


def test_pass_through_the_page_then_history(tmp_path, emulators, browser, panels):
    world_path, cell_path = _files(tmp_path, seed=41)
    serial = "DXL-PANEL-41"
    db = f"sqlite:///{tmp_path / 'r.db'}"
    emu = emulators("dynamixel", world_path, serial=serial, process=True)
    panel = panels(tmp_path, _url(emu), cell_path, db)
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.goto(panel.base + "/")
    # the wrong label scanned: the robot in the cell reports another serial; ERROR (not FAIL) in plain words,
    # nothing to resume, nothing moved, nothing journaled; ABORT gives it up
    _sign_in_and_scan(page, "WRONG-SN")
    page.keyboard.press("Enter")  # START
    page.wait_for_selector("#prompt-text", state="visible", timeout=20_000)
    page.click("#prompt-ok")
    st = _verdict(page, panel, "error", 60_000)
    assert st["session"] is None and st["resumable"] is False and st["cause"] == "serial"
    assert page.inner_text("#verdict-reason") == f"The unit in the cell is not WRONG-SN: the robot reports serial " \
                                                 f"{serial}."
    assert "Scan the label" in page.inner_text("#verdict-action")
    assert page.is_visible("#verdict-abort") and not page.is_visible("#verdict-resume")
    assert not page.is_visible("#verdict-retry")  # the same serial again would fail the same way
    assert not (tmp_path / "home" / "sessions").exists() or not list((tmp_path / "home" / "sessions").iterdir())
    page.click("#verdict-abort")
    page.wait_for_selector("#verdict.aborted")
    assert page.inner_text("#verdict-word") == "ABORTED" and "Given up" in page.inner_text("#verdict-reason")
    # the right label, scanned into the verdict screen's own field: armed, START has the focus
    page.keyboard.type(serial)
    page.keyboard.press("Enter")
    page.wait_for_selector("#verdict.aborted", state="hidden")
    assert page.evaluate("document.activeElement.id") == "start" and page.input_value("#serial") == serial
    page.keyboard.press("Enter")  # START
    page.wait_for_selector("#prompt-text", state="visible", timeout=20_000)
    assert serial in page.inner_text("#prompt-text")
    assert not list((tmp_path / "home" / "sessions").glob("*"))  # nothing moves before the operator confirms
    page.click("#prompt-ok")
    st = _verdict(page, panel, "pass", 180_000)
    assert page.inner_text("#verdict-word") == "PASS" and st["verdict"] == "PASS" and st["stored"] is True
    assert st["samples"] == st["samples_planned"] == 14
    with open_records(db) as rec:  # the PASS on screen is a record in the database
        stored = rec.session(st["session"])
    assert stored["verdict"]["passed"] is True and stored["operator"] == "a.operator"
    hidden = World.from_file(world_path).hidden()
    for name, p in stored["result"]["parameters"].items():  # the same engine as station run: truth recovered
        if name.startswith("offset.") and p["identifiable"]:
            assert abs(p["value"] - hidden[name]) <= 4 * p["std"] + np.pi / 4096, name
    # the verdict fills the screen at each size (a phone too) and stays there
    for w, h in ((1280, 800), (1920, 1080), (390, 844)):
        page.set_viewport_size({"width": w, "height": h})
        box = page.locator("#verdict").bounding_box()
        assert box["width"] == w and box["height"] == h
        word = page.locator("#verdict-word").bounding_box()
        assert word["x"] >= 0 and word["x"] + word["width"] <= w, (w, word)  # PASS is never clipped
        assert page.evaluate("document.documentElement.scrollWidth") <= w
        shot = page.screenshot(path=str(tmp_path / f"pass-{w}x{h}.png"))
        r, g, b = _green_red(shot)
        assert g > 100 and g > 1.5 * r and g > 1.5 * b, (w, h, r, g, b)
    time.sleep(1.0)
    assert page.is_visible("#verdict.pass")
    # the report is linked and served
    href = page.get_attribute("#report-link", "href")
    with urllib.request.urlopen(panel.base + href, timeout=10) as r:
        assert r.status == 200 and serial in r.read().decode()
    # history one click away
    page.click("#verdict-history")
    page.wait_for_selector("#history-runs tr:nth-child(2)")
    assert "PASS" in page.inner_text("#history-runs")
    # operator units: degrees with fixed decimals (the API stays SI: radians)
    trend = page.inner_text("#history-trend")
    j2 = stored["result"]["parameters"]["offset.j2"]
    assert f"joint 2 zero offset\tdeg\t{np.degrees(j2['value']):.4f} ± {np.degrees(j2['std']):.4f}" in trend, trend
    assert "e-" not in trend and "rad" not in trend
    # the next scan clears the verdict
    page.focus("#serial")
    page.fill("#serial", "")
    page.keyboard.type("DXL-NEXT")
    page.keyboard.press("Enter")
    page.wait_for_selector("#verdict.pass", state="hidden")
    assert panel.state()["state"] == "idle"


@pytest.mark.slow
def test_failing_unit_names_the_limit(tmp_path, emulators, browser, panels):
    world_path, cell_path = _files(tmp_path, seed=42)
    strict = tmp_path / "strict.yaml"
    strict.write_text(STRICT)
    serial = "DXL-PANEL-42"
    db = f"sqlite:///{tmp_path / 'r.db'}"
    emu = emulators("dynamixel", world_path, serial=serial, process=True)
    panel = panels(tmp_path, _url(emu), cell_path, db, "--limits", str(strict), "--no-confirm")
    page = browser.new_page(viewport={"width": 1920, "height": 1080})
    page.goto(panel.base + "/")
    _sign_in_and_scan(page, serial)
    page.click("#start")
    _verdict(page, panel, "fail", 180_000)
    assert page.inner_text("#verdict-word") == "FAIL"
    failing = page.inner_text("#verdict-failing")
    st = panel.state()
    with open_records(db) as rec:
        stored = rec.session(st["session"])
    (m,) = [m for m in stored["verdict"]["measurements"] if not m["passed"]]
    assert m["name"] == "fit_rms" and "Fit error (rms): " in failing and "above the limit of 0.001 mm" in failing
    assert f"{m['value']:.4g}" in failing
    r, g, b = _green_red(page.screenshot(path=str(tmp_path / "fail-1920x1080.png")))
    assert r > 100 and r > 1.5 * g, (r, g, b)


@pytest.mark.slow
def test_panel_killed_mid_run_resumes_from_the_page(tmp_path, emulators, browser, panels):
    world_path, cell_path = _files(tmp_path, seed=43, time_mode="realtime", time_scale=4.0)
    serial = "DXL-PANEL-43"
    db = f"sqlite:///{tmp_path / 'r.db'}"
    emu = emulators("dynamixel", world_path, serial=serial, process=True)
    panel = panels(tmp_path, _url(emu), cell_path, db, "--no-confirm")
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.goto(panel.base + "/")
    _sign_in_and_scan(page, serial)
    page.click("#start")
    end = time.monotonic() + 90
    while panel.state()["samples"] < 4 and time.monotonic() < end:
        time.sleep(0.05)
    sid = panel.state()["session"]
    st = panel.state()
    assert sid and st["state"] == "running", (st["verdict"], st["message"])
    panel.kill()
    journal = tmp_path / "home" / "sessions" / sid / "journal.jsonl"
    _, before = read_journal(journal)
    kept = [e for e in before if e["type"] == "sample"]
    assert len(kept) >= 4 and not any(e["type"] == "end" for e in before)
    again = panels(tmp_path, _url(emu), cell_path, db, "--no-confirm")
    page.goto(again.base + "/")
    page.wait_for_selector(f"#resumable button[data-session='{sid}']")
    page.click(f"#resumable button[data-session='{sid}']")
    _verdict(page, again, "pass", 180_000)
    assert again.state()["session"] == sid
    _, events = read_journal(journal)
    samples = [e for e in events if e["type"] == "sample"]
    poses = [e["pose"] for e in samples]
    assert len(poses) == len(set(poses)) == 14  # nothing lost, nothing repeated
    assert samples[:len(kept)] == kept
    with open_records(db) as rec:
        assert len(rec.session(sid)["samples"]) == 14
