"""The operator panel's web app (Starlette): one page and the public JSON API it uses (docs/panel.md).

    GET  /api/state            {"state": idle|running|prompt|done, "serial", "procedure", "step", "samples",
                                "samples_planned", "verdict": null|PASS|FAIL|NOT STORED|ABORTED|ERROR, "session", ...}
    POST /api/start            {"serial", "operator"[, "procedure"]}
    POST /api/abort
    POST /api/prompt           {"answer"}
    POST /api/clear            the verdict screen goes away (the next serial was scanned)
    POST /api/resume           {"session"[, "operator"]}
    GET  /api/resumable        interrupted sessions on this station
    GET  /api/history/{serial} previous runs and each parameter's trend
    GET  /api/events           server-sent events: the state on every change
    GET  /api/points/{label}/image       the reference point's picture (``image:`` in the cell file)
    GET  /api/points/{label}/sketch.svg  where the point is in the cell, seen from above (generated)
    GET  /report/{session}     the session's HTML report

    GET  /api/csrf             {"csrf": token} for a script's state changes (the page carries its own)

Every request passes ``station.panel.webguard`` first (its own Host names; for a state change: Origin/Referer of
the panel itself, ``Content-Type: application/json`` and an ``X-CSRF-Token`` the panel issued). With a token,
every request also needs ``Authorization: Bearer TOKEN`` or the ``station_token`` cookie (opening
``/?token=TOKEN`` once sets it)."""

from __future__ import annotations

import asyncio
import hmac
import json
import secrets
from importlib import resources
from pathlib import Path

from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse, Response, StreamingResponse
from starlette.routing import Route

from station.panel.controller import Controller, PanelError, WrongState, report_path
from station.panel.history import unit_history
from station.panel.webguard import Guard

COOKIE = "station_token"


def _page() -> str:
    return resources.files("station.panel").joinpath("page.html").read_text(encoding="utf-8")


