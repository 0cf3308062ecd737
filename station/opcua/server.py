"""The ``Station`` object over asyncua, fed from the panel's controller (one state for page and line).

Variables (read-only for clients): ``State`` (idle|running|prompt|done), ``Serial``, ``Procedure``, ``Step``,
``Progress`` (0-1, Double), ``Verdict`` ("" until a unit ends, then PASS|FAIL|NOT STORED|ABORTED|ERROR),
``LastResult`` (JSON of the finished unit: session, verdict, stored, failing limits in words, measurements,
parameters in SI). Methods: ``Start(serial: String, procedure: String) -> session: String`` and ``Abort()``.

Security: an endpoint on loopback may be anonymous without encryption; any other address is served only with
``Basic256Sha256`` (sign & encrypt), the server's certificate and key, and a users file (``station.opcua.users``:
user names and passwords, rights ``read`` and ``operate``), and with a folder of trusted client certificates
when given. An anonymous or unencrypted endpoint off loopback is refused. Nobody writes variables or changes the
address space; ``Start``/``Abort`` need ``operate``."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import threading
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

from station.panel.controller import BadProcedure, Controller, PanelError, WrongState
from station.panel.serve import is_loopback
from station.robot.errors import ConfigError

NAMESPACE = "urn:station"
START_WAIT_S = 30.0  # Start answers once the robot confirmed the serial and the journal exists, at most this long
# Start refused once the robot was reached, by the reason's kind (station.panel.reasons); the codes of
# docs/opcua.md, OPC 10000-4 7.39 / asyncua.ua.StatusCodes names
REFUSED = {"serial": 0x80AB0000,  # BadInvalidArgument: not this robot's serial
           "setup": 0x80890000,  # BadConfigurationError: the station's setup (wrong robot type, files, database)
           "robot": 0x808B0000,  # BadDeviceFailure: the robot or its bus (unreachable, fault, safety stop)
           "station": 0x80020000}  # BadInternalError
VARIABLES = ("State", "Serial", "Procedure", "Step", "Progress", "Verdict", "LastResult")


@dataclass
class OpcuaOptions:
    endpoint: str = "opc.tcp://127.0.0.1:4840"
    cert: Path | None = None
    key: Path | None = None
    trust: Path | None = None  # folder of trusted client certificates (DER/PEM)
    operator: str = "line"  # who started a unit through OPC UA without a users file (the record's operator)
    users: Path | None = None  # users file: names, password hashes, rights (required off loopback)


def _host(endpoint: str) -> str:
    try:
        u = urlsplit(endpoint)
    except ValueError:
        u = None
    if u is None or u.scheme != "opc.tcp" or not u.hostname:
        raise ConfigError(f"OPC UA endpoint {endpoint!r} must look like opc.tcp://HOST:PORT")
    return u.hostname


def check_security(opts: OpcuaOptions) -> bool:
    """True when the endpoint must be secured (off loopback); refuses an off-loopback endpoint without a
    certificate and key, or without a users file, and a users file the station cannot read."""
    if opts.users is not None:
        from station.opcua.users import load_users

        load_users(opts.users)  # one line naming file, line and field
    if is_loopback(_host(opts.endpoint)):
        return bool(opts.cert and opts.key)
    if not (opts.cert and opts.key):
        raise ConfigError(f"OPC UA endpoint {opts.endpoint} is not loopback: it is served only with Basic256Sha256 "
                          "(--opcua-cert and --opcua-key; see docs/opcua.md), never anonymously")
    for p in (opts.cert, opts.key):
        if not Path(p).is_file():
            raise ConfigError(f"{p}: no such certificate/key file")
    if opts.users is None:
        raise ConfigError(f"OPC UA endpoint {opts.endpoint} is not loopback: clients must sign in; give a users "
                          "file (--opcua-users / --users; see docs/opcua.md), never anonymous")
    return True


def _result(code: int, *outputs: str, argument: int | None = None, n_inputs: int = 2):
    """A method's answer: its status code, the status of each input argument (the bad one named), outputs."""
    from asyncua import ua

    res = ua.CallMethodResult()
    res.StatusCode = ua.StatusCode(code)
    res.InputArgumentResults = [ua.StatusCode(code if i == argument else ua.StatusCodes.Good)
                                for i in range(n_inputs)]
    res.OutputArguments = [ua.Variant(o, ua.VariantType.String) for o in outputs]
    return res


def _snapshot_values(ctl: Controller) -> dict:
    s = ctl.snapshot()
    # written in this order: a client that sees Verdict (or State "done") change reads the new LastResult
    return {"LastResult": json.dumps(ctl.last_result(), default=str), "Serial": s["serial"] or "",
            "Procedure": s["procedure"] or "", "Step": s["step"] or "", "Progress": float(s["progress"]),
            "Verdict": s["verdict"] or "", "State": s["state"]}


