"""The panel against a hostile web (docs/reliability.md, "Security"): ``station panel`` in its own process, the
requests a page of another site (or a DNS-rebinding one) can make, each refused with 403 and nothing started;
the same request from the panel's own page goes through (so the refusal is the guard's, not an accident). A
planted session under $STATION_HOME/sessions resumed through the panel runs no code of the attacker's."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import socket
import ssl
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from station.engine import events as ev
from station.engine.journal import Journal
from tests.panel.test_panel_browser import Panel, _files

ROBOT = "dynamixel:///dev/null?model=omx"  # never reached: with the confirm prompt nothing opens the robot
EVIL = "http://evil.example"
STATE_CHANGES = [("/api/start", {"serial": "SN-1", "operator": "eve"}), ("/api/prompt", {"answer": "ok"}),
                 ("/api/clear", {}), ("/api/abort", {}), ("/api/resume", {"session": "S-1"})]


def _req(base: str, method: str, path: str, body=None, headers=None, raw: bytes | None = None) -> tuple[int, dict]:
    data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
    req = urllib.request.Request(base + path, data=data, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read() or b"{}")
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read() or b"{}")


def _csrf(base: str) -> str:
    return _req(base, "GET", "/api/csrf")[1]["csrf"]


def _own(panel: Panel, path: str, body: dict) -> tuple[int, dict]:
    """The panel's own page: same origin, JSON, its CSRF token."""
    return _req(panel.base, "POST", path, body, {"Origin": panel.base, "Content-Type": "application/json",
                                                 "X-CSRF-Token": _csrf(panel.base)})


def _nothing_started(panel: Panel, home: Path, planted: tuple[str, ...] = ()) -> None:
    """Idle, no session, no journal but the planted ones."""
    st = panel.state()
    assert st["state"] == "idle" and st["session"] is None and st["serial"] is None, st
    folder = home / "sessions"
    assert sorted(p.name for p in folder.iterdir()) == sorted(planted) if folder.exists() else not planted


@pytest.fixture
def panel(tmp_path):
    _, cell = _files(tmp_path, seed=71)
    p = Panel(tmp_path, ROBOT, cell, f"sqlite:///{tmp_path / 'r.db'}")
    yield p
    p.close()


def _plant(home: Path, sid: str, procedure: str, path: Path, sha: str, url: str = ROBOT) -> Path:
    """A session folder as an attacker (or a copied disk) leaves it: resumable-looking, naming a file."""
    folder = home / "sessions" / sid
    Journal.create(folder / "journal.jsonl", ev.Header(
        session=sid, procedure=procedure, procedure_path=str(path), procedure_sha256=sha, serial="SN-9",
        url=url, limits={"path": None, "version": "v", "sha256": "0" * 64})).close()
    return folder


def _evil(tmp_path: Path) -> tuple[Path, Path, str]:
    marker = tmp_path / "attacker-code-ran"
    evil = tmp_path / "evil.py"
    evil.write_text(f'"""Evil."""\nopen({str(marker)!r}, "w").write("import")\n'
                    f"def checklist(s):\n    open({str(marker)!r}, 'w').write('checklist')\n")
    return evil, marker, hashlib.sha256(evil.read_bytes()).hexdigest()


