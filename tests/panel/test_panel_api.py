"""The panel's public JSON API over HTTP (``station panel`` in its own process, emulated Dynamixel arm):
never PASS unless stored (an unwritable records database ends as NOT STORED, the journal keeps the run),
the token off loopback, and bad requests refused with a reason."""

from __future__ import annotations

import json
import time
import urllib.error
import urllib.request

import pytest
from clirunner import station_proc

from station.engine import read_journal
from tests.panel.test_panel_browser import Panel, _files, _url


def _call(base: str, method: str, path: str, body=None, headers=None) -> tuple[int, dict]:
    """A script's request: a state change carries a CSRF token from ``GET /api/csrf`` (docs/panel.md)."""
    data = None if body is None else json.dumps(body).encode()
    headers = {"Content-Type": "application/json", **(headers or {})}
    if method != "GET":
        code, got = _call(base, "GET", "/api/csrf", headers=headers)
        if code == 200:
            headers["X-CSRF-Token"] = got["csrf"]
    req = urllib.request.Request(base + path, data=data, method=method, headers=headers)
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read() or b"{}")
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read() or b"{}")


@pytest.fixture
def panels():
    started = []

    def make(*a) -> Panel:
        p = Panel(*a)
        started.append(p)
        return p

    yield make
    for p in started:
        p.close()


def test_unstorable_record_ends_not_stored_never_pass(tmp_path, emulators, panels):
    world_path, cell_path = _files(tmp_path, seed=61)
    serial = "DXL-API-61"
    # the database takes the pre-run check (the station opens and proves it before the robot moves) and goes
    # away mid-run: the file becomes a directory, which SQLite cannot open, so storing fails at the end
    dbfile = tmp_path / "r.db"
    db = f"sqlite:///{dbfile}"
    emu = emulators("dynamixel", world_path, serial=serial, process=True)
    panel = panels(tmp_path, _url(emu), cell_path, db, "--no-confirm")
    code, st = _call(panel.base, "POST", "/api/start", {"serial": serial, "operator": "o.one"})
    assert code == 202 and st["state"] == "running"
    seen = set()
    end = time.monotonic() + 180
    while time.monotonic() < end:
        st = panel.state()
        seen.add(st["verdict"])
        if st["samples"] >= 1 and dbfile.is_file():
            dbfile.unlink()
            dbfile.mkdir()
        if st["state"] == "done":
            break
        time.sleep(0.05)
    assert dbfile.is_dir(), "the run ended before the database went away"
    assert st["verdict"] == "NOT STORED" and st["stored"] is False and "PASS" not in seen, st["message"]
    assert "station records sync" in st["message"]
    journal = tmp_path / "home" / "sessions" / st["session"] / "journal.jsonl"
    _, events = read_journal(journal)
    assert events[-1]["type"] == "end" and events[-1]["status"] == "completed"
    assert sum(e["type"] == "sample" for e in events) == 14  # the journal keeps everything


def test_bad_requests_are_refused_with_a_reason(tmp_path, panels):
    _, cell_path = _files(tmp_path, seed=62)
    panel = panels(tmp_path, "dynamixel:///dev/null?model=omx", cell_path, f"sqlite:///{tmp_path / 'r.db'}")
    assert _call(panel.base, "POST", "/api/start", {"serial": "", "operator": "x"})[0] == 400
    code, body = _call(panel.base, "POST", "/api/start", {"serial": "A1", "operator": ""})
    assert code == 400 and "sign in" in body["error"]
    assert _call(panel.base, "POST", "/api/prompt", {"answer": "ok"})[0] == 409
    assert _call(panel.base, "POST", "/api/abort")[0] == 409
    code, body = _call(panel.base, "GET", "/api/history/NOPE")
    assert code == 200 and body == {"serial": "NOPE", "runs": [], "trend": {}}
    st = panel.state()
    assert {k: st[k] for k in ("state", "serial", "verdict", "samples", "samples_planned")} == {
        "state": "idle", "serial": None, "verdict": None, "samples": 0, "samples_planned": 0}


def test_token_required_and_checked(tmp_path, panels):
    _, cell_path = _files(tmp_path, seed=63)
    panel = panels(tmp_path, "dynamixel:///dev/null?model=omx", cell_path, f"sqlite:///{tmp_path / 'r.db'}",
                   "--token", "s3cret-line-7")
    assert _call(panel.base, "GET", "/api/state")[0] == 401
    assert _call(panel.base, "GET", "/api/state", headers={"Authorization": "Bearer wrong"})[0] == 401
    assert _call(panel.base, "GET", "/api/state", headers={"Authorization": "Bearer s3cret-line-7"})[0] == 200
    assert _call(panel.base, "POST", "/api/start", {"serial": "A", "operator": "b"})[0] == 401
    # opening the page with ?token= once sets the cookie the page's own requests carry
    opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor())
    with opener.open(panel.base + "/?token=s3cret-line-7", timeout=10) as r:
        assert r.status == 200 and "START" in r.read().decode()
    with opener.open(panel.base + "/api/state", timeout=10) as r:
        assert json.loads(r.read())["state"] == "idle"


def test_off_loopback_without_token_is_refused(tmp_path):
    _, cell_path = _files(tmp_path, seed=64)
    proc = station_proc("panel", "--robot", "dynamixel:///dev/null?model=omx", "--cell", cell_path, "--host", "0.0.0.0",
                        timeout=60)
    assert proc.code == 2
    lines = proc.err_lines
    assert len(lines) == 1 and lines[0].startswith("station: error: ") and "--token" in lines[0], proc.err
