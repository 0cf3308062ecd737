"""Who may do what over OPC UA (docs/opcua.md, "Users and rights"): the users file, password hashes, and the
asyncua user manager and permission rules built from it.

Users file (YAML, ``--users FILE``)::

    format: station-opcua-users/1
    users:
      - name: mes
        password: scrypt$16384$8$1$<salt>$<hash>     # python -m station.opcua.users mes
        rights: [read, operate]
      - name: scada
        password: scrypt$...
        rights: [read]

Rights: ``read`` (browse, read, subscribe) and ``operate`` (also call ``Start`` and ``Abort``). Nobody may
write a variable or change the address space. Without a users file (loopback only) clients are anonymous with
both rights, as on the station PC's own page. With one, anonymous sessions are refused; five wrong passwords for
a name within a minute lock that name for a minute."""

from __future__ import annotations

import base64
import contextvars
import hashlib
import hmac
import secrets
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from asyncua.crypto.permission_rules import User, UserRole

from station.robot.errors import ConfigError

FORMAT = "station-opcua-users/1"
RIGHTS = ("read", "operate")
SCRYPT = (2**14, 8, 1)  # N, r, p: ~50 ms and 16 MiB per check on the station PC
LOCK_AFTER, LOCK_S = 5, 60.0

# the user of the request being processed (set by the permission check, read by the method handlers: both run
# in the task that processes the request)
current_user: contextvars.ContextVar = contextvars.ContextVar("station_opcua_user", default=None)


class UsersFileError(ConfigError):
    """A users file the station refuses; the message names file, line and field."""


@dataclass(frozen=True)
class Account:
    name: str
    password: str  # scrypt$N$r$p$salt$hash (base64)
    rights: frozenset[str]


def hash_password(password: str, *, salt: bytes | None = None, params: tuple[int, int, int] = SCRYPT) -> str:
    n, r, p = params
    salt = salt or secrets.token_bytes(16)
    key = hashlib.scrypt(password.encode(), salt=salt, n=n, r=r, p=p, dklen=32)
    b64 = lambda b: base64.b64encode(b).decode()  # noqa: E731
    return f"scrypt${n}${r}${p}${b64(salt)}${b64(key)}"


def _parse_hash(stored: str) -> tuple[int, int, int, bytes, bytes] | None:
    parts = stored.split("$")
    if len(parts) != 6 or parts[0] != "scrypt":
        return None
    try:
        n, r, p = (int(x) for x in parts[1:4])
        salt, key = base64.b64decode(parts[4], validate=True), base64.b64decode(parts[5], validate=True)
    except ValueError:
        return None
    # within what hashlib.scrypt accepts and the station PC can afford (memory 128 * r * N bytes <= 64 MiB)
    if not (2 <= n <= 2**20 and n & (n - 1) == 0 and 1 <= r <= 32 and 1 <= p <= 16 and 128 * r * n <= 2**26
            and len(salt) >= 8 and len(key) >= 16):
        return None
    return n, r, p, salt, key


def verify_password(password: str, stored: str) -> bool:
    parsed = _parse_hash(stored)
    if parsed is None:
        return False
    n, r, p, salt, key = parsed
    got = hashlib.scrypt(password.encode(), salt=salt, n=n, r=r, p=p, maxmem=2**27, dklen=len(key))
    return hmac.compare_digest(got, key)


def load_users(path: str | Path) -> dict[str, Account]:
    """The accounts of a users file; :class:`UsersFileError` (``FILE:LINE: FIELD: ...``) for anything else."""
    from station.yamlfile import load_yaml_doc

    doc = load_yaml_doc(path, UsersFileError, "users file")
    data = doc.data
    if not isinstance(data, dict):
        raise UsersFileError(f"{doc.where()}: expected a mapping with format and users")
    unknown = [k for k in data if k not in ("format", "users")]
    if unknown:
        raise UsersFileError(f"{doc.where((unknown[0],))}: unknown key {unknown[0]!r}")
    if data.get("format") != FORMAT:
        raise UsersFileError(f"{doc.where(('format',))}: format must be {FORMAT}, got {data.get('format')!r}")
    users = data.get("users")
    if not isinstance(users, list) or not users:
        raise UsersFileError(f"{doc.where(('users',))}: expected a list of users (name, password, rights)")
    out: dict[str, Account] = {}
    for i, u in enumerate(users):
        at = ("users", i)
        if not isinstance(u, dict):
            raise UsersFileError(f"{doc.where(at)}: expected name, password and rights")
        extra = [k for k in u if k not in ("name", "password", "rights")]
        if extra:
            raise UsersFileError(f"{doc.where((*at, extra[0]))}: unknown key {extra[0]!r}")
        name, pw, rights = u.get("name"), u.get("password"), u.get("rights")
        if not isinstance(name, str) or not name.strip() or len(name) > 64 or any(c.isspace() for c in name):
            raise UsersFileError(f"{doc.where((*at, 'name'))}: expected a user name (no spaces, at most 64 "
                                 f"characters), got {name!r}")
        if name in out:
            raise UsersFileError(f"{doc.where((*at, 'name'))}: user {name!r} appears twice")
        if not isinstance(pw, str) or _parse_hash(pw) is None:
            raise UsersFileError(f"{doc.where((*at, 'password'))}: expected a scrypt hash (python -m "
                                 "station.opcua.users NAME writes one), never a plain password")
        if not isinstance(rights, list) or not rights or any(r not in RIGHTS for r in rights):
            raise UsersFileError(f"{doc.where((*at, 'rights'))}: expected a list of {' and '.join(RIGHTS)}, got "
                                 f"{rights!r}")
        granted = set(rights) | ({"read"} if "operate" in rights else set())
        out[name] = Account(name, pw, frozenset(granted))
    return out