def test_cross_site_simple_requests_are_refused_and_nothing_starts(panel, tmp_path):
    home = tmp_path / "home"
    _plant(home, "S-1", "zero_offsets", Path("/nonexistent/zero_offsets.py"), "0" * 64)
    before = (home / "sessions" / "S-1" / "journal.jsonl").read_bytes()
    # what any web page open on the station PC can send without a preflight: text/plain, its own Origin
    for path, body in STATE_CHANGES:
        for headers in ({"Origin": EVIL, "Content-Type": "text/plain"},
                        {"Origin": EVIL, "Content-Type": "application/x-www-form-urlencoded"},
                        {"Referer": EVIL + "/page.html", "Content-Type": "text/plain"},
                        {"Origin": "null", "Content-Type": "text/plain"},
                        # a JSON request (preflighted by a browser) with a token from this panel: still not its page
                        {"Origin": EVIL, "Content-Type": "application/json", "X-CSRF-Token": _csrf(panel.base)}):
            code, reply = _req(panel.base, "POST", path, body, headers)
            assert code == 403 and "cross-site" in reply["error"], (path, headers, code, reply)
        # same origin but not the page's request: no CSRF token (403), or not JSON (415)
        code, reply = _req(panel.base, "POST", path, body, {"Origin": panel.base, "Content-Type": "application/json"})
        assert code == 403 and "CSRF" in reply["error"], (path, reply)
        code, reply = _req(panel.base, "POST", path, body, {"Origin": panel.base, "Content-Type": "text/plain",
                                                            "X-CSRF-Token": _csrf(panel.base)})
        assert code == 415, (path, reply)
        _nothing_started(panel, home, ("S-1",))
    assert (home / "sessions" / "S-1" / "journal.jsonl").read_bytes() == before
    assert sorted(p.name for p in (home / "sessions").iterdir()) == ["S-1"]
    # the page's own request goes through: the start waits for the operator's confirm (nothing moves yet) ...
    code, st = _own(panel, "/api/start", {"serial": "SN-1", "operator": "o.one"})
    assert code == 202 and st["state"] in ("running", "prompt"), st  # the worker may be at the prompt already
    end = time.monotonic() + 30
    while panel.state()["state"] != "prompt" and time.monotonic() < end:
        time.sleep(0.05)
    assert panel.state()["state"] == "prompt"
    # ... and the attacker's "ok" to "cell clear? Confirm to start the robot" is refused: the prompt stays open
    code, _ = _req(panel.base, "POST", "/api/prompt", raw=b'{"answer":"ok"}',
                   headers={"Origin": EVIL, "Content-Type": "text/plain"})
    assert code == 403
    st = panel.state()
    assert st["state"] == "prompt" and "Confirm to start the robot" in st["prompt"]["text"]
    assert sorted(p.name for p in (home / "sessions").iterdir()) == ["S-1"]  # nothing journaled, nothing moved
    code, st = _own(panel, "/api/prompt", {"answer": "abort"})
    assert code == 200


def test_dns_rebinding_host_is_refused_on_every_route(panel):
    port = panel.port
    for host in (f"evil.example:{port}", "evil.example", f"127.0.0.1.evil.example:{port}", f"127.0.0.1:{port + 1}",
                 f"localhost:{port}@evil.example"):
        for method, path in (("GET", "/"), ("GET", "/api/state"), ("GET", "/api/csrf"), ("GET", "/api/resumable"),
                             ("GET", "/api/events"), ("GET", "/report/x"), ("POST", "/api/start")):
            # what the rebinding page sends: its own name as Host and (for a POST) as Origin
            headers = {"Host": host, "Origin": f"http://{host}", "Content-Type": "application/json"}
            code, reply = _req(panel.base, method, path, {"serial": "SN-2", "operator": "eve"}
                               if method == "POST" else None, headers)
            assert code == 403 and "Host" in reply["error"], (host, path, code, reply)
    _nothing_started(panel, panel_home(panel))
    # the panel's own names are served
    for host in (f"127.0.0.1:{port}", f"localhost:{port}", f"LOCALHOST:{port}"):
        assert _req(panel.base, "GET", "/api/state", headers={"Host": host})[0] == 200, host


def panel_home(panel: Panel) -> Path:
    return panel.home


