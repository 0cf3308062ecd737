"""``station opcua`` with a real asyncua client on loopback: browse urn:station/Station, subscribe to Verdict,
call Start(serial, procedure) on an emulated Dynamixel arm with hidden offsets, read LastResult once the verdict
arrives and check it against the records database and the hidden truth; Abort; refusal off loopback."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
from station.mocks.world import World
from test_panel_browser import _files, _url

from station.records import open_records


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _server(tmp_path, url, cell, db, endpoint, *extra):
    env = {**os.environ, "STATION_HOME": str(tmp_path / "home")}
    return subprocess.Popen([sys.executable, "-m", "station.cli", "opcua", "--robot", url, "--cell", str(cell),
                             "--db", db, "--endpoint", endpoint, "--reference", "cell", "--cone", "70",
                             "--poses", "12", "--holdout", "2", *extra], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _unit_server(tmp_path, emulators, seed: int, serial: str, **files):
    """An emulated Dynamixel arm (its own process) with hidden offsets and ``station opcua`` for it:
    ``(world_path, db, endpoint, proc)``."""
    world_path, cell_path = _files(tmp_path, seed=seed, **files)
    db = f"sqlite:///{tmp_path / 'r.db'}"
    endpoint = f"opc.tcp://127.0.0.1:{_free_port()}"
    emu = emulators("dynamixel", world_path, serial=serial, process=True)
    return world_path, db, endpoint, _server(tmp_path, _url(emu), cell_path, db, endpoint)


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
            if proc.poll() is not None or time.monotonic() > end:
                raise AssertionError(proc.communicate()) from None
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
    world_path, db, endpoint, proc = _unit_server(tmp_path, emulators, 51, serial)

    async def scenario():
        from asyncua import ua

        client = await _connect(endpoint, proc)
        try:
            idx, station, n = await _station_nodes(client)
            assert await n["State"].read_value() == "idle" and await n["Verdict"].read_value() == ""
            handler = _Verdicts()
            sub = await client.create_subscription(50, handler)
            await sub.subscribe_data_change(n["Verdict"])
            with pytest.raises(ua.UaStatusCodeError):  # a serial with a space is refused, nothing starts
                await station.call_method(n["Start"], ua.Variant("BAD SERIAL", ua.VariantType.String),
                                          ua.Variant("", ua.VariantType.String))
            session = await station.call_method(n["Start"], ua.Variant(serial, ua.VariantType.String),
                                                ua.Variant("zero_offsets", ua.VariantType.String))
            assert session.startswith(f"zero_offsets-{serial}-")
            assert await n["Serial"].read_value() == serial
            await _wait(lambda: any(v for v in handler.values), 180)
            verdict = next(v for v in handler.values if v)
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
        out, err = proc.communicate(timeout=30)
    assert verdict == "PASS" and state == "done" and progress == 1.0
    assert result["session"] == session and result["verdict"] == "PASS" and result["stored"] is True
    with open_records(db) as rec:  # PASS on the line means the record is in the database
        stored = rec.session(session)
    assert stored["verdict"]["passed"] is True and stored["operator"] == "line"
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
        proc.communicate(timeout=30)
    assert verdict == "ABORTED" and result["session"] == session
    journal = tmp_path / "home" / "sessions" / session / "journal.jsonl"
    last = json.loads(journal.read_text().strip().splitlines()[-1])
    assert last["type"] == "end" and last["status"] == "interrupted"  # teardown ran; `station resume` continues


@pytest.mark.parametrize("endpoint", ["opc.tcp://0.0.0.0:4841", "opc.tcp://192.0.2.7:4841"])
def test_off_loopback_without_certificates_is_refused(tmp_path, endpoint):
    world_path, cell_path = _files(tmp_path, seed=53)
    proc = _server(tmp_path, "dynamixel:///dev/null?model=omx", cell_path, "sqlite:///x.db", endpoint)
    out, err = proc.communicate(timeout=60)
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
                   endpoint, "--cert", str(cert), "--key", str(key))

    async def scenario():
        end = time.monotonic() + 60
        while True:  # wait until it listens
            try:
                with socket.create_connection(("127.0.0.1", int(endpoint.rsplit(":", 1)[1])), timeout=1):
                    break
            except OSError:
                if proc.poll() is not None or time.monotonic() > end:
                    raise AssertionError(proc.communicate()) from None
                await asyncio.sleep(0.3)
        plain = Client(endpoint, timeout=10)
        with pytest.raises(Exception):  # noqa: B017 - asyncua raises BadSecurityPolicyRejected or similar
            await plain.connect()
            await _station_nodes(plain)
        secure = Client(endpoint, timeout=30)  # RSA handshakes on a loaded 2-core host
        secure.application_uri = "urn:client"
        await secure.set_security_string(f"Basic256Sha256,SignAndEncrypt,{ccert},{ckey}")
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
        proc.communicate(timeout=30)
