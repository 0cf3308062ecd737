"""What the line's PLC/MES learns over OPC UA (docs/opcua.md), with a real asyncua client: every status code a
method answers, which argument it blames (``InputArgumentResults``), and ``LastResult`` always a JSON document
with the verdict and the reason in words, also for a start the robot refused (a wrong serial) and before the
first unit.

The robot is an emulated Dynamixel arm on a pty (real dynamixel_sdk) whose URL carries the unit's serial, as
``station mock dynamixel`` prints it; a robot that cannot be opened and a records database that cannot be
written are real too (a path that is no serial port, a folder where the database file should be)."""

from __future__ import annotations

import asyncio
import json
import signal
import time

import pytest

from station.engine import read_journal
from tests.opcua.test_opcua_server import _free_port, _station_nodes, _unit_server, _wait
from tests.panel.test_panel_browser import _files


async def _client(endpoint: str, proc=None):
    from asyncua import Client

    end = time.monotonic() + 60
    while True:
        client = Client(endpoint, timeout=10, watchdog_intervall=10.0)  # a loaded 2-core host: see test_opcua_server
        try:
            await client.connect()
            return client
        except (OSError, TimeoutError):
            if (proc is not None and not proc.running()) or time.monotonic() > end:
                raise AssertionError(proc.wait() if proc is not None else "no server") from None
            await asyncio.sleep(0.3)


async def _call(client, station, method, *args: str):
    """One Call request as a PLC sends it: ``(status name, [status name per input argument], outputs)``."""
    from asyncua import ua

    req = ua.CallMethodRequest()
    req.ObjectId = station.nodeid
    req.MethodId = method.nodeid
    req.InputArguments = [ua.Variant(a, ua.VariantType.String) for a in args]
    (res,) = await client.uaclient.call([req])
    return res.StatusCode.name, [c.name for c in res.InputArgumentResults], \
        [v.Value for v in res.OutputArguments or []]


async def _last(n) -> dict:
    return json.loads(await n["LastResult"].read_value())


@pytest.mark.slow
def test_start_refusals_abort_and_last_result_over_the_wire(tmp_path, emulators):
    serial = "DXL-OPC-91"
    _, db, endpoint, proc = _unit_server(tmp_path, emulators, 91, serial, time_mode="realtime", time_scale=2.0)

    async def scenario():
        client = await _client(endpoint, proc)
        try:
            _, station, n = await _station_nodes(client)
            # before the first unit: JSON already, no verdict yet, a reason in words
            boot = await _last(n)
            assert boot["verdict"] == "" and boot["reason"] and boot["session"] is None
            assert await _call(client, station, n["Abort"]) == ("BadInvalidState", [], [])  # nothing running

            # a serial the robot in the cell does not carry: refused at Start, the reason in LastResult
            code, args, _ = await _call(client, station, n["Start"], "WRONG-SN", "")
            assert (code, args) == ("BadInvalidArgument", ["BadInvalidArgument", "Good"])
            wrong = await _last(n)
            assert await n["Verdict"].read_value() == "ERROR" and await n["State"].read_value() == "done"
            assert wrong["verdict"] == "ERROR" and wrong["serial"] == "WRONG-SN" and wrong["session"] is None
            assert "WRONG-SN" in wrong["reason"] and serial in wrong["reason"] and wrong["cause"] == "serial"
            assert wrong["resumable"] is False and "Scan the label" in wrong["action"]
            # ABORT on an ERROR gives the unit up: Good, ABORTED with the reason
            assert await _call(client, station, n["Abort"]) == ("Good", [], [])
            gave_up = await _last(n)
            assert gave_up["verdict"] == "ABORTED" and "WRONG-SN" in gave_up["reason"]
            assert await n["Verdict"].read_value() == "ABORTED"
            assert await _call(client, station, n["Abort"]) == ("BadInvalidState", [], [])  # twice: nothing left

            # malformed serial, unknown procedure: the argument named, the reason published
            code, args, _ = await _call(client, station, n["Start"], "BAD SERIAL", "")
            assert (code, args) == ("BadInvalidArgument", ["BadInvalidArgument", "Good"])
            assert "not a serial number" in (await _last(n))["reason"]
            code, args, _ = await _call(client, station, n["Start"], serial, "no_such_procedure")
            assert (code, args) == ("BadInvalidArgument", ["Good", "BadInvalidArgument"])
            unknown = await _last(n)
            assert "no_such_procedure" in unknown["reason"] and unknown["cause"] == "setup"

            # the right unit starts (Good, the session id); a second Start while it runs: BadInvalidState, and
            # neither the running unit's state nor LastResult changes
            code, args, (session,) = await _call(client, station, n["Start"], serial, "zero_offsets")
            assert code == "Good" and session.startswith(f"zero_offsets-{serial}-")
            before = await n["LastResult"].read_value()
            assert (await _call(client, station, n["Start"], "OTHER-1", ""))[0] == "BadInvalidState"
            assert (await _call(client, station, n["Start"], "BAD SERIAL", ""))[0] == "BadInvalidArgument"
            assert await n["Serial"].read_value() == serial and await n["LastResult"].read_value() == before
            assert await n["State"].read_value() in ("running", "prompt")
            end = time.monotonic() + 90
            while await n["Progress"].read_value() <= 0 and time.monotonic() < end:
                await asyncio.sleep(0.1)
            assert await _call(client, station, n["Abort"]) == ("Good", [], [])
            while await n["Verdict"].read_value() != "ABORTED" and time.monotonic() < end:
                await asyncio.sleep(0.1)
            aborted = await _last(n)
            return session, aborted
        finally:
            await client.disconnect()

    try:
        session, aborted = asyncio.run(scenario())
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
    assert aborted["verdict"] == "ABORTED" and aborted["session"] == session and aborted["resumable"] is True
    assert aborted["reason"].startswith("Aborted by the operator") and "RESUME" in aborted["action"]
    _, events = read_journal(tmp_path / "home" / "sessions" / session / "journal.jsonl")
    assert events[-1]["type"] == "end" and events[-1]["status"] == "interrupted"
    # the refused starts left no session behind
    assert [p.name for p in (tmp_path / "home" / "sessions").iterdir()] == [session]