def test_planted_sessions_run_no_foreign_code_through_the_panel(panel, tmp_path):
    home = tmp_path / "home"
    evil, marker, sha = _evil(tmp_path)
    _plant(home, "P-evil", "evil", evil, sha)  # names the attacker's file with its own sha256
    _plant(home, "P-shadow", "zero_offsets", evil, sha)  # a shipped name, the attacker's file and sha
    _plant(home, "P-other-robot", "zero_offsets", evil, sha, url="ur://192.0.2.9?model=ur5e")
    code, listed = _req(panel.base, "GET", "/api/resumable")
    assert code == 200 and listed == []  # none of them is offered
    for sid, says in (("P-evil", "unknown procedure 'evil'"), ("P-shadow", "sha256 differs"),
                      ("P-other-robot", "not on this panel's robot")):
        code, reply = _own(panel, "/api/resume", {"session": sid})
        assert code == 400 and says in reply["error"] and "\n" not in reply["error"], (sid, reply)
    for ref in (str(home / "sessions" / "P-evil"), str(home / "sessions" / "P-evil" / "journal.jsonl"),
                "../sessions/P-evil", "."):
        code, reply = _own(panel, "/api/resume", {"session": ref})
        assert code == 400 and "not a session id" in reply["error"], (ref, reply)
    # a start request does not name code either: a path is refused, a name is looked up where procedures live
    for proc, says in ((str(evil), "not a procedure name"), ("../evil", "not a procedure name"),
                       ("evil", "unknown procedure 'evil'")):
        code, reply = _own(panel, "/api/start", {"serial": "SN-3", "operator": "o", "procedure": proc})
        assert code == 400 and says in reply["error"], (proc, reply)
    _nothing_started(panel, home, ("P-evil", "P-shadow", "P-other-robot"))
    assert not marker.exists()  # no file of the attacker's ran


@pytest.mark.parametrize("fast_only", [True, pytest.param(False, marks=pytest.mark.slow)], ids=["refusals", "tls"])
def test_off_loopback_with_tls_client_certificates_and_refusals(tmp_path, fast_only):
    """Beyond loopback: a token or TLS client certificates, else the panel does not start (one line, exit 2);
    with client certificates required, a client without one gets no answer at all (the ``tls`` run)."""
    from clirunner import station_main, station_spawn

    from tests.opcua.test_opcua_server import _cert

    _, cell = _files(tmp_path, seed=72)
    base = ["panel", "--robot", ROBOT, "--cell", str(cell)]
    cert, key = _cert(tmp_path, "station")
    pem = tmp_path / "station-cert.pem"
    for extra, says in (([], "--token"), (["--tls-cert", str(pem), "--tls-key", str(key)], "--token"),
                        (["--tls-client-ca", str(pem)], "--tls-cert"),
                        (["--tls-cert", str(key), "--tls-key", str(key), "--tls-client-ca", str(pem)], "TLS files"),
                        (["--token", "t0k3n-abcdef", "--allow-host", "a b"], "--allow-host")):
        code, _, err = station_main(*base, "--host", "0.0.0.0", *extra)  # refused before it listens
        lines = err.strip().splitlines()
        assert code == 2 and lines[-1].startswith("station: error: ") and says in lines[-1], (extra, err)
    if fast_only:
        return
    client_cert, client_key = _cert(tmp_path, "client")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = station_spawn(*base, "--host", "0.0.0.0", "--port", port, "--tls-cert", pem, "--tls-key", key,
                         "--tls-client-ca", tmp_path / "client-cert.pem", module=True,
                         env={"STATION_HOME": str(tmp_path / "home")})
    try:
        ctx = ssl.create_default_context(cafile=str(pem))
        ctx.check_hostname = False
        end = time.monotonic() + 60
        while True:  # up: the handshake without a client certificate is refused
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=5) as raw, \
                        ctx.wrap_socket(raw, server_hostname="localhost") as tls:
                    tls.sendall(b"GET /api/state HTTP/1.1\r\nHost: localhost\r\n\r\n")
                    got = tls.recv(100)
                assert not got.startswith(b"HTTP/1.1 200"), got
                break
            except (ssl.SSLError, ConnectionResetError, BrokenPipeError):
                break
            except OSError:
                if not proc.running() or time.monotonic() > end:
                    raise AssertionError(proc.wait()) from None
                time.sleep(0.2)
        ctx.load_cert_chain(str(tmp_path / "client-cert.pem"), str(client_key))
        for host, want in ((f"localhost:{port}", b"200"), (f"evil.example:{port}", b"403")):
            with socket.create_connection(("127.0.0.1", port), timeout=10) as raw, \
                    ctx.wrap_socket(raw, server_hostname="localhost") as tls:
                tls.sendall(f"GET /api/state HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n".encode())
                got = b""
                while chunk := tls.recv(4096):
                    got += chunk
            assert got.split(b"\r\n", 1)[0] == b"HTTP/1.1 " + want + (b" OK" if want == b"200" else b" Forbidden"), got
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)