class _Endpoints:
    """The panel's HTTP endpoints over one controller; ``guard`` (set once built) issues the CSRF tokens."""

    def __init__(self, controller: Controller, token: str | None, tls: bool) -> None:
        self.controller, self.token, self.tls = controller, token, tls
        self.page = _page()
        self.guard: Guard | None = None

    async def body(self, request: Request) -> dict:
        try:
            data = await request.json()
        except (ValueError, UnicodeDecodeError):
            raise PanelError("the body must be a JSON object") from None
        if not isinstance(data, dict):
            raise PanelError("the body must be a JSON object")
        return data

    @staticmethod
    def refused(e: PanelError) -> JSONResponse:
        return JSONResponse({"error": str(e)}, status_code=409 if isinstance(e, WrongState) else 400)

    async def index(self, request: Request):
        q = request.query_params.get("token")
        if self.token and q and hmac.compare_digest(q.encode(), self.token.encode()):
            r = RedirectResponse("/", status_code=303)
            r.set_cookie(COOKIE, self.token, httponly=True, samesite="strict", secure=self.tls)
            return r
        nonce = secrets.token_urlsafe(16)
        html = self.page.replace("__STATION_CSRF__", self.guard.new_token()).replace("__STATION_NONCE__", nonce)
        return HTMLResponse(html, headers={
            "Cache-Control": "no-store",  # the page carries its CSRF token
            "Content-Security-Policy": f"default-src 'self'; script-src 'nonce-{nonce}'; style-src 'self' "
                                       "'unsafe-inline'; img-src 'self' data:; connect-src 'self'; "
                                       "frame-ancestors 'none'; base-uri 'none'; form-action 'none'"})

    async def csrf(self, request: Request):
        return JSONResponse({"csrf": self.guard.new_token()}, headers={"Cache-Control": "no-store"})

    async def state(self, request: Request):
        return JSONResponse(self.controller.snapshot())

    async def start(self, request: Request):
        try:
            d = await self.body(request)
            sid = await asyncio.to_thread(self.controller.start, str(d.get("serial") or ""),
                                          str(d.get("operator") or ""), d.get("procedure") or None)
        except PanelError as e:
            return self.refused(e)
        return JSONResponse({**self.controller.snapshot(), "session": sid or self.controller.snapshot()["session"]},
                            status_code=202)

    async def abort(self, request: Request):
        try:
            self.controller.abort()
        except PanelError as e:
            return self.refused(e)
        return JSONResponse(self.controller.snapshot(), status_code=202)

    async def prompt(self, request: Request):
        try:
            d = await self.body(request)
            self.controller.answer(str(d.get("answer") or ""))
        except PanelError as e:
            return self.refused(e)
        return JSONResponse(self.controller.snapshot())

    async def clear(self, request: Request):
        try:
            self.controller.clear()
        except PanelError as e:
            return self.refused(e)
        return JSONResponse(self.controller.snapshot())

    async def resume(self, request: Request):
        try:
            d = await self.body(request)
            sid = await asyncio.to_thread(self.controller.resume, str(d.get("session") or ""), d.get("operator"))
        except PanelError as e:
            return self.refused(e)
        return JSONResponse({**self.controller.snapshot(), "session": sid}, status_code=202)

    async def resumable(self, request: Request):
        return JSONResponse(await asyncio.to_thread(self.controller.resumable))

    async def history(self, request: Request):
        serial = request.path_params["serial"]
        return JSONResponse(await asyncio.to_thread(unit_history, serial, self.controller.config.db))

    async def events(self, request: Request):
        async def stream():
            version = -1
            while True:
                if await request.is_disconnected():
                    return
                snap = self.controller.snapshot()
                if snap["version"] != version:
                    version = snap["version"]
                    yield f"data: {json.dumps(snap)}\n\n"
                else:
                    await asyncio.to_thread(self.controller.wait_change, version, 1.0)
                    if self.controller.version == version:
                        yield ": keep-alive\n\n"

        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})

    async def report(self, request: Request):
        p = report_path(request.path_params["session"])
        if p is None:
            return JSONResponse({"error": "no report for this session"}, status_code=404)
        # the report is the station's own HTML (escaped, pictures inline): nothing in it may run or load
        return FileResponse(p, media_type="text/html", headers={
            "Content-Security-Policy": "default-src 'none'; img-src data:; style-src 'unsafe-inline'; "
                                       "frame-ancestors 'none'"})

    def _point(self, request: Request):
        cell = self.controller.cell()
        return None if cell is None else cell.points.get(request.path_params["label"])

    async def point_image(self, request: Request):
        from station.engine.cell import IMAGE_TYPES

        p = await asyncio.to_thread(self._point, request)
        if p is None or not p.image:
            return JSONResponse({"error": "no picture of this point in the cell file"}, status_code=404)
        path = Path(p.image)  # checked at load: inside the cell file's folder; the URL names a label only
        return FileResponse(path, media_type=IMAGE_TYPES[path.suffix.lower()],
                            headers={"Content-Security-Policy": "default-src 'none'; style-src 'unsafe-inline'",
                                     "X-Content-Type-Options": "nosniff"})

    async def point_sketch(self, request: Request):
        from station.panel.sketch import point_sketch as sketch

        p = await asyncio.to_thread(self._point, request)
        if p is None:
            return JSONResponse({"error": "no such reference point in the cell file"}, status_code=404)
        return Response(sketch(self.controller.cell(), p.label), media_type="image/svg+xml",
                        headers={"Content-Security-Policy": "default-src 'none'; style-src 'unsafe-inline'"})

    def routes(self) -> list[Route]:
        post = {"methods": ["POST"]}
        return [Route("/", self.index), Route("/api/state", self.state),
                Route("/api/start", self.start, **post), Route("/api/abort", self.abort, **post),
                Route("/api/prompt", self.prompt, **post), Route("/api/clear", self.clear, **post),
                Route("/api/resume", self.resume, **post), Route("/api/resumable", self.resumable),
                Route("/api/history/{serial:path}", self.history), Route("/api/events", self.events),
                Route("/api/points/{label}/image", self.point_image),
                Route("/api/points/{label}/sketch.svg", self.point_sketch),
                Route("/report/{session}", self.report), Route("/api/csrf", self.csrf)]


def create_app(controller: Controller, token: str | None = None, *, host: str = "127.0.0.1", port: int = 8470,
               loopback: bool = True, tls: bool = False, allow_hosts: tuple[str, ...] = ()) -> Guard:
    """The panel's ASGI app for a server listening on ``host:port``: the Starlette routes inside the
    :class:`~station.panel.webguard.Guard` of that address."""
    endpoints = _Endpoints(controller, token, tls)
    endpoints.guard = Guard(Starlette(routes=endpoints.routes()), bind=host, port=port, loopback=loopback, tls=tls,
                            allow_hosts=allow_hosts, token=token, cookie=COOKIE)
    return endpoints.guard