@dataclass
class StationUser(User):
    """An asyncua session's user with the station's rights."""

    rights: frozenset = frozenset()


def _asyncua_user(name: str, rights: frozenset[str]) -> StationUser:
    return StationUser(role=UserRole.User, name=name, rights=rights)


class UserManager:
    """asyncua's ``get_user``: anonymous (loopback without a users file) or a name and password of the file."""

    def __init__(self, accounts: dict[str, Account] | None) -> None:
        self.accounts = accounts
        self._failures: dict[str, list[float]] = {}
        self._lock = threading.Lock()
        self._dummy = hash_password(secrets.token_hex(8))  # unknown names cost the same time as known ones

    def get_user(self, iserver, username: str | None = None, password: str | None = None, certificate=None):
        if self.accounts is None:  # loopback without a users file: anonymous tokens only (the server's policy)
            return _asyncua_user("anonymous", frozenset(RIGHTS)) if username is None else None
        if username is None or password is None:
            return None
        now = time.monotonic()
        with self._lock:
            recent = [t for t in self._failures.get(username, []) if now - t < LOCK_S]
            self._failures[username] = recent
            locked = len(recent) >= LOCK_AFTER
        account = self.accounts.get(username)
        ok = verify_password(password, account.password if account else self._dummy) and account is not None
        if locked or not ok:
            if not ok:
                with self._lock:
                    self._failures.setdefault(username, []).append(now)
            return None
        return _asyncua_user(account.name, account.rights)


def _request_ids() -> tuple[set, set]:
    from asyncua import ua

    o = ua.ObjectIds
    read = {o.ReadRequest_Encoding_DefaultBinary, o.BrowseRequest_Encoding_DefaultBinary,
            o.BrowseNextRequest_Encoding_DefaultBinary, o.TranslateBrowsePathsToNodeIdsRequest_Encoding_DefaultBinary,
            o.RegisterNodesRequest_Encoding_DefaultBinary, o.UnregisterNodesRequest_Encoding_DefaultBinary,
            o.CreateSubscriptionRequest_Encoding_DefaultBinary, o.ModifySubscriptionRequest_Encoding_DefaultBinary,
            o.DeleteSubscriptionsRequest_Encoding_DefaultBinary, o.TransferSubscriptionsRequest_Encoding_DefaultBinary,
            o.CreateMonitoredItemsRequest_Encoding_DefaultBinary, o.ModifyMonitoredItemsRequest_Encoding_DefaultBinary,
            o.DeleteMonitoredItemsRequest_Encoding_DefaultBinary, o.SetMonitoringModeRequest_Encoding_DefaultBinary,
            o.SetPublishingModeRequest_Encoding_DefaultBinary, o.PublishRequest_Encoding_DefaultBinary,
            o.RepublishRequest_Encoding_DefaultBinary, o.HistoryReadRequest_Encoding_DefaultBinary}
    session = {o.CreateSessionRequest_Encoding_DefaultBinary, o.ActivateSessionRequest_Encoding_DefaultBinary,
               o.CloseSessionRequest_Encoding_DefaultBinary, o.CloseSecureChannelRequest_Encoding_DefaultBinary,
               o.GetEndpointsRequest_Encoding_DefaultBinary, o.FindServersRequest_Encoding_DefaultBinary}
    return {ua.NodeId(i) for i in session | read}, {ua.NodeId(o.CallRequest_Encoding_DefaultBinary)}


class Rights:
    """asyncua permission rules: ``read`` for reading services, ``operate`` for method calls (Start, Abort);
    writes and address-space changes for nobody."""

    def __init__(self) -> None:
        self.read, self.operate = _request_ids()

    def check_validity(self, user, action_type_id, body) -> bool:
        current_user.set(user)
        rights = getattr(user, "rights", frozenset())
        if action_type_id in self.read:
            return "read" in rights
        if action_type_id in self.operate:
            return "operate" in rights
        return False


def main(argv: list[str] | None = None) -> int:
    """``python -m station.opcua.users NAME [read|operate]``: asks for the password twice and prints the entry
    for the users file (the password itself is never written anywhere)."""
    import getpass
    import sys

    args = sys.argv[1:] if argv is None else argv
    if not args or len(args) > 2 or (len(args) == 2 and args[1] not in RIGHTS):
        print("usage: python -m station.opcua.users NAME [read|operate]", file=sys.stderr)
        return 2
    name, right = args[0], (args[1] if len(args) == 2 else "read")
    pw = getpass.getpass(f"password for {name}: ")
    if len(pw) < 8 or pw != getpass.getpass("again: "):
        print("station: error: the passwords differ or are shorter than 8 characters", file=sys.stderr)
        return 2
    rights = "[read, operate]" if right == "operate" else "[read]"
    print(f"  - name: {name}\n    password: {hash_password(pw)}\n    rights: {rights}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