EVIL_PAGE = """<!doctype html><html><body><h1>cat pictures</h1>
<iframe name="sink" style="display:none"></iframe>
<form id="f" method="POST" enctype="text/plain" target="sink" action="{panel}/api/start">
<input name='{{"serial":"SN-EVIL","operator":"eve","x":"' value='"}}'></form>
<script>
const P = "{panel}";
async function attack() {{
  const send = (path, body, type) => fetch(P + path, {{method: "POST", mode: "no-cors", credentials: "include",
      headers: {{"Content-Type": type}}, body: JSON.stringify(body)}}).catch(() => null);
  for (let i = 0; i < 3; i++) {{
    await send("/api/start", {{serial: "SN-EVIL", operator: "eve"}}, "text/plain");
    await send("/api/prompt", {{answer: "ok"}}, "text/plain");
    await send("/api/clear", {{}}, "text/plain");
    await send("/api/resume", {{session: "S-1"}}, "text/plain");
    await send("/api/abort", {{}}, "text/plain");
    // a JSON request needs a preflight the panel never grants: it must not even be sent
    await fetch(P + "/api/start", {{method: "POST", credentials: "include",
      headers: {{"Content-Type": "application/json"}}, body: JSON.stringify({{serial: "SN-EVIL", operator: "e"}})}})
      .catch(() => null);
  }}
  document.getElementById("f").submit();
  // reading the panel is refused too (no CORS): the page cannot learn a CSRF token
  const r = await fetch(P + "/api/csrf", {{credentials: "include"}}).then((x) => x.text()).catch(() => "blocked");
  document.title = "done:" + r;
}}
attack();
</script></body></html>"""


def _evil_site(panel_base: str):
    """Another web site open on the station PC (another origin on this machine)."""
    import threading
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    page = EVIL_PAGE.format(panel=panel_base).encode()

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 - http.server's name
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(page)))
            self.end_headers()
            self.wfile.write(page)

        def log_message(self, *a):
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


