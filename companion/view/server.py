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

Access: bound to 127.0.0.1 by default. The view has a token (given in a file or
``$COMPANION_VIEW_TOKEN``, else made up), printed only in the URL it shows its operator
(``…/?token=…``); it is never served to anyone who asks.

* Commanding (``POST /api/control``) always needs it, on loopback too (another local user can reach a
  loopback port, but cannot read the operator's terminal, a file of mode 0600, or a process's
  environment): ``Authorization: Bearer TOKEN``, compared in constant time, besides the page's own
  header (``X-Companion-View: 1``) and origin (no cross-site request can send them). The page takes
  the token from its address once, keeps it in the tab's ``sessionStorage`` and drops it from the
  address bar.
* Watching: on a loopback bind open to anyone local, for loopback Host names only (a web page
  elsewhere cannot reach it by DNS rebinding). Any other bind needs the token for everything: as
  ``?token=`` once (the page's later requests carry it in a cookie) or ``Authorization: Bearer``.
"""

from __future__ import annotations

import asyncio
import collections
import hmac
import ipaddress
import json
import logging
import math
import shutil
import socket
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from companion.errors import InputError

log = logging.getLogger(__name__)

#: The control requests the page may send (the rest of the protocol stays with ``companion ctl``).
PAGE_COMMANDS = ("engage", "disengage", "pause", "resume")
#: How far back the page's timeline goes, seconds.
TIMELINE_S = 60.0
_COOKIE = "companion_view_token"
_STATIC = {"index.html": "text/html", "app.js": "text/javascript", "style.css": "text/css", "favicon.svg": "image/svg+xml"}
_LOOPBACK_NAMES = ("localhost", "localhost.localdomain", "ip6-localhost")


@dataclass(frozen=True)
class ViewOptions:
    """What ``companion view`` connects to and how it serves.

    Attributes:
        health_endpoint: the service's health PUB endpoint.
        preview_endpoint: the service's preview XPUB endpoint, or None (no picture).
        control_endpoint: the control socket, or None: read-only (no buttons).
        curve: CURVE client options for the ZeroMQ sockets (see
            :func:`~companion.service.client.curve_client_options`), or None.
        host: the address to bind (127.0.0.1 by default).
        port: the TCP port (0 = any free one).
        token: the access token, or None (only on a loopback bind, and then nothing commands).
        title: shown in the page's header.
        control_timeout_s: how long a control request waits for the service's reply, seconds.
        say: called with each line the operator's terminal should show (the rig check's lines from
            health's ``rig``, when they first arrive or change), or None.
    """

    health_endpoint: str
    preview_endpoint: str | None
    control_endpoint: str | None
    curve: dict[str, bytes] | None = None
    host: str = "127.0.0.1"
    port: int = 8080
    token: str | None = None
    title: str = "companion"
    control_timeout_s: float = 3.0
    say: Callable[[str], None] | None = None


def is_loopback_host(host: str) -> bool:
    """True for a loopback address or name (127.0.0.0/8, ::1, localhost)."""
    host = host.strip("[]")
    if host.lower() in _LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_options(options: ViewOptions) -> None:
    """Refuse a network bind without a token, and a token too short to be one.

    Raises:
        InputError: naming what is wrong.
    """
    if not is_loopback_host(options.host) and not options.token:
        raise InputError(
            f"--host {options.host} serves the network: it needs a token (--token-file FILE, or "
            "$COMPANION_VIEW_TOKEN; `companion view` makes one up and prints it when neither is given)"
        )
    if options.token is not None and len(options.token) < 8:
        raise InputError("the view's token must be at least 8 characters")
    if not 0 <= options.port <= 65535:
        raise InputError(f"--port must be 0..65535, got {options.port}")


def _finite(x: Any) -> float | None:
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) else None


def timeline_point(h: dict[str, Any]) -> dict[str, Any]:
    """The compact form of one health message that the page's timeline draws."""
    decision = h.get("decision") or {}
    sp = h.get("setpoint") or {}
    regions = h.get("regions_m") or {}
    return {
        "t": _finite(h.get("time_s")),
        "state": h.get("state"),
        "kind": decision.get("kind"),
        "yaw": _finite(h.get("yaw")),
        "pitch": _finite(h.get("pitch")),
        "fwd": _finite(sp.get("forward_m_s")),
        "yaw_rate": _finite(sp.get("yaw_rate_deg_s")),
        "center": _finite(regions.get("center")),
    }


@dataclass(eq=False)
class _Client:
    """One WebSocket: the newest health text and JPEG waiting for it (replaced, never queued)."""

    wake: asyncio.Event = field(default_factory=asyncio.Event)
    text: dict[str, str] = field(default_factory=dict)  # message type -> its newest text
    jpeg: bytes | None = None


class ViewServer:
    """The view's state (newest health, 60 s timeline, newest JPEG) and its HTTP server.

    Use ``await start()`` then ``await stop()``; :attr:`urls` says where it serves.
    """

    def __init__(self, options: ViewOptions) -> None:
        check_options(options)
        self.options = options
        self.health: dict[str, Any] | None = None
        self.health_at_s: float | None = None  # this process's monotonic clock
        self.timeline: collections.deque[dict[str, Any]] = collections.deque()
        self.jpeg: bytes | None = None
        self.preview_header: dict[str, Any] | None = None
        self.preview_at_s: float | None = None
        self.previews = 0
        self._preview_times: collections.deque[float] = collections.deque(maxlen=64)
        self.thresholds: dict[str, float] | None = None
        self.rig_lines: list[str] = []
        self._thresholds_version: Any = None
        self._clients: set[_Client] = set()
        self._mjpeg_wake: asyncio.Event | None = None
        self._ctx: Any = None
        self._tasks: list[asyncio.Task] = []
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
        import zmq
        import zmq.asyncio
        from aiohttp import web

        self._load_static()
        self._mjpeg_wake = asyncio.Event()
        self._ctx = zmq.asyncio.Context()
        health = self._socket(zmq.SUB, self.options.health_endpoint, b"")
        self._tasks.append(asyncio.create_task(self._follow_health(health), name="view health"))
        if self.options.preview_endpoint:
            preview = self._socket(zmq.SUB, self.options.preview_endpoint, b"preview")
            self._tasks.append(asyncio.create_task(self._follow_preview(preview), name="view preview"))
        self._tasks.append(asyncio.create_task(self._ticker(), name="view ticker"))
        app = web.Application(middlewares=[self._guard], client_max_size=64 * 1024)
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
        self.urls = [self._url(h) for h in _display_hosts(self.options.host)]
        log.info("view: serving on %s", ", ".join(self.urls))

    def _url(self, host: str) -> str:
        shown = f"[{host}]" if ":" in host else host
        query = f"/?token={self.options.token}" if self.options.token else "/"
        return f"http://{shown}:{self.port}{query}"

    def _socket(self, kind: int, endpoint: str, topic: bytes) -> Any:
        import zmq

        sock = self._ctx.socket(kind)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.RCVHWM, 8)
        for name, value in (self.options.curve or {}).items():
            setattr(sock, name, value)
        sock.setsockopt(zmq.SUBSCRIBE, topic)
        sock.connect(endpoint)
        return sock

    async def stop(self) -> None:
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            try:
                await task
            except (asyncio.CancelledError, Exception):
                pass
        self._tasks = []
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        if self._ctx is not None:
            self._ctx.destroy(linger=0)
            self._ctx = None

    def _load_static(self) -> None:
        from importlib import resources

        root = resources.files("companion.view") / "static"
        self._static = {name: (root / name).read_bytes() for name in _STATIC}

    # ------------------------------------------------------------------ following the service

    async def _follow_health(self, sock: Any) -> None:
        while True:
            raw = await sock.recv()
            try:
                h = json.loads(raw)
            except ValueError:
                log.warning("view: a health message that is not JSON: %r", raw[:80])
                continue
            if not isinstance(h, dict):
                continue
            self.health, self.health_at_s = h, time.monotonic()
            point = timeline_point(h)
            if point["t"] is not None:
                if self.timeline and self.timeline[-1]["t"] is not None and point["t"] < self.timeline[-1]["t"]:
                    self.timeline.clear()  # a new service (its clock started again)
                self.timeline.append(point)
                while self.timeline and point["t"] - self.timeline[0]["t"] > TIMELINE_S:
                    self.timeline.popleft()
            self._thresholds_from_health(h)
            self._rig_from_health(h)
            self._broadcast_text("health", json.dumps({"type": "health", "health": h, "view": self._view_status()}))

    async def _follow_preview(self, sock: Any) -> None:
        from companion.service.preview_frame import unpack

        while True:
            frames = await sock.recv_multipart()
            try:
                header, jpeg = unpack(frames)
            except Exception as err:
                log.warning("view: %s", err)
                continue
            now = time.monotonic()
            self.jpeg, self.preview_header, self.preview_at_s = jpeg, header, now
            self.previews += 1
            self._preview_times.append(now)
            for client in self._clients:
                client.jpeg = jpeg
                client.wake.set()
            assert self._mjpeg_wake is not None
            self._mjpeg_wake.set()
            self._mjpeg_wake = asyncio.Event()

    def _thresholds_from_health(self, h: dict[str, Any]) -> None:
        """The region bars' near/far thresholds from health's ``thresholds_m`` (every message carries
        them, so they are right from the first message, with or without a picture); an older service
        without them: asked once per config version through the control socket."""
        t = h.get("thresholds_m") if isinstance(h.get("thresholds_m"), dict) else {}
        near, far = _finite(t.get("near_m")), _finite(t.get("far_m"))
        if near is not None and far is not None:
            new = {"near_m": near, "far_m": far}
            if new != self.thresholds:
                self.thresholds = new
                self._broadcast_text("thresholds", json.dumps({"type": "thresholds", **new}))
            return
        if self.thresholds is None or self._thresholds_version != h.get("config_version"):
            self._thresholds_version = h.get("config_version")
            if self.options.control_endpoint:
                asyncio.create_task(self._fetch_thresholds())

    def _rig_from_health(self, h: dict[str, Any]) -> None:
        """The rig check's lines (health's ``rig``): kept for the page, and said in the terminal when
        they first arrive or change."""
        rig = h.get("rig") if isinstance(h.get("rig"), dict) else {}
        lines = [str(line) for line in rig.get("lines") or [] if isinstance(line, str)]
        if lines != self.rig_lines:
            self.rig_lines = lines
            if self.options.say is not None:
                for line in lines:
                    self.options.say(line)

    async def _fetch_thresholds(self) -> None:
        try:
            reply = await self._control({"cmd": "get_config", "section": "controller"})
        except Exception as err:  # the thresholds are only a drawing aid
            log.debug("view: no thresholds from get_config: %s", err)
            return
        terms = ((reply.get("result") or {}).get("config") or {}).get("input_terms") or {}
        try:
            near, far = float(terms["near"]["params_m"][0]), float(terms["far"]["params_m"][-1])
        except (KeyError, IndexError, TypeError, ValueError):
            return
        self.thresholds = {"near_m": near, "far_m": far}
        self._broadcast_text("thresholds", json.dumps({"type": "thresholds", **self.thresholds}))

    async def _ticker(self) -> None:
        """Once a second: the view's own status (how old the newest health and picture are)."""
        while True:
            await asyncio.sleep(1.0)
            self._broadcast_text("tick", json.dumps({"type": "tick", "view": self._view_status()}))

    def _view_status(self) -> dict[str, Any]:
        now = time.monotonic()
        recent = [t for t in self._preview_times if now - t <= 2.0]
        return {
            "health_age_s": None if self.health_at_s is None else now - self.health_at_s,
            "preview_age_s": None if self.preview_at_s is None else now - self.preview_at_s,
            "preview_fps": len(recent) / 2.0,
            "previews": self.previews,
            "preview_encode_ms": (self.preview_header or {}).get("encode_ms"),
            "clients": len(self._clients),
            "health_endpoint": self.options.health_endpoint,
            "rig_lines": self.rig_lines,
        }

    def _broadcast_text(self, kind: str, text: str) -> None:
        """Queue ``text`` for every page; a newer message of the same kind replaces one not sent yet."""
        for client in self._clients:
            client.text.pop(kind, None)
            client.text[kind] = text
            client.wake.set()

    # ------------------------------------------------------------------ control

    async def _control(self, request: dict[str, Any]) -> dict[str, Any]:
        from companion.service.client import ControlClient

        endpoint = self.options.control_endpoint
        assert endpoint is not None

        def call() -> dict[str, Any]:
            with ControlClient(endpoint, timeout_s=self.options.control_timeout_s, curve=self.options.curve) as client:
                return client.call(request)

        return await asyncio.to_thread(call)

    # ------------------------------------------------------------------ HTTP

    def _token_ok(self, request: Any) -> bool:
        """Whether ``request`` carries the token (in its query, its cookie or its Authorization)."""
        given = [
            request.query.get("token", ""),
            request.cookies.get(_COOKIE, ""),
            request.headers.get("Authorization", "").removeprefix("Bearer ").strip(),
        ]
        return any(self._is_token(g) for g in given)

    def _is_token(self, given: str) -> bool:
        token = self.options.token
        # Constant time: how much of a guess matched must not show in how long the refusal takes.
        return token is not None and bool(given) and hmac.compare_digest(given.encode(), token.encode())

    def _bearer_ok(self, request: Any) -> bool:
        """Whether ``request`` carries the token as ``Authorization: Bearer`` (what commanding needs)."""
        header = request.headers.get("Authorization", "")
        return header.startswith("Bearer ") and self._is_token(header.removeprefix("Bearer ").strip())

    def _same_origin(self, request: Any) -> bool:
        origin = request.headers.get("Origin")
        if origin is None:
            return True
        from yarl import URL

        try:
            o = URL(origin)
        except ValueError:
            return False
        return o.host is not None and f"{o.host}:{o.port}" == f"{request.url.host}:{request.url.port}"

    async def _guard_impl(self, request: Any, handler: Any) -> Any:
        from aiohttp import web

        loopback_bind = is_loopback_host(self.options.host)
        if loopback_bind and not is_loopback_host(request.url.host or ""):
            # Bound to loopback: a Host that is not loopback is a DNS-rebinding page.
            return web.Response(status=403, text="companion view: this view answers only to localhost\n")
        if not loopback_bind and not self._token_ok(request):
            return web.Response(
                status=401,
                text="companion view: this view needs its token: open the address `companion view` printed (…/?token=…)\n",
            )
        if request.method != "GET" or request.path == "/ws":
            if not self._same_origin(request):
                return web.Response(status=403, text="companion view: cross-origin request refused\n")
        response = await handler(request)
        if response.prepared:  # a WebSocket or a stream: its headers are gone already
            return response
        if not loopback_bind and request.query.get("token") and isinstance(response, web.Response):
            # For the page's later reads (its WebSocket, its images); commanding needs the header.
            response.set_cookie(_COOKIE, self.options.token, httponly=True, samesite="Strict", path="/")
        response.headers.setdefault("X-Content-Type-Options", "nosniff")
        response.headers.setdefault("Referrer-Policy", "no-referrer")
        response.headers.setdefault("Cache-Control", "no-store")
        return response

    @property
    def _guard(self) -> Any:
        from aiohttp import web

        @web.middleware
        async def guard(request: Any, handler: Any) -> Any:
            return await self._guard_impl(request, handler)

        return guard

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
            "timeline": list(self.timeline),
            "thresholds": self.thresholds,
            "health": self.health,
            "view": self._view_status(),
        }

    async def _ws(self, request: Any) -> Any:
        from aiohttp import WSMsgType, web

        ws = web.WebSocketResponse(heartbeat=10.0, max_msg_size=4096)
        await ws.prepare(request)
        client = _Client()
        await ws.send_str(json.dumps(self._hello()))
        client.jpeg = self.jpeg
        client.wake.set()
        self._clients.add(client)

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
            self._clients.discard(client)
            task.cancel()
            try:
                await task
            except (asyncio.CancelledError, ConnectionError, RuntimeError):
                pass
        return ws

    async def _api_health(self, request: Any) -> Any:
        from aiohttp import web

        return web.json_response({"health": self.health, "view": self._view_status(), "thresholds": self.thresholds})

    async def _api_timeline(self, request: Any) -> Any:
        from aiohttp import web

        return web.json_response({"timeline_s": TIMELINE_S, "timeline": list(self.timeline)})

    async def _preview_jpg(self, request: Any) -> Any:
        from aiohttp import web

        if self.jpeg is None:
            raise web.HTTPNotFound(text="no preview yet\n")
        return web.Response(body=self.jpeg, content_type="image/jpeg")

    async def _mjpeg(self, request: Any) -> Any:
        from aiohttp import web

        response = web.StreamResponse(headers={"Content-Type": "multipart/x-mixed-replace; boundary=frame"})
        await response.prepare(request)
        while True:
            assert self._mjpeg_wake is not None
            jpeg = self.jpeg
            if jpeg is not None:
                await response.write(
                    b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
                    + str(len(jpeg)).encode()
                    + b"\r\n\r\n"
                    + jpeg
                    + b"\r\n"
                )
            await self._mjpeg_wake.wait()

    async def _api_control(self, request: Any) -> Any:
        from aiohttp import web

        if request.headers.get("X-Companion-View") != "1":
            return web.json_response({"ok": False, "error": {"type": "Forbidden", "message": "not from the view's page"}}, status=403)
        if self.options.control_endpoint is None:
            return web.json_response(
                {"ok": False, "error": {"type": "ReadOnly", "message": "this view has no control socket (read-only or a simulation)"}},
                status=409,
            )
        if not self._bearer_ok(request):
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
            reply = await self._control({"cmd": cmd})
        except Exception as err:  # no reply (service gone, CURVE refused): say so on the page
            return web.json_response({"ok": False, "cmd": cmd, "error": {"type": type(err).__name__, "message": str(err)}}, status=504)
        return web.json_response(reply)


def _display_hosts(host: str) -> list[str]:
    """The addresses to print for ``host``: itself, or this machine's IPv4 addresses for a wildcard."""
    if host not in ("0.0.0.0", "::", ""):
        return [host]
    found: list[str] = []
    ip = shutil.which("ip")
    if ip is not None:
        try:
            out = subprocess.run([ip, "-4", "-o", "addr", "show"], capture_output=True, text=True, timeout=2.0).stdout
            for line in out.splitlines():
                parts = line.split()
                if "inet" in parts:
                    addr = parts[parts.index("inet") + 1].split("/")[0]
                    if not addr.startswith("127."):
                        found.append(addr)
        except (OSError, subprocess.SubprocessError):
            pass
    if not found:
        try:
            found = sorted({a[4][0] for a in socket.getaddrinfo(socket.gethostname(), None, socket.AF_INET)} - {"127.0.0.1"})
        except OSError:
            pass
    return found or ["127.0.0.1"]


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