def test_robot_and_setup_refusals_and_a_slow_start(tmp_path, monkeypatch):
    """In this process (the server's thread next to the test): a robot that cannot be opened is
    ``BadDeviceFailure``, a records database that cannot be written ``BadConfigurationError``, each with its
    reason in LastResult; a start still connecting when the wait ends answers ``GoodCompletesAsynchronously``."""
    from station.opcua import server as opcua_server
    from station.panel.controller import Controller, PanelConfig

    _, cell = _files(tmp_path, seed=92)
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    ctl = Controller(PanelConfig(robot=f"dynamixel://{tmp_path / 'no-such-port'}?model=omx", cell=str(cell),
                                 db=f"sqlite:///{tmp_path / 'r.db'}", confirm=False))
    endpoint = f"opc.tcp://127.0.0.1:{_free_port()}"
    srv = opcua_server.start_in_thread(ctl, opcua_server.OpcuaOptions(endpoint=endpoint))

    async def scenario():
        client = await _client(endpoint)
        try:
            _, station, n = await _station_nodes(client)
            out = {}
            out["device"] = await _call(client, station, n["Start"], "SN-92", ""), await _last(n)
            (tmp_path / "records-is-a-folder").mkdir()  # SQLite cannot open a folder as its database
            ctl.config.db = f"sqlite:///{tmp_path / 'records-is-a-folder'}"
            out["setup"] = await _call(client, station, n["Start"], "SN-92", ""), await _last(n)
            ctl.config.db = f"sqlite:///{tmp_path / 'r.db'}"
            monkeypatch.setattr(opcua_server, "START_WAIT_S", 0.0)
            out["async"] = await _call(client, station, n["Start"], "SN-92", "")
            await _wait(lambda: ctl.snapshot()["state"] == "done", 60)
            await asyncio.sleep(0.3)  # the next publish
            out["async-end"] = await _last(n)
            return out
        finally:
            await client.disconnect()

    try:
        out = asyncio.run(scenario())
    finally:
        srv.stop()
    (code, args, _), last = out["device"]
    assert (code, args) == ("BadDeviceFailure", ["Good", "Good"])
    assert last["verdict"] == "ERROR" and last["cause"] == "robot" and last["reason"] and "no-such-port" in \
        last["detail"]
    (code, args, _), last = out["setup"]
    assert (code, args) == ("BadConfigurationError", ["Good", "Good"])
    assert last["verdict"] == "ERROR" and last["cause"] == "setup" and "records-is-a-folder" in last["detail"]
    assert out["async"] == ("GoodCompletesAsynchronously", ["Good", "Good"], [""])
    assert out["async-end"]["verdict"] == "ERROR" and out["async-end"]["cause"] == "robot"
    assert not (tmp_path / "home" / "sessions").exists() or not list((tmp_path / "home" / "sessions").iterdir())