@pytest.mark.slow
def test_real_browser_page_works_with_its_tokens_and_other_sites_cannot_drive_it(tmp_path):
    """Debian's chromium (Playwright): the panel with ``--token`` opened as the operator does (``/?token=``),
    sign in, scan, START, the confirm prompt, the verdict, the next scan (start, prompt and clear: each a state
    change with the page's CSRF token). Meanwhile a page of another site in the same browser (same machine,
    another port: the token cookie is "same-site" and goes along) fires every state change as simple requests and
    as a form: nothing starts. A rebinding name mapped to 127.0.0.1 gets 403 for the page itself."""
    from tests.panel.test_panel_browser import CHROMIUM

    if not os.path.exists(CHROMIUM):
        pytest.fail("needs Debian's chromium (apt-get install -y chromium; .ci/run does)", pytrace=False)
    from playwright.sync_api import sync_playwright

    _, cell = _files(tmp_path, seed=73)
    panel = Panel(tmp_path, ROBOT, cell, f"sqlite:///{tmp_path / 'r.db'}", "--token", "line-token-73")
    evil = _evil_site(panel.base)
    home = tmp_path / "home"
    _plant(home, "S-1", "zero_offsets", Path("/nonexistent/zero_offsets.py"), "0" * 64)
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=[
                "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                "--host-resolver-rules=MAP evil.example 127.0.0.1"])
            ctx = browser.new_context(viewport={"width": 1280, "height": 800})
            page = ctx.new_page()
            page.goto(panel.base + "/?token=line-token-73")  # sets the HttpOnly SameSite=Strict cookie
            page.fill("#operator", "a.operator")
            page.press("#operator", "Enter")
            page.keyboard.type("SN-PAGE-73")
            page.keyboard.press("Enter")
            # another site in the same browser, while the operator's page is signed in and armed
            bad = ctx.new_page()
            bad.goto(f"http://127.0.0.1:{evil.server_address[1]}/")
            bad.wait_for_function("document.title.startsWith('done:')", timeout=30_000)
            assert "csrf" not in bad.title()  # it could not read a token
            time.sleep(0.5)
            st = _req(panel.base, "GET", "/api/state", headers={"Authorization": "Bearer line-token-73"})[1]
            assert st["state"] == "idle" and st["serial"] is None, st
            assert sorted(p.name for p in (home / "sessions").iterdir()) == ["S-1"]
            # a rebinding name for this machine: the panel refuses to serve its page under it
            r = bad.goto(f"http://evil.example:{panel.port}/?token=line-token-73")
            assert r.status == 403 and "Host" in bad.content()
            # the operator's page works: START, the confirm prompt, the verdict, the next scan
            page.click("#start")
            page.wait_for_selector("#prompt-text", state="visible", timeout=20_000)
            assert "Confirm to start the robot" in page.inner_text("#prompt-text")
            page.click("#prompt-ok")
            page.wait_for_selector("#verdict.error", timeout=60_000)  # the robot at /dev/null: ERROR in words
            assert "/dev/null" in page.text_content("#verdict-message") or panel_msg(panel)
            # nothing was journaled, so no RESUME: TRY AGAIN starts the same unit again (a POST with the page's
            # token, through the confirm prompt once more)
            assert page.is_visible("#verdict-retry") and not page.is_visible("#verdict-resume")
            page.click("#verdict-retry")
            page.wait_for_selector("#prompt-text", state="visible", timeout=20_000)
            assert "SN-PAGE-73" in page.inner_text("#prompt-text")
            page.click("#prompt-ok")
            page.wait_for_selector("#verdict.error", timeout=60_000)
            page.focus("#next-serial")
            page.keyboard.type("SN-NEXT")
            page.keyboard.press("Enter")
            page.wait_for_selector("#verdict.error", state="hidden")
            st = _req(panel.base, "GET", "/api/state", headers={"Authorization": "Bearer line-token-73"})[1]
            assert st["state"] == "idle"
            browser.close()
    finally:
        evil.shutdown()
        panel.close()
    assert not (home / "sessions" / "S-1" / "journal.jsonl").read_text().count('"type":"resume"')


def panel_msg(panel: Panel) -> str:
    return str(_req(panel.base, "GET", "/api/state", headers={"Authorization": "Bearer line-token-73"})[1]["message"])


def test_host_and_origin_rules_of_the_guard():
    """The rules themselves (no server): loopback names with the port; a reverse proxy's name by --allow-host;
    Origin must be the Host the request came to, in the panel's scheme."""
    from station.panel.webguard import Guard

    g = Guard(None, bind="127.0.0.1", port=8470, loopback=True, allow_hosts=("station.line3.example",
                                                                                  "proxy.example:443"))
    for ok in ("127.0.0.1:8470", "localhost:8470", "[::1]:8470", "LocalHost:8470", "station.line3.example",
               "station.line3.example:8443", "proxy.example:443"):
        assert g.host_ok(ok), ok
    for bad in ("127.0.0.1", "127.0.0.1:80", "evil.example:8470", "proxy.example", "proxy.example:8470",
                "localhost.:8471", "a@127.0.0.1:8470", "127.0.0.1:8470/x", "[::1", ""):
        assert not g.host_ok(bad), bad
    assert g.origin_ok("http://127.0.0.1:8470", None, "127.0.0.1:8470")[0]
    assert g.origin_ok(None, "http://localhost:8470/x?y", "localhost:8470")[0]
    assert g.origin_ok(None, None, "localhost:8470")[0]  # no browser: the CSRF token still decides
    assert g.origin_ok("https://station.line3.example", None, "station.line3.example")[0]  # TLS at the proxy
    for origin, host in (("http://localhost:8470", "127.0.0.1:8470"), ("https://127.0.0.1:8470", "127.0.0.1:8470"),
                         ("http://127.0.0.1:8471", "127.0.0.1:8470"), ("null", "127.0.0.1:8470"),
                         ("http://evil.example", "127.0.0.1:8470"), ("file://", "127.0.0.1:8470")):
        assert not g.origin_ok(origin, None, host)[0], (origin, host)
    token = g.new_token()
    forged = token[:-1] + ("1" if token[-1] == "0" else "0")  # one hex digit of the signature changed
    assert g.token_ok(token) and not g.token_ok(forged) and not g.token_ok("x.y") and not g.token_ok(None)
    assert not Guard(None, bind="127.0.0.1", port=8470, loopback=True).token_ok(token)  # another panel process
