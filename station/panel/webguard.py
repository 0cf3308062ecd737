"""What every request to the panel passes before any handler sees it (docs/panel.md, "Listening and access").

- **Host** (every request): the name the client used must be one of the panel's own: the address it listens
  on, the machine's names, loopback names on loopback, and the names given with ``--allow-host``; with the
  port it listens on. A page of another site whose name was re-pointed at this machine (DNS rebinding) sends
  its own name and is refused: it can neither read the state nor fetch a CSRF token.
- **Token** (with ``--token``): ``Authorization: Bearer TOKEN`` or the ``station_token`` cookie, else 401;
  ``GET /?token=TOKEN`` (the right one) passes to the page, which sets the cookie.
- **State changes** (every method but GET/HEAD): ``Origin`` (else ``Referer``) must be the panel itself (a
  request without either comes from no browser); the body is ``application/json`` (a browser sends a cross-site
  form or ``text/plain`` request without asking first; JSON needs a CORS preflight this server never grants);
  and ``X-CSRF-Token`` holds a token the panel gave a page it served (``GET /`` embeds one; a script asks
  ``GET /api/csrf``).

Refusals are ``403`` (``415`` for a body that is not JSON) with ``{"error": one line}``; nothing is started."""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import json
import secrets
import socket
from urllib.parse import urlsplit

CSRF_HEADER = "x-csrf-token"
SAFE_METHODS = frozenset({"GET", "HEAD"})
# every response: no framing (a page of another site cannot overlay the panel and borrow an operator's click),
# no content sniffing, the panel's address stays out of other sites' logs
SECURITY_HEADERS = [(b"x-frame-options", b"DENY"), (b"x-content-type-options", b"nosniff"),
                    (b"referrer-policy", b"same-origin"), (b"cross-origin-resource-policy", b"same-origin")]


def _norm_host(host: str) -> str:
    """A host name or address as compared: lower case, IPv6 in brackets, no trailing dot."""
    h = host.strip().lower().rstrip(".")
    if h.startswith("[") and h.endswith("]"):
        return h
    try:
        if ipaddress.ip_address(h).version == 6:
            return f"[{h}]"
    except ValueError:
        pass
    return h


def split_host(value: str) -> tuple[str, int | None] | None:
    """``(host, port)`` of a Host header value (port None when absent); None when it is not one."""
    value = value.strip()
    if not value or any(c.isspace() or c in "/\\@?#" for c in value):
        return None
    try:
        u = urlsplit("//" + value)
        port = u.port
        host = u.hostname
    except ValueError:
        return None
    if not host:
        return None
    return _norm_host(host if ":" not in host else f"[{host}]"), port


def own_names(bind: str, *, loopback: bool) -> set[str]:
    """The names a client of this machine may use for a panel listening on ``bind``."""
    names = {_norm_host(bind)}
    if loopback:
        names |= {"localhost", "127.0.0.1", "[::1]"}
    wildcard = bind in ("0.0.0.0", "::", "")
    if not loopback:
        for n in {socket.gethostname(), socket.getfqdn()}:
            if n:
                names.add(_norm_host(n))
        if wildcard:  # every address this machine resolves its own name to (the interfaces it is known by)
            try:
                for info in socket.getaddrinfo(socket.gethostname(), None):
                    names.add(_norm_host(str(info[4][0])))
            except OSError:
                pass
            names |= {"localhost", "127.0.0.1", "[::1]"}
    names.discard(_norm_host("0.0.0.0"))
    names.discard("[::]")
    return names


