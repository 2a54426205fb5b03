"""``companion view``: a web page that shows what the drone sees, served by a process of its own.

The view process follows the service exactly as ``companion watch`` and ``companion ctl`` do: it
subscribes to the health PUB socket and to the preview XPUB socket, and sends engage / disengage /
pause / resume through :class:`~companion.service.client.ControlClient` on the control socket. The
service never waits for it: its sockets drop what a slow or stopped subscriber does not take, so the
view crashing or hanging changes nothing on the vehicle.

HTTP (aiohttp; one process, one event loop):

* ``GET /``: the page (``companion/view/static``: plain HTML, JS and CSS, no external URL);
* ``GET /ws``: a WebSocket: a ``hello`` (the last 60 s of decisions, the thresholds, whether control
  is possible), then each health message as JSON text and each preview frame as a binary JPEG. A
  client that cannot keep up gets the newest message when it is ready again, never a backlog;
* ``GET /api/health``, ``GET /api/timeline``, ``GET /preview.jpg``, ``GET /stream.mjpg`` (MJPEG, for
  a video player);
* ``POST /api/control`` with ``{"cmd": "engage" | "disengage" | "pause" | "resume"}``.

Who may watch and command, and how the token is given: :mod:`companion.view.access`. What the view
knows of the service and pushes to its pages: :mod:`companion.view.feed`.
"""

from __future__ import annotations

import asyncio
import json
import logging
from typing import Any

from companion.errors import InputError
from companion.view.access import AccessGuard
from companion.view.feed import TIMELINE_S, Client, ServiceFeed
from companion.view.options import ViewOptions, check_options, display_hosts

log = logging.getLogger(__name__)

#: The control requests the page may send (the rest of the protocol stays with ``companion ctl``).
PAGE_COMMANDS = ("engage", "disengage", "pause", "resume")
_STATIC = {"index.html": "text/html", "app.js": "text/javascript", "style.css": "text/css", "favicon.svg": "image/svg+xml"}


