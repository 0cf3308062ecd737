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


def create_app(controller: Controller, token: str | None = None, *, host: str = "127.0.0.1", port: int = 8470,
               loopback: bool = True, tls: bool = False, allow_hosts: tuple[str, ...] = ()) -> Guard:
    """The panel's ASGI app for a server listening on ``host:port``: the Starlette routes inside the
    :class:`~station.panel.webguard.Guard` of that address."""
    page = _page()
    app_guard: Guard | None = None  # set below; the page and /api/csrf issue its tokens

    async def body(request: Request) -> dict:
        try:
            data = await request.json()
        except (ValueError, UnicodeDecodeError):
            raise PanelError("the body must be a JSON object") from None
        if not isinstance(data, dict):
            raise PanelError("the body must be a JSON object")
        return data

    def refused(e: PanelError) -> JSONResponse:
        return JSONResponse({"error": str(e)}, status_code=409 if isinstance(e, WrongState) else 400)

    async def index(request: Request):
        q = request.query_params.get("token")
        if token and q and hmac.compare_digest(q.encode(), token.encode()):
            r = RedirectResponse("/", status_code=303)
            r.set_cookie(COOKIE, token, httponly=True, samesite="strict", secure=tls)
            return r
        nonce = secrets.token_urlsafe(16)
        html = page.replace("__STATION_CSRF__", app_guard.new_token()).replace("__STATION_NONCE__", nonce)
        return HTMLResponse(html, headers={
            "Cache-Control": "no-store",  # the page carries its CSRF token
            "Content-Security-Policy": f"default-src 'self'; script-src 'nonce-{nonce}'; style-src 'self' "
                                       "'unsafe-inline'; img-src 'self' data:; connect-src 'self'; "
                                       "frame-ancestors 'none'; base-uri 'none'; form-action 'none'"})

    async def csrf(request: Request):
        return JSONResponse({"csrf": app_guard.new_token()}, headers={"Cache-Control": "no-store"})

    async def state(request: Request):
        return JSONResponse(controller.snapshot())

    async def start(request: Request):
        try:
            d = await body(request)
            sid = await asyncio.to_thread(controller.start, str(d.get("serial") or ""),
                                          str(d.get("operator") or ""), d.get("procedure") or None)
        except PanelError as e:
            return refused(e)
        return JSONResponse({**controller.snapshot(), "session": sid or controller.snapshot()["session"]},
                            status_code=202)

    async def abort(request: Request):
        try:
            controller.abort()
        except PanelError as e:
            return refused(e)
        return JSONResponse(controller.snapshot(), status_code=202)

    async def prompt(request: Request):
        try:
            d = await body(request)
            controller.answer(str(d.get("answer") or ""))
        except PanelError as e:
            return refused(e)
        return JSONResponse(controller.snapshot())

    async def clear(request: Request):
        try:
            controller.clear()
        except PanelError as e:
            return refused(e)
        return JSONResponse(controller.snapshot())

    async def resume(request: Request):
        try:
            d = await body(request)
            sid = await asyncio.to_thread(controller.resume, str(d.get("session") or ""), d.get("operator"))
        except PanelError as e:
            return refused(e)
        return JSONResponse({**controller.snapshot(), "session": sid}, status_code=202)

    async def resumable(request: Request):
        return JSONResponse(await asyncio.to_thread(controller.resumable))

    async def history(request: Request):
        serial = request.path_params["serial"]
        return JSONResponse(await asyncio.to_thread(unit_history, serial, controller.config.db))

    async def events(request: Request):
        async def stream():
            version = -1
            while True:
                if await request.is_disconnected():
                    return
                snap = controller.snapshot()
                if snap["version"] != version:
                    version = snap["version"]
                    yield f"data: {json.dumps(snap)}\n\n"
                else:
                    await asyncio.to_thread(controller.wait_change, version, 1.0)
                    if controller.version == version:
                        yield ": keep-alive\n\n"

        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})

    async def report(request: Request):
        p = report_path(request.path_params["session"])
        if p is None:
            return JSONResponse({"error": "no report for this session"}, status_code=404)
        # the report is the station's own HTML (escaped, pictures inline): nothing in it may run or load
        return FileResponse(p, media_type="text/html", headers={
            "Content-Security-Policy": "default-src 'none'; img-src data:; style-src 'unsafe-inline'; "
                                       "frame-ancestors 'none'"})

    def _point(request: Request):
        cell = controller.cell()
        return None if cell is None else cell.points.get(request.path_params["label"])

    async def point_image(request: Request):
        from station.engine.cell import IMAGE_TYPES

        p = await asyncio.to_thread(_point, request)
        if p is None or not p.image:
            return JSONResponse({"error": "no picture of this point in the cell file"}, status_code=404)
        path = Path(p.image)  # checked at load: inside the cell file's folder; the URL names a label only
        return FileResponse(path, media_type=IMAGE_TYPES[path.suffix.lower()],
                            headers={"Content-Security-Policy": "default-src 'none'; style-src 'unsafe-inline'",
                                     "X-Content-Type-Options": "nosniff"})

    async def point_sketch(request: Request):
        from station.panel.sketch import point_sketch as sketch

        p = await asyncio.to_thread(_point, request)
        if p is None:
            return JSONResponse({"error": "no such reference point in the cell file"}, status_code=404)
        return Response(sketch(controller.cell(), p.label), media_type="image/svg+xml",
                        headers={"Content-Security-Policy": "default-src 'none'; style-src 'unsafe-inline'"})

    post = {"methods": ["POST"]}
    routes = [Route("/", index), Route("/api/state", state),
              Route("/api/start", start, **post), Route("/api/abort", abort, **post),
              Route("/api/prompt", prompt, **post), Route("/api/clear", clear, **post),
              Route("/api/resume", resume, **post), Route("/api/resumable", resumable),
              Route("/api/history/{serial:path}", history), Route("/api/events", events),
              Route("/api/points/{label}/image", point_image),
              Route("/api/points/{label}/sketch.svg", point_sketch),
              Route("/report/{session}", report), Route("/api/csrf", csrf)]
    app_guard = Guard(Starlette(routes=routes), bind=host, port=port, loopback=loopback, tls=tls,
                      allow_hosts=allow_hosts, token=token, cookie=COOKIE)
    return app_guard