class StationServer:
    def __init__(self, ctl: Controller, opts: OpcuaOptions) -> None:
        self.ctl, self.opts = ctl, opts
        self.secure = check_security(opts)
        self.server = None
        self.nodes: dict = {}
        self._stop = asyncio.Event()

    async def start(self) -> None:
        from asyncua import Server, ua

        from station.opcua.users import Rights, UserManager, load_users

        logging.getLogger("asyncua").setLevel(logging.CRITICAL)  # refused logins are answered, not narrated
        accounts = load_users(self.opts.users) if self.opts.users is not None else None
        server = Server(user_manager=UserManager(accounts))
        await server.init()
        server.set_endpoint(self.opts.endpoint)
        server.set_server_name("station")
        server.allow_remote_admin(False)  # asyncua's built-in "admin" user: never from the network
        server.set_identity_tokens([ua.UserNameIdentityToken] if accounts is not None else
                                   [ua.AnonymousIdentityToken])
        rules = Rights()  # read: browse/read/subscribe; operate: Start/Abort; nobody writes or edits nodes
        if self.secure:
            server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt], permission_ruleset=rules)
            await server.load_certificate(str(self.opts.cert))
            await server.load_private_key(str(self.opts.key))
            if self.opts.trust:
                from asyncua.crypto.truststore import TrustStore
                from asyncua.crypto.validator import CertificateValidator

                store = TrustStore([Path(self.opts.trust)], [])
                await store.load()
                server.set_certificate_validator(CertificateValidator(trust_store=store))
        else:
            server.set_security_policy([ua.SecurityPolicyType.NoSecurity], permission_ruleset=rules)
        idx = await server.register_namespace(NAMESPACE)
        obj = await server.nodes.objects.add_object(idx, "Station")
        for name, value in _snapshot_values(self.ctl).items():
            vt = ua.VariantType.Double if name == "Progress" else ua.VariantType.String
            self.nodes[name] = await obj.add_variable(idx, name, ua.Variant(value, vt))
        await obj.add_method(idx, "Start", self._start, [ua.VariantType.String, ua.VariantType.String],
                             [ua.VariantType.String])
        await obj.add_method(idx, "Abort", self._abort, [], [])
        self.server = server
        await server.start()

    async def _start(self, parent, serial, procedure):
        from asyncua import ua

        from station.opcua.users import current_user

        s, p = (v.Value if isinstance(v, ua.Variant) else v for v in (serial, procedure))
        s, p = str(s or ""), str(p or "")
        user = current_user.get()
        # the record names who started the unit: the signed-in user, else the line (anonymous on loopback)
        operator = user.name if self.opts.users is not None and user is not None and user.name else self.opts.operator
        # Results are returned, not raised: asyncua answers any exception of a method with BadUnexpectedError.
        # A refusal says which argument was wrong (InputArgumentResults, OPC 10000-4 5.11.2) and, but for a unit
        # running, publishes Verdict ERROR with the reason in LastResult.
        try:
            sid = await asyncio.to_thread(self.ctl.start, s, operator, p or None, confirm=False,
                                          wait_session=START_WAIT_S)
        except WrongState:
            return _result(ua.StatusCodes.BadInvalidState)
        except PanelError as e:
            bad_procedure = isinstance(e, BadProcedure)
            self.ctl.refuse(s, operator, str(e), procedure=None if bad_procedure else p or None,
                            bad_procedure=bad_procedure)
            await self.publish()
            return _result(ua.StatusCodes.BadInvalidArgument, argument=1 if bad_procedure else 0)
        snap = self.ctl.snapshot()
        if not sid and snap["state"] == "done":  # ended before its journal existed: refused by the robot
            await self.publish()
            kind = snap.get("cause")
            return _result(REFUSED.get(kind, ua.StatusCodes.BadInternalError), argument=0 if kind == "serial"
                           else None)
        await self.publish()
        # still connecting after START_WAIT_S: running, the session id follows in LastResult
        return _result(ua.StatusCodes.Good if sid else ua.StatusCodes.GoodCompletesAsynchronously, sid or "")

    async def _abort(self, parent):
        from asyncua import ua

        try:
            self.ctl.abort()
        except PanelError:
            return _result(ua.StatusCodes.BadInvalidState, n_inputs=0)
        await self.publish()
        return []

    async def publish(self) -> None:
        from asyncua import ua

        for name, value in _snapshot_values(self.ctl).items():
            vt = ua.VariantType.Double if name == "Progress" else ua.VariantType.String
            node = self.nodes[name]
            if await node.read_value() != value:
                await node.write_value(ua.Variant(value, vt))

    async def run(self) -> None:
        """Mirror the controller's state into the variables until :meth:`request_stop`."""
        version = -1
        try:
            while not self._stop.is_set():
                if self.ctl.version != version:
                    version = self.ctl.version
                    await self.publish()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._stop.wait(), 0.1)
        finally:
            if self.server is not None:
                await self.server.stop()

    def request_stop(self) -> None:
        self._stop.set()


class ServerThread:
    """The OPC UA server on its own event loop in a daemon thread (next to the panel's web server)."""

    def __init__(self, ctl: Controller, opts: OpcuaOptions) -> None:
        self.station = StationServer(ctl, opts)  # security checks happen here, in the caller's thread
        self.loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self.thread = threading.Thread(target=self._main, name="opcua", daemon=True)

    def _main(self) -> None:
        asyncio.set_event_loop(self.loop)

        async def go():
            try:
                await self.station.start()
            except BaseException as e:
                self._error = e
                self._ready.set()
                return
            self._ready.set()
            await self.station.run()

        self.loop.run_until_complete(go())

    def start(self) -> ServerThread:
        self.thread.start()
        self._ready.wait(30)
        if self._error is not None:
            raise ConfigError(f"OPC UA server at {self.station.opts.endpoint}: {self._error}")
        return self

    def stop(self) -> None:
        if self.thread.is_alive():
            self.loop.call_soon_threadsafe(self.station.request_stop)
            self.thread.join(10)


def start_in_thread(ctl: Controller, opts: OpcuaOptions) -> ServerThread:
    return ServerThread(ctl, opts).start()


async def serve_forever(ctl: Controller, opts: OpcuaOptions) -> None:
    s = StationServer(ctl, opts)
    await s.start()
    await s.run()