class ViewServer:
    """The view's HTTP server over what it follows of the service (:attr:`feed`).

    Use ``await start()`` then ``await stop()``; :attr:`urls` says where it serves.
    """

    def __init__(self, options: ViewOptions) -> None:
        check_options(options)
        self.options = options
        self.feed = ServiceFeed(options)
        self._access = AccessGuard(options)
        self._runner: Any = None
        self.urls: list[str] = []
        self.port: int | None = None
        self._static: dict[str, bytes] = {}

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Connect to the service's sockets and start serving.

        Raises:
            InputError: the port cannot be bound.
        """
        from aiohttp import web

        self._load_static()
        self.feed.start()
        app = web.Application(middlewares=[self._access.middleware], client_max_size=64 * 1024)
        app.router.add_get("/", self._index)
        app.router.add_get("/static/{name}", self._static_file)
        app.router.add_get("/favicon.ico", self._favicon)
        app.router.add_get("/ws", self._ws)
        app.router.add_get("/api/health", self._api_health)
        app.router.add_get("/api/timeline", self._api_timeline)
        app.router.add_get("/preview.jpg", self._preview_jpg)
        app.router.add_get("/stream.mjpg", self._mjpeg)
        app.router.add_post("/api/control", self._api_control)
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False, shutdown_timeout=1.0)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.options.host, self.options.port)
        try:
            await site.start()
        except OSError as err:
            await self.stop()
            raise InputError(f"cannot serve on {self.options.host}:{self.options.port}: {err.strerror or err} (try --port)") from None
        sockets = site._server.sockets if site._server is not None else []  # noqa: SLF001 (aiohttp keeps them there)
        self.port = sockets[0].getsockname()[1] if sockets else self.options.port
        self.urls = [self._url(h) for h in display_hosts(self.options.host)]
        log.info("view: serving on %s", ", ".join(self.urls))

    def _url(self, host: str) -> str:
        shown = f"[{host}]" if ":" in host else host
        query = f"/?token={self.options.token}" if self.options.token else "/"
        return f"http://{shown}:{self.port}{query}"

    async def stop(self) -> None:
        await self.feed.stop()
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        self.feed.close()

    def _load_static(self) -> None:
        from importlib import resources

        root = resources.files("companion.view") / "static"
        self._static = {name: (root / name).read_bytes() for name in _STATIC}


    # ------------------------------------------------------------------ HTTP

    async def _index(self, request: Any) -> Any:
        from aiohttp import web

        # With ?token=, the page keeps the token in the tab's sessionStorage and drops it from the
        # address bar itself (a redirect would hide it from the page too).
        response = web.Response(body=self._static["index.html"], content_type="text/html", charset="utf-8")
        response.headers["Content-Security-Policy"] = (
            "default-src 'self'; img-src 'self' blob: data:; connect-src 'self'; style-src 'self'; "
            "script-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'"
        )
        return response

    async def _static_file(self, request: Any) -> Any:
        from aiohttp import web

        name = request.match_info["name"]
        if name not in _STATIC or name == "index.html":
            raise web.HTTPNotFound()
        return web.Response(body=self._static[name], content_type=_STATIC[name])

    async def _favicon(self, request: Any) -> Any:
        from aiohttp import web

        return web.Response(body=self._static["favicon.svg"], content_type="image/svg+xml")

    def _hello(self) -> dict[str, Any]:
        return {
            "type": "hello",
            "title": self.options.title,
            "control": self.options.control_endpoint is not None,
            "commands": list(PAGE_COMMANDS),
            "timeline_s": TIMELINE_S,
            "timeline": list(self.feed.timeline),
            "thresholds": self.feed.thresholds,
            "health": self.feed.health,
            "view": self.feed.view_status(),
        }

    async def _ws(self, request: Any) -> Any:
        from aiohttp import WSMsgType, web

        ws = web.WebSocketResponse(heartbeat=10.0, max_msg_size=4096)
        await ws.prepare(request)
        client = Client()
        await ws.send_str(json.dumps(self._hello()))
        client.jpeg = self.feed.jpeg
        client.wake.set()
        self.feed.clients.add(client)

        async def sender() -> None:
            while not ws.closed:
                await client.wake.wait()
                client.wake.clear()
                texts, client.text = client.text, {}
                jpeg, client.jpeg = client.jpeg, None
                for text in texts.values():
                    await ws.send_str(text)
                if jpeg is not None:
                    await ws.send_bytes(jpeg)  # waits while the client is slow; newer frames replace it

        task = asyncio.create_task(sender())
        try:
            async for msg in ws:  # the page sends nothing that matters; this notices the close
                if msg.type == WSMsgType.ERROR:
                    break
        finally:
            self.feed.clients.discard(client)
            task.cancel()
            try:
                await task
            except (asyncio.CancelledError, ConnectionError, RuntimeError):
                pass
        return ws

    async def _api_health(self, request: Any) -> Any:
        from aiohttp import web

        return web.json_response({"health": self.feed.health, "view": self.feed.view_status(), "thresholds": self.feed.thresholds})

    async def _api_timeline(self, request: Any) -> Any:
        from aiohttp import web

        return web.json_response({"timeline_s": TIMELINE_S, "timeline": list(self.feed.timeline)})

    async def _preview_jpg(self, request: Any) -> Any:
        from aiohttp import web

        if self.feed.jpeg is None:
            raise web.HTTPNotFound(text="no preview yet\n")
        return web.Response(body=self.feed.jpeg, content_type="image/jpeg")

    async def _mjpeg(self, request: Any) -> Any:
        from aiohttp import web

        response = web.StreamResponse(headers={"Content-Type": "multipart/x-mixed-replace; boundary=frame"})
        await response.prepare(request)
        while True:
            assert self.feed.mjpeg_wake is not None
            jpeg = self.feed.jpeg
            if jpeg is not None:
                await response.write(
                    b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
                    + str(len(jpeg)).encode()
                    + b"\r\n\r\n"
                    + jpeg
                    + b"\r\n"
                )
            await self.feed.mjpeg_wake.wait()

    async def _api_control(self, request: Any) -> Any:
        from aiohttp import web

        if request.headers.get("X-Companion-View") != "1":
            return web.json_response({"ok": False, "error": {"type": "Forbidden", "message": "not from the view's page"}}, status=403)
        if self.options.control_endpoint is None:
            return web.json_response(
                {"ok": False, "error": {"type": "ReadOnly", "message": "this view has no control socket (read-only or a simulation)"}},
                status=409,
            )
        if not self._access.bearer_ok(request):
            message = (
                "commanding needs the view's token (Authorization: Bearer TOKEN): open the address "
                "`companion view` printed (…/?token=…)"
                if self.options.token is not None
                else "this view has no token: it cannot command (start it with --token-file or $COMPANION_VIEW_TOKEN)"
            )
            return web.json_response({"ok": False, "error": {"type": "Forbidden", "message": message}}, status=403)
        try:
            body = await request.json()
        except (ValueError, UnicodeDecodeError):
            body = None
        cmd = body.get("cmd") if isinstance(body, dict) else None
        if cmd not in PAGE_COMMANDS:
            return web.json_response(
                {"ok": False, "error": {"type": "ProtocolError", "message": f"cmd must be one of {', '.join(PAGE_COMMANDS)}"}},
                status=400,
            )
        log.info("view: %s requested from %s", cmd, request.remote)
        try:
            reply = await self.feed.control({"cmd": cmd})
        except Exception as err:  # no reply (service gone, CURVE refused): say so on the page
            return web.json_response({"ok": False, "cmd": cmd, "error": {"type": type(err).__name__, "message": str(err)}}, status=504)
        return web.json_response(reply)



async def serve(options: ViewOptions, ready: Any = None, stop: asyncio.Event | None = None) -> None:
    """Run the view until cancelled (or ``stop`` is set); ``ready(server)`` is called once it serves."""
    server = ViewServer(options)
    await server.start()
    try:
        if ready is not None:
            ready(server)
        if stop is None:
            stop = asyncio.Event()
        await stop.wait()
    finally:
        await server.stop()
