"""``station opcua`` with a real asyncua client on loopback: browse urn:station/Station, subscribe to Verdict,
call Start(serial, procedure) on an emulated Dynamixel arm with hidden offsets, read LastResult once the verdict
arrives and check it against the records database and the hidden truth; Abort; refusal off loopback."""

from __future__ import annotations

import asyncio
import contextlib
import json
import signal
import socket
import subprocess
import time

import numpy as np
import pytest
from clirunner import station_main, station_spawn
from station.mocks.world import World

from station.records import open_records
from tests.panel.test_panel_browser import _files, _url


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _server(tmp_path, url, cell, db, endpoint, *extra):
    return station_spawn("opcua", "--robot", url, "--cell", cell, "--db", db, "--endpoint", endpoint, "--reference",
                         "cell", "--cone", "70", "--poses", "12", "--holdout", "2", *extra, module=True,
                         env={"STATION_HOME": str(tmp_path / "home")})


def _unit_server(tmp_path, emulators, seed: int, serial: str, *extra: str, **files):
    """An emulated Dynamixel arm (its own process) with hidden offsets and ``station opcua`` for it:
    ``(world_path, db, endpoint, proc)``."""
    world_path, cell_path = _files(tmp_path, seed=seed, **files)
    db = f"sqlite:///{tmp_path / 'r.db'}"
    endpoint = f"opc.tcp://127.0.0.1:{_free_port()}"
    emu = emulators("dynamixel", world_path, serial=serial, process=True)
    return world_path, db, endpoint, _server(tmp_path, _url(emu), cell_path, db, endpoint, *extra)


async def _connect(endpoint: str, proc):
    from asyncua import Client

    end = time.monotonic() + 60
    while True:
        # asyncua's client probes the server every watchdog_intervall (default 1 s) and must get the answer
        # within that time, else it drops the connection ("client is disconnected"): at load ~9 on 2 cores the
        # server answered later than 1 s while a procedure ran. A client-side liveness setting, not the server's.
        client = Client(endpoint, timeout=10, watchdog_intervall=10.0)
        try:
            await client.connect()
            return client
        except (OSError, TimeoutError):
            if not proc.running() or time.monotonic() > end:
                raise AssertionError(proc.wait()) from None
            await asyncio.sleep(0.3)


class _Verdicts:
    def __init__(self) -> None:
        self.values: list[str] = []

    def datachange_notification(self, node, val, data) -> None:
        self.values.append(val)


async def _station_nodes(client):
    idx = await client.get_namespace_index("urn:station")
    station = await client.nodes.objects.get_child(f"{idx}:Station")
    names = ("State", "Serial", "Procedure", "Step", "Progress", "Verdict", "LastResult", "Start", "Abort")
    return idx, station, {n: await station.get_child(f"{idx}:{n}") for n in names}


async def _wait(pred, timeout: float) -> None:
    end = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > end:
            raise AssertionError("timed out")
        await asyncio.sleep(0.1)


@pytest.mark.slow
def test_start_subscribe_verdict_read_result(tmp_path, emulators):
    serial = "DXL-OPC-51"
    world_path, db, endpoint, proc = _unit_server(tmp_path, emulators, 51, serial, "--users",
                                                  str(_users_file(tmp_path)))

    async def scenario():
        from asyncua import ua

        client = await _signed_in(endpoint, proc, "mes", "mes-pass-1")  # rights read and operate
        try:
            idx, station, n = await _station_nodes(client)
            assert await n["State"].read_value() == "idle" and await n["Verdict"].read_value() == ""
            handler = _Verdicts()
            sub = await client.create_subscription(50, handler)
            await sub.subscribe_data_change(n["Verdict"])
            with pytest.raises(ua.uaerrors.BadInvalidArgument):  # a serial with a space: refused, nothing starts
                await station.call_method(n["Start"], ua.Variant("BAD SERIAL", ua.VariantType.String),
                                          ua.Variant("", ua.VariantType.String))
            assert json.loads(await n["LastResult"].read_value())["verdict"] == "ERROR"  # ... and says why
            session = await station.call_method(n["Start"], ua.Variant(serial, ua.VariantType.String),
                                                ua.Variant("zero_offsets", ua.VariantType.String))
            assert session.startswith(f"zero_offsets-{serial}-")
            assert await n["Serial"].read_value() == serial and await n["Verdict"].read_value() == ""
            end = time.monotonic() + 180
            while not (verdict := await n["Verdict"].read_value()) and time.monotonic() < end:
                await asyncio.sleep(0.1)
            await _wait(lambda: verdict in handler.values, 10)  # the subscriber was told too
            result = json.loads(await n["LastResult"].read_value())
            progress = await n["Progress"].read_value()
            state = await n["State"].read_value()
            await sub.delete()
            return session, verdict, result, progress, state
        finally:
            await client.disconnect()

    try:
        session, verdict, result, progress, state = asyncio.run(scenario())
        hidden = World.from_file(world_path).hidden()
    finally:
        proc.send_signal(signal.SIGINT)
        _, out, err = proc.wait(timeout=30)
    assert verdict == "PASS" and state == "done" and progress == 1.0
    assert result["session"] == session and result["verdict"] == "PASS" and result["stored"] is True
    with open_records(db) as rec:  # PASS on the line means the record is in the database
        stored = rec.session(session)
    assert stored["verdict"]["passed"] is True and stored["operator"] == "mes"  # who started it, by name
    for name, p in result["parameters"].items():
        if name.startswith("offset.") and p["identifiable"]:
            assert p["value"] == pytest.approx(stored["result"]["parameters"][name]["value"], abs=1e-12)
            assert abs(p["value"] - hidden[name]) <= 4 * p["std"] + np.pi / 4096, name