class Guard:
    """The Host, Origin/Referer, content type and CSRF rules of one panel (an ASGI middleware around its app)."""

    def __init__(self, app, *, bind: str, port: int, loopback: bool, tls: bool = False,
                 allow_hosts: list[str] | tuple[str, ...] = (), token: str | None = None,
                 cookie: str = "station_token") -> None:
        self.app = app
        self.token, self.cookie = token, cookie
        self.port = port
        self.scheme = "https" if tls else "http"
        self.names = own_names(bind, loopback=loopback)
        self.extra: set[tuple[str, int | None]] = set()  # --allow-host NAME[:PORT]: e.g. a TLS reverse proxy
        for h in allow_hosts:
            parsed = split_host(h)
            if parsed is None:
                from station.robot.errors import ConfigError

                raise ConfigError(f"--allow-host {h!r}: expected a host name or address, optionally with :PORT")
            self.extra.add(parsed)
        self._secret = secrets.token_bytes(32)  # a new panel process: pages it did not serve are refused

    # ---- Host ------------------------------------------------------------------------------------------
    def host_ok(self, value: str | None) -> bool:
        parsed = split_host(value or "")
        if parsed is None:
            return False
        host, port = parsed
        if any(h == host and (p is None or p == port) for h, p in self.extra):  # --allow-host NAME[:PORT]
            return True
        default = 443 if self.scheme == "https" else 80
        return host in self.names and (port if port is not None else default) == self.port

    def _proxied(self, value: str) -> bool:
        parsed = split_host(value)
        return parsed is not None and any(h == parsed[0] for h, _ in self.extra)

    # ---- Origin / Referer --------------------------------------------------------------------------------
    def origin_ok(self, origin: str | None, referer: str | None, host: str) -> tuple[bool, str]:
        """The request comes from a page of this panel (or from no browser at all: neither header)."""
        for name, value in (("Origin", origin), ("Referer", referer)):
            if value is None:
                continue
            try:
                u = urlsplit(value.strip())
                netloc = u.netloc.rsplit("@", 1)[-1]
            except ValueError:
                return False, f"{name} {value[:80]!r} is not this panel"
            schemes = ("http", "https") if self._proxied(host) else (self.scheme,)
            if u.scheme not in schemes or not netloc or split_host(netloc) is None:
                return False, f"{name} {value[:80]!r} is not this panel"
            if _same(split_host(netloc), split_host(host), u.scheme):
                return True, ""
            return False, f"{name} {value[:80]!r} is not this panel ({self.scheme}://{host})"
        return True, ""

    # ---- token ---------------------------------------------------------------------------------------------
    def authorized(self, headers: dict[str, str], path: str, query: str) -> bool:
        if not self.token:
            return True
        want = self.token.encode()
        auth = headers.get("authorization", "")
        if auth.lower().startswith("bearer "):
            return hmac.compare_digest(auth[7:].strip().encode(), want)
        from starlette.requests import cookie_parser

        if hmac.compare_digest(cookie_parser(headers.get("cookie", "")).get(self.cookie, "").encode(), want):
            return True
        if path == "/":  # opening the page with ?token=TOKEN once: the page sets the cookie
            from urllib.parse import parse_qs

            given = parse_qs(query).get("token", [""])[0]
            return bool(given) and hmac.compare_digest(given.encode(), want)
        return False

    # ---- CSRF ---------------------------------------------------------------------------------------------
    def new_token(self) -> str:
        """A token for one page: a random nonce and its MAC under this process's secret."""
        nonce = secrets.token_urlsafe(16)
        return f"{nonce}.{self._mac(nonce)}"

    def token_ok(self, token: str | None) -> bool:
        if not token or token.count(".") != 1 or len(token) > 200:
            return False
        nonce, mac = token.split(".")
        return hmac.compare_digest(mac, self._mac(nonce))

    def _mac(self, nonce: str) -> str:
        return hmac.new(self._secret, nonce.encode(), hashlib.sha256).hexdigest()[:32]

    # ---- the middleware ------------------------------------------------------------------------------------
    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers") or []}
        host = headers.get("host", "")
        refusal = None
        if not self.host_ok(host):
            refusal = (403, f"Host {host[:80]!r} is not a name of this panel (DNS rebinding or a wrong address; "
                            "--allow-host adds a name)")
        elif scope["type"] == "websocket":
            refusal = (403, "no websockets here")
        elif not self.authorized(headers, scope.get("path", ""), scope.get("query_string", b"").decode("latin-1")):
            refusal = (401, "token required (Authorization: Bearer or open /?token=...)")
        elif scope["method"] not in SAFE_METHODS:
            ok, why = self.origin_ok(headers.get("origin"), headers.get("referer"), host)
            ctype = headers.get("content-type", "").split(";")[0].strip().lower()
            if not ok:
                refusal = (403, f"cross-site request refused: {why}")
            elif ctype != "application/json":
                refusal = (415, f"a state change needs Content-Type: application/json, not {ctype or 'none'!r}")
            elif not self.token_ok(headers.get(CSRF_HEADER)):
                refusal = (403, "CSRF token missing or not from this panel (reload the page; scripts: GET "
                                "/api/csrf and send it as X-CSRF-Token)")
        if refusal is not None:
            if scope["type"] == "websocket":
                await send({"type": "websocket.close", "code": 1008})
                return
            body = {"error": refusal[1]}
            if refusal[1].startswith("CSRF") and headers.get(CSRF_HEADER):
                body["csrf"] = "stale"  # a page served by an earlier panel process: the page reloads itself
            await _send_json(send, refusal[0], body)
            return

        async def send_with_headers(message):
            if message["type"] == "http.response.start":
                have = {k.lower() for k, _ in message.get("headers", [])}
                message = {**message, "headers": [*message.get("headers", []),
                                                  *[(k, v) for k, v in SECURITY_HEADERS if k not in have]]}
            await send(message)

        await self.app(scope, receive, send_with_headers)


def _same(a: tuple[str, int | None] | None, b: tuple[str, int | None] | None, scheme: str) -> bool:
    """Two host:port pairs name the same origin (a missing port is the scheme's default)."""
    if a is None or b is None:
        return False
    default = 443 if scheme == "https" else 80
    return a[0] == b[0] and (a[1] or default) == (b[1] or default)


async def _send_json(send, status: int, body: dict) -> None:
    data = json.dumps(body).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(data)).encode()),
                            *SECURITY_HEADERS]})
    await send({"type": "http.response.body", "body": data})
