"""What ``companion view`` knows of the service it follows, and the pages it pushes it to.

The view subscribes to the service's health PUB socket and to its preview XPUB socket, exactly as
``companion watch`` does, and keeps the newest of each: the newest health message and a 60 s timeline
of them, the newest preview JPEG, the region bars' thresholds and the rig check's lines. Each page (a
WebSocket) gets the newest message of each kind when it is ready for it, never a backlog. Requests to
the service go through :class:`~companion.service.client.ControlClient` on its control socket.
"""

from __future__ import annotations

import asyncio
import collections
import json
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

from companion.view.options import ViewOptions

log = logging.getLogger(__name__)

#: How far back the page's timeline goes, seconds.
TIMELINE_S = 60.0


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
class Client:
    """One WebSocket: the newest health text and JPEG waiting for it (replaced, never queued)."""

    wake: asyncio.Event = field(default_factory=asyncio.Event)
    text: dict[str, str] = field(default_factory=dict)  # message type -> its newest text
    jpeg: bytes | None = None


class ServiceFeed:
    """The view's state (newest health, 60 s timeline, newest JPEG) and the pages that follow it.

    ``start()`` subscribes (in the running event loop), ``await stop()`` ends the subscriptions and
    ``close()`` drops the sockets.

    Attributes:
        clients: the pages (WebSockets) that follow the service.
        mjpeg_wake: set when a new JPEG arrives (and then replaced), for the MJPEG streams.
    """

    def __init__(self, options: ViewOptions) -> None:
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
        self.clients: set[Client] = set()
        self.mjpeg_wake: asyncio.Event | None = None
        self._ctx: Any = None
        self._tasks: list[asyncio.Task] = []

    def start(self) -> None:
        """Connect to the service's sockets and follow them."""
        import zmq
        import zmq.asyncio

        self.mjpeg_wake = asyncio.Event()
        self._ctx = zmq.asyncio.Context()
        health = self._socket(zmq.SUB, self.options.health_endpoint, b"")
        self._tasks.append(asyncio.create_task(self._follow_health(health), name="view health"))
        if self.options.preview_endpoint:
            preview = self._socket(zmq.SUB, self.options.preview_endpoint, b"preview")
            self._tasks.append(asyncio.create_task(self._follow_preview(preview), name="view preview"))
        self._tasks.append(asyncio.create_task(self._ticker(), name="view ticker"))

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
        """Stop following the service (the sockets stay until :meth:`close`)."""
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            try:
                await task
            except (asyncio.CancelledError, Exception):
                pass
        self._tasks = []

    def close(self) -> None:
        """Drop the sockets."""
        if self._ctx is not None:
            self._ctx.destroy(linger=0)
            self._ctx = None

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
            self.broadcast_text("health", json.dumps({"type": "health", "health": h, "view": self.view_status()}))

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
            for client in self.clients:
                client.jpeg = jpeg
                client.wake.set()
            assert self.mjpeg_wake is not None
            self.mjpeg_wake.set()
            self.mjpeg_wake = asyncio.Event()

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
                self.broadcast_text("thresholds", json.dumps({"type": "thresholds", **new}))
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
            reply = await self.control({"cmd": "get_config", "section": "controller"})
        except Exception as err:  # the thresholds are only a drawing aid
            log.debug("view: no thresholds from get_config: %s", err)
            return
        terms = ((reply.get("result") or {}).get("config") or {}).get("input_terms") or {}
        try:
            near, far = float(terms["near"]["params_m"][0]), float(terms["far"]["params_m"][-1])
        except (KeyError, IndexError, TypeError, ValueError):
            return
        self.thresholds = {"near_m": near, "far_m": far}
        self.broadcast_text("thresholds", json.dumps({"type": "thresholds", **self.thresholds}))

    async def _ticker(self) -> None:
        """Once a second: the view's own status (how old the newest health and picture are)."""
        while True:
            await asyncio.sleep(1.0)
            self.broadcast_text("tick", json.dumps({"type": "tick", "view": self.view_status()}))

    def view_status(self) -> dict[str, Any]:
        """The view's own status: how old the newest health and picture are, the preview's rate, the pages."""
        now = time.monotonic()
        recent = [t for t in self._preview_times if now - t <= 2.0]
        return {
            "health_age_s": None if self.health_at_s is None else now - self.health_at_s,
            "preview_age_s": None if self.preview_at_s is None else now - self.preview_at_s,
            "preview_fps": len(recent) / 2.0,
            "previews": self.previews,
            "preview_encode_ms": (self.preview_header or {}).get("encode_ms"),
            "clients": len(self.clients),
            "health_endpoint": self.options.health_endpoint,
            "rig_lines": self.rig_lines,
        }

    def broadcast_text(self, kind: str, text: str) -> None:
        """Queue ``text`` for every page; a newer message of the same kind replaces one not sent yet."""
        for client in self.clients:
            client.text.pop(kind, None)
            client.text[kind] = text
            client.wake.set()

    # ------------------------------------------------------------------ requests to the service

    async def control(self, request: dict[str, Any]) -> dict[str, Any]:
        """Send ``request`` on the service's control socket (in a thread); its reply."""
        from companion.service.client import ControlClient

        endpoint = self.options.control_endpoint
        assert endpoint is not None

        def call() -> dict[str, Any]:
            with ControlClient(endpoint, timeout_s=self.options.control_timeout_s, curve=self.options.curve) as client:
                return client.call(request)

        return await asyncio.to_thread(call)