@pytest.mark.slow
def test_abort_through_opcua_leaves_a_resumable_session(tmp_path, emulators):
    serial = "DXL-OPC-52"
    _, db, endpoint, proc = _unit_server(tmp_path, emulators, 52, serial, time_mode="realtime", time_scale=2.0)

    async def scenario():
        from asyncua import ua

        client = await _connect(endpoint, proc)
        try:
            _, station, n = await _station_nodes(client)
            session = await station.call_method(n["Start"], ua.Variant(serial, ua.VariantType.String),
                                                ua.Variant("", ua.VariantType.String))
            end = time.monotonic() + 90
            while await n["Progress"].read_value() <= 0 and time.monotonic() < end:
                await asyncio.sleep(0.1)
            await station.call_method(n["Abort"])
            while await n["State"].read_value() != "done" and time.monotonic() < end:
                await asyncio.sleep(0.1)
            return session, await n["Verdict"].read_value(), json.loads(await n["LastResult"].read_value())
        finally:
            await client.disconnect()

    try:
        session, verdict, result = asyncio.run(scenario())
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
    assert verdict == "ABORTED" and result["session"] == session
    journal = tmp_path / "home" / "sessions" / session / "journal.jsonl"
    last = json.loads(journal.read_text().strip().splitlines()[-1])
    assert last["type"] == "end" and last["status"] == "interrupted"  # teardown ran; `station resume` continues


@pytest.mark.parametrize("endpoint", ["opc.tcp://0.0.0.0:4841", "opc.tcp://192.0.2.7:4841"])
def test_off_loopback_without_certificates_is_refused(tmp_path, endpoint):
    world_path, cell_path = _files(tmp_path, seed=53)
    proc = _server(tmp_path, "dynamixel:///dev/null?model=omx", cell_path, "sqlite:///x.db", endpoint)
    _, out, err = proc.wait(timeout=60)
    assert proc.returncode == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("station: error: ") and "Basic256Sha256" in lines[0], err


def _cert(folder, name: str):
    key, cert = folder / f"{name}-key.pem", folder / f"{name}-cert.der"
    pem = folder / f"{name}-cert.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "30", "-keyout", str(key),
                    "-out", str(pem), "-subj", f"/CN={name}", "-addext",
                    f"subjectAltName=URI:urn:{name},DNS:localhost,IP:127.0.0.1"], check=True, capture_output=True)
    subprocess.run(["openssl", "x509", "-in", str(pem), "-outform", "der", "-out", str(cert)], check=True,
                   capture_output=True)
    return cert, key


