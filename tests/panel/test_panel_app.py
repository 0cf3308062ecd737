"""``station.panel.app`` and ``station.panel.serve``: the panel's HTTP interface in process (Starlette's test
client), its guard (token, CSRF, Host), and the refusal to listen off loopback unprotected."""

from __future__ import annotations

import warnings

import pytest

from station.panel import Controller, PanelConfig
from station.panel.app import create_app
from station.panel.serve import TLS, check_listen, is_loopback
from station.robot.errors import ConfigError

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from starlette.testclient import TestClient


@pytest.fixture
def client():
    ctl = Controller(PanelConfig(robot="ur://127.0.0.1:9?model=ur5e", confirm=False))
    app = create_app(ctl, token="s3cret", host="127.0.0.1", port=8470)
    with TestClient(app, base_url="http://127.0.0.1:8470") as c:
        yield c


def test_state_token_and_csrf(client):
    assert client.get("/api/state").status_code == 401  # the token is required
    auth = {"Authorization": "Bearer s3cret"}
    r = client.get("/api/state", headers=auth)
    assert r.status_code == 200 and r.json()["state"] == "idle"
    # a state change without the page's CSRF token is refused; with it, the start is judged on its merits
    r = client.post("/api/start", json={"serial": "X"}, headers=auth)
    assert r.status_code == 403 and "X-CSRF-Token" in r.text
    token = client.get("/api/csrf", headers=auth).json()["csrf"]
    r = client.post("/api/start", json={"serial": ""}, headers={**auth, "X-CSRF-Token": token})
    assert r.status_code == 400 and "serial" in r.json()["error"]
    # another Host (DNS rebinding): refused
    assert client.get("/api/state", headers={**auth, "Host": "evil.example:8470"}).status_code in (400, 403)


def test_listening_rules(tmp_path):
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.0.2.7")
    check_listen("127.0.0.1", None)  # loopback: no token needed
    with pytest.raises(ConfigError, match="--host 0.0.0.0 is not loopback: the panel then requires --token"):
        check_listen("0.0.0.0", None)
    with pytest.raises(ConfigError, match="--tls-cert .*: no such file"):
        check_listen("0.0.0.0", "t", TLS(tmp_path / "c.pem", tmp_path / "k.pem"))