@pytest.mark.slow
def test_basic256sha256_endpoint_refuses_unencrypted_clients(tmp_path):
    from asyncua import Client

    world_path, cell_path = _files(tmp_path, seed=54)
    cert, key = _cert(tmp_path, "station")
    ccert, ckey = _cert(tmp_path, "client")
    endpoint = f"opc.tcp://127.0.0.1:{_free_port()}"
    proc = _server(tmp_path, "dynamixel:///dev/null?model=omx", cell_path, f"sqlite:///{tmp_path / 'r.db'}",
                   endpoint, "--cert", str(cert), "--key", str(key), "--users", str(_users_file(tmp_path)))

    async def scenario():
        end = time.monotonic() + 60
        while True:  # wait until it listens
            try:
                with socket.create_connection(("127.0.0.1", int(endpoint.rsplit(":", 1)[1])), timeout=1):
                    break
            except OSError:
                if not proc.running() or time.monotonic() > end:
                    raise AssertionError(proc.wait()) from None
                await asyncio.sleep(0.3)
        plain = Client(endpoint, timeout=10)
        with pytest.raises(Exception):  # noqa: B017 - asyncua raises BadSecurityPolicyRejected or similar
            await plain.connect()
            await _station_nodes(plain)
        secure = Client(endpoint, timeout=30)  # RSA handshakes on a loaded 2-core host
        secure.application_uri = "urn:client"
        await secure.set_security_string(f"Basic256Sha256,SignAndEncrypt,{ccert},{ckey}")
        secure.set_user("scada")  # the password travels encrypted under the endpoint's policy
        secure.set_password("scada-pass-1")
        await secure.connect()
        try:
            _, _, n = await _station_nodes(secure)
            return await n["State"].read_value()
        finally:
            await secure.disconnect()

    try:
        assert asyncio.run(scenario()) == "idle"
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)


# ---- users and rights ----------------------------------------------------------------------------------------
def _users_file(tmp_path):
    from station.opcua.users import hash_password

    f = tmp_path / "users.yaml"
    f.write_text("format: station-opcua-users/1\nusers:\n"
                 f"  - name: mes\n    password: {hash_password('mes-pass-1')}\n    rights: [read, operate]\n"
                 f"  - name: scada\n    password: {hash_password('scada-pass-1')}\n    rights: [read]\n")
    return f


async def _signed_in(endpoint: str, proc, user: str | None, password: str | None):
    from asyncua import Client

    end = time.monotonic() + 60
    while True:
        client = Client(endpoint, timeout=10, watchdog_intervall=10.0)
        if user is not None:
            client.set_user(user)
            client.set_password(password)
        try:
            await client.connect()
            return client
        except (OSError, TimeoutError):
            if not proc.running() or time.monotonic() > end:
                raise AssertionError(proc.wait()) from None
            await asyncio.sleep(0.3)


@pytest.mark.slow
def test_users_and_rights_read_and_operate(tmp_path):
    """With a users file: no anonymous session, no wrong password, five wrong ones lock the name; ``read`` may
    browse, read and subscribe but not call Start/Abort nor write; ``operate`` may call them (and is still
    refused a procedure given as a path). Nothing starts for a refused call."""
    from asyncua import ua

    _, cell_path = _files(tmp_path, seed=55)
    marker = tmp_path / "attacker-code-ran"
    (tmp_path / "evil.py").write_text(f'"""Evil."""\nopen({str(marker)!r}, "w")\ndef checklist(s):\n    pass\n')
    endpoint = f"opc.tcp://127.0.0.1:{_free_port()}"
    proc = _server(tmp_path, "dynamixel:///dev/null?model=omx", cell_path, f"sqlite:///{tmp_path / 'r.db'}", endpoint,
                   "--users", str(_users_file(tmp_path)))

    async def refused(user, password) -> str:
        from asyncua import Client

        c = Client(endpoint, timeout=10)
        if user is not None:
            c.set_user(user)
            c.set_password(password)
        with pytest.raises(ua.UaStatusCodeError) as e:
            await c.connect()
        with contextlib.suppress(Exception):
            await c.disconnect()
        return type(e.value).__name__

    async def scenario():
        reader = await _signed_in(endpoint, proc, "scada", "scada-pass-1")
        try:
            _, station, n = await _station_nodes(reader)
            assert await n["State"].read_value() == "idle"
            sub = await reader.create_subscription(50, _Verdicts())  # subscribing is reading
            await sub.subscribe_data_change(n["Verdict"])
            for call in (lambda: station.call_method(n["Start"], ua.Variant("SN-R", ua.VariantType.String),
                                                     ua.Variant("", ua.VariantType.String)),
                         lambda: station.call_method(n["Abort"]),
                         lambda: n["State"].write_value("done")):
                with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                    await call()
            assert await n["State"].read_value() == "idle" and await n["Serial"].read_value() == ""
        finally:
            await reader.disconnect()
        assert await refused(None, None) == "BadIdentityTokenRejected"  # anonymous
        assert await refused("scada", "wrong") == "BadUserAccessDenied"
        assert await refused("nobody", "scada-pass-1") == "BadUserAccessDenied"
        operator = await _signed_in(endpoint, proc, "mes", "mes-pass-1")
        try:
            _, station, n = await _station_nodes(operator)
            for serial, procedure, code in (("BAD SERIAL", "", "BadInvalidArgument"),
                                            ("SN-O", str(tmp_path / "evil.py"), "BadInvalidArgument"),
                                            ("SN-O", "evil", "BadInvalidArgument")):
                with pytest.raises(ua.UaStatusCodeError) as e:
                    await station.call_method(n["Start"], ua.Variant(serial, ua.VariantType.String),
                                              ua.Variant(procedure, ua.VariantType.String))
                assert type(e.value).__name__ == code, (serial, procedure, e.value)
                refusal = json.loads(await n["LastResult"].read_value())  # the reason for the line, in words
                assert refusal["verdict"] == "ERROR" and refusal["session"] is None and refusal["reason"]
            await station.call_method(n["Abort"])  # the call is allowed: it gives the refused unit up (ABORTED)
            with pytest.raises(ua.uaerrors.BadInvalidState):  # then nothing is running, nothing to give up
                await station.call_method(n["Abort"])
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):  # operate is not write
                await n["Verdict"].write_value("PASS")
            assert await n["State"].read_value() == "done" and await n["Verdict"].read_value() == "ABORTED"
        finally:
            await operator.disconnect()
        for _ in range(5):
            await refused("mes", "guess")
        assert await refused("mes", "mes-pass-1") == "BadUserAccessDenied"  # locked for a minute

    try:
        asyncio.run(scenario())
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
    assert not marker.exists() and not (tmp_path / "home" / "sessions").exists()


@pytest.mark.parametrize("text, says", [
    ("format: station-opcua-users/1\nusers:\n  - name: a\n    password: hunter2\n    rights: [read]\n",
     ":4: users[0].password: expected a scrypt hash"),
    ("format: station-opcua-users/1\nusers:\n  - name: a\n    password: HASH\n    rights: [admin]\n",
     ":5: users[0].rights: expected a list of read and operate"),
    ("format: station-opcua-users/1\nusers:\n  - name: a\n    password: HASH\n    rights: [read]\n"
     "  - name: a\n    password: HASH\n    rights: [read]\n", ":6: users[1].name: user 'a' appears twice"),
    ("format: station-opcua-users/2\nusers: []\n", ":1: format"),
])
def test_bad_users_file_is_one_line(tmp_path, text, says):
    world_path, cell_path = _files(tmp_path, seed=56)
    from station.opcua.users import hash_password

    f = tmp_path / "users.yaml"
    f.write_text(text.replace("HASH", hash_password("x" * 8)))
    code, _, err = station_main(*["opcua", "--robot", "dynamixel:///dev/null?model=omx", "--cell", cell_path,
                         "--endpoint", "opc.tcp://127.0.0.1:4899", "--users", f])  # refused before it listens
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("station: error: users file"), err
    assert says in lines[0], lines[0]


def test_off_loopback_without_users_is_refused(tmp_path):
    _, cell_path = _files(tmp_path, seed=57)
    cert, key = _cert(tmp_path, "station")
    proc = _server(tmp_path, "dynamixel:///dev/null?model=omx", cell_path, "sqlite:///x.db",
                   "opc.tcp://0.0.0.0:4898", "--cert", str(cert), "--key", str(key))
    _, out, err = proc.wait(timeout=60)
    lines = err.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "users file" in lines[0] and "anonymous" in lines[0], err


def test_users_entry_helper(monkeypatch, capsys):
    from station.opcua import users

    answers = iter(["line-pass-77", "line-pass-77"])
    monkeypatch.setattr("getpass.getpass", lambda prompt="": next(answers))
    assert users.main(["mes", "operate"]) == 0
    entry = capsys.readouterr().out
    stored = entry.split("password: ")[1].split()[0]
    assert "line-pass-77" not in entry and "rights: [read, operate]" in entry
    assert users.verify_password("line-pass-77", stored) and not users.verify_password("line-pass-78", stored)
