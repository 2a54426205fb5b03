"""The control server: the ZeroMQ ROUTER socket's own thread, its budgets and its replies.

:class:`ControlServer` owns the control socket in a thread of its own, so that no client, however many
messages it sends or however slowly it reads, can stall the flight loop (setpoints, the watchdog,
signals). It enforces the budgets (per connection and in total, requests per second), bounds the
requests in progress, parses and validates each request, answers ``ping`` and ``get_config`` itself
from immutable snapshots, and hands everything else to the flight loop one request per task, bounded
(:class:`~companion.service.control.ControlPlane` carries them out there).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import math
import os
import queue
import threading
import time
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from typing import Any

import zmq

from companion.config import BusConfig
from companion.errors import CompanionError, ProtocolError
from companion.service import protocol

log = logging.getLogger(__name__)

#: Requests carried out on the flight loop at once; a further one gets a "Busy" reply at once.
MAX_IN_FLIGHT = 8
#: Messages read from the socket per turn of the server's loop (then replies are sent, events read).
_RECV_BATCH = 64
#: After a full batch (more messages are waiting: a flood), the thread sleeps this long, seconds. It
#: bounds the share of the CPU and of the interpreter lock that clients can take from the flight loop
#: (at most ~13 000 messages a second); what waits meanwhile stays in ZeroMQ's small per-connection
#: queues, and a client that keeps flooding loses its surplus there.
_FLOOD_PAUSE_S = 0.005
#: The control thread's niceness above the process's (Linux): under load the flight loop's threads
#: come first.
_NICENESS = 5
#: Connections whose budgets are remembered; beyond this the idle ones are forgotten.
_MAX_TRACKED_PEERS = 1024
#: Requests that stop the vehicle: never refused by a request budget (one client's flood must not keep
#: another from stopping it), and they have places in progress of their own beyond :data:`MAX_IN_FLIGHT`.
STOP_COMMANDS = frozenset({"disengage", "pause"})
#: A stop request is at most this long (a longer message is not looked at before the budgets).
_MAX_STOP_BYTES = 256
#: A connection's request rate is averaged over about this long, seconds; one that sent within it is
#: active (it shares the budget of all).
_RATE_WINDOW_S = 1.0
#: The active connections are counted again at most this often, seconds (a count is O(connections)).
_RECOUNT_S = 0.1

@dataclass
class _Bucket:
    """A token bucket: ``tokens`` (requests) at ``t_s``, refilled at ``rate`` per second up to ``rate``."""

    tokens: float
    t_s: float

    def take(self, now_s: float, rate: float) -> bool:
        self.tokens = min(rate, self.tokens + (now_s - self.t_s) * rate)
        self.t_s = now_s
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True


@dataclass
class _Peer:
    """One connection: its budget (its bucket's ``t_s`` is when it last sent), and the rate at which
    it sends requests, refused ones too."""

    bucket: _Bucket
    rate_per_s: float = 0.0  # requests per second, averaged over about _RATE_WINDOW_S, at bucket.t_s

    def take(self, now_s: float, rate: float) -> bool:
        """Count one request at ``now_s`` in the rate, and take it from the budget (``rate`` per
        second); whether the budget had it."""
        self.rate_per_s = self.rate_per_s * math.exp(-(now_s - self.bucket.t_s) / _RATE_WINDOW_S) + 1.0 / _RATE_WINDOW_S
        return self.bucket.take(now_s, rate)


@dataclass
class ControlStats:
    """What the control server has seen (health's ``control``)."""

    received: int = 0
    rate_limited: int = 0
    busy: int = 0
    bad: int = 0
    replies_dropped: int = 0


def _envelope(frames: list[bytes]) -> tuple[list[bytes], list[bytes]] | None:
    """(the reply envelope, the payload frames) of one ROUTER message; None when it has no payload."""
    if len(frames) < 2:
        return None  # no identity and payload: nothing we could reply to
    identity, rest = frames[0], frames[1:]
    if len(rest) >= 2 and rest[0] == b"":
        return [identity, b""], rest[1:]  # REQ client
    return [identity], rest  # DEALER client


class ControlServer:
    """The control socket's own thread (see the module doc). Start with :meth:`start`, end with :meth:`stop`.

    Args:
        sock: the bound ROUTER socket; from :meth:`start` on only this thread uses it.
        cfg: the ``[bus]`` config (the budgets; a restart changes them).
        loop: the flight loop, where :meth:`ControlPlane.handle_request` runs.
        handle_local: answers the requests the thread gives itself, or returns None
            (:meth:`ControlPlane.handle_local`).
        handle: a request's coroutine on the flight loop (:meth:`ControlPlane.handle_request`).
        on_internal_error: called (from this thread) with a one-line message when a request failed
            with a bug.
        clock: monotonic seconds, for the budgets.
    """

    def __init__(
        self,
        sock: zmq.Socket,
        cfg: BusConfig,
        loop: asyncio.AbstractEventLoop,
        handle_local: Callable[[Any], dict[str, Any] | None],
        handle: Callable[[Any], Coroutine[Any, Any, dict[str, Any]]],
        on_internal_error: Callable[[str], None],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._sock = sock
        self._cfg = cfg
        self._loop = loop
        self._handle_local = handle_local
        self._handle = handle
        self._on_internal_error = on_internal_error
        self._clock = clock
        self._adapter = protocol.request_adapter()
        self._refusals = {
            "client": protocol.encode(
                protocol.error_reply(
                    None,
                    None,
                    "RateLimited",
                    f"more than bus.requests_per_s_per_client = {cfg.requests_per_s_per_client:g} requests "
                    "per second from this connection; not carried out",
                )
            ),
            "all": protocol.encode(
                protocol.error_reply(
                    None,
                    None,
                    "RateLimited",
                    f"more than bus.max_requests_per_s = {cfg.max_requests_per_s:g} requests per second "
                    "from all clients; not carried out",
                )
            ),
            "busy": protocol.encode(
                protocol.error_reply(
                    None, None, "Busy", f"{MAX_IN_FLIGHT} requests are in progress already; try again"
                )
            ),
        }
        self._done: queue.SimpleQueue[tuple[list[bytes], str, Any, concurrent.futures.Future]] = queue.SimpleQueue()
        self._pending: set[concurrent.futures.Future] = set()
        self._peers: dict[bytes, _Peer] = {}
        self._all = _Bucket(cfg.max_requests_per_s, clock())
        self._reserve = _Bucket(cfg.max_requests_per_s, clock())  # the light users' share (_admit)
        self._active = 1  # connections that sent within _RATE_WINDOW_S, counted at _counted_s
        self._counted_s = -math.inf
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="control server", daemon=True)
        self.stats = ControlStats()
        self.error: BaseException | None = None  # what ended the thread, if it died

    # ------------------------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """End the thread: requests in progress are cancelled (their clients get no reply)."""
        self._stop.set()
        self._wake()
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            log.error("the control server's thread did not stop within %.1f s", timeout_s)
        for fut in list(self._pending):
            fut.cancel()
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass  # closed already

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except (BlockingIOError, OSError):
            pass  # the pipe is full (the thread wakes anyway) or closed (it has stopped)

    # ------------------------------------------------------------------------------------ the thread

    def _run(self) -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), os.getpriority(os.PRIO_PROCESS, 0) + _NICENESS)
        except (AttributeError, OSError) as err:  # not Linux, or not allowed: the budgets still bound it
            log.debug("control thread niceness unchanged: %s", err)
        poller = zmq.Poller()
        poller.register(self._sock, zmq.POLLIN)
        poller.register(self._wake_r, zmq.POLLIN)
        try:
            while not self._stop.is_set():
                ready = dict(poller.poll(200))
                if self._wake_r in ready:
                    try:
                        os.read(self._wake_r, 4096)
                    except BlockingIOError:
                        pass
                self._send_done()
                if self._sock in ready and self._receive() == _RECV_BATCH:
                    time.sleep(_FLOOD_PAUSE_S)
        except Exception as err:  # a bug: the service notices (health) and stops cleanly
            self.error = err
            log.exception("the control server's thread failed")
            self._on_internal_error(f"control server: {type(err).__name__}: {err}")

    def _receive(self) -> int:
        """Read and handle up to :data:`_RECV_BATCH` messages; returns how many."""
        for n in range(_RECV_BATCH):
            try:
                frames = self._sock.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return n
            self.stats.received += 1
            split = _envelope(frames)
            if split is None:
                continue
            envelope, parts = split
            stop = len(parts) == 1 and self._is_stop(parts[0])
            refusal = self._admit(envelope[0], stop=stop)
            if refusal is not None:
                self._send(envelope, refusal)
                continue
            if len(parts) != 1:
                self.stats.bad += 1
                message = f"expected one JSON frame after the envelope, got {len(parts)} frames"
                self._reply(envelope, protocol.error_reply(None, None, "ProtocolError", message))
                continue
            self._dispatch(envelope, parts[0])
        return _RECV_BATCH

    def _admit(self, identity: bytes, now_s: float | None = None, stop: bool = False) -> bytes | None:
        """None when this connection, and all together, are within their request budgets; else the
        error reply, encoded (the same bytes for every refusal of a kind: a flood costs no JSON).

        Fair shares: when the budget of all connections is spent, a connection that sends at less than
        its fair share of it (the budget of all divided among the connections active in the last
        second) still gets in, from a reserve as large as that budget; the connections that send more
        are refused, and the total stays bounded at twice the budget. The rate counts every request a
        connection sent, refused ones too: a flood over many connections, each under its own budget,
        is still a flood, however slowly a loaded machine reads it. A ``stop`` request
        (:data:`STOP_COMMANDS`) is never refused by a budget, only when even its own places in
        progress are taken.
        """
        now_s = self._clock() if now_s is None else now_s
        per = self._cfg.requests_per_s_per_client
        total = self._cfg.max_requests_per_s
        peer = self._peers.get(identity)
        if peer is None:
            if len(self._peers) >= _MAX_TRACKED_PEERS:
                self._forget_idle(now_s)
            peer = self._peers[identity] = _Peer(_Bucket(per, now_s))
        within = peer.take(now_s, per)
        if stop:  # counted, never refused
            if len(self._pending) >= MAX_IN_FLIGHT + len(STOP_COMMANDS) * 2:
                self.stats.busy += 1
                return self._refusals["busy"]
            return None
        if not within:
            self.stats.rate_limited += 1
            return self._refusals["client"]
        if not self._all.take(now_s, total) and (
            peer.rate_per_s >= total / self._active_connections(now_s) or not self._reserve.take(now_s, total)
        ):
            self.stats.rate_limited += 1
            return self._refusals["all"]
        if len(self._pending) >= MAX_IN_FLIGHT:
            self.stats.busy += 1
            return self._refusals["busy"]
        return None

    def _active_connections(self, now_s: float) -> int:
        """Connections that sent within the last :data:`_RATE_WINDOW_S` (at least 1), counted again at
        most every :data:`_RECOUNT_S`."""
        if now_s - self._counted_s >= _RECOUNT_S:
            self._active = max(1, sum(1 for p in self._peers.values() if now_s - p.bucket.t_s < _RATE_WINDOW_S))
            self._counted_s = now_s
        return self._active

    def _is_stop(self, raw: bytes) -> bool:
        """Whether ``raw`` is a valid stop request (:data:`STOP_COMMANDS`); only a short message that
        names one is parsed here, so a flood of anything else costs no JSON."""
        if len(raw) > _MAX_STOP_BYTES or not any(cmd.encode() in raw for cmd in STOP_COMMANDS):
            return False
        try:
            return protocol.parse_request(raw, self._adapter, self._cfg.max_request_bytes).cmd in STOP_COMMANDS
        except ProtocolError:
            return False

    def _forget_idle(self, now_s: float) -> None:
        per = self._cfg.requests_per_s_per_client
        idle = [k for k, p in self._peers.items() if p.bucket.tokens + (now_s - p.bucket.t_s) * per >= per]
        for k in idle or list(self._peers)[: len(self._peers) // 2]:
            del self._peers[k]

    def _dispatch(self, envelope: list[bytes], raw: bytes) -> None:
        cmd = rid = None
        try:
            request = protocol.parse_request(raw, self._adapter, self._cfg.max_request_bytes)
            cmd, rid = request.cmd, request.id
            local = self._handle_local(request)
        except ProtocolError as err:
            self.stats.bad += 1
            cmd = cmd or err.context.get("cmd")
            rid = rid if rid is not None else err.context.get("id")
            log.info("bad request: %s", err)
            self._reply(envelope, protocol.error_reply(cmd, rid, "ProtocolError", str(err)))
            return
        except Exception as err:
            self._reply(envelope, self._internal_error(cmd, rid, err))
            return
        if local is not None:
            self._reply(envelope, protocol.ok_reply(cmd, rid, local))
            return
        fut = asyncio.run_coroutine_threadsafe(self._handle(request), self._loop)
        self._pending.add(fut)
        fut.add_done_callback(lambda f: (self._done.put((envelope, cmd, rid, f)), self._wake()))

    def _send_done(self) -> None:
        while True:
            try:
                envelope, cmd, rid, fut = self._done.get_nowait()
            except queue.Empty:
                return
            self._pending.discard(fut)
            if fut.cancelled():
                continue
            err = fut.exception()
            if err is None:
                message = protocol.ok_reply(cmd, rid, fut.result())
            elif isinstance(err, ProtocolError):
                log.info("bad request: %s", err)
                message = protocol.error_reply(cmd, rid, "ProtocolError", str(err))
            elif isinstance(err, CompanionError):
                log.info("%s request failed: %s", cmd, err)
                message = protocol.error_reply(cmd, rid, type(err).__name__, str(err))
            else:
                message = self._internal_error(cmd, rid, err)
            self._reply(envelope, message)

    def _internal_error(self, cmd: Any, rid: Any, err: BaseException) -> dict[str, Any]:
        log.error("request %s failed", cmd, exc_info=err)
        self._on_internal_error(f"internal error handling {cmd}: {type(err).__name__}: {err}")
        return protocol.error_reply(cmd, rid, "InternalError", f"{type(err).__name__}: {err}")

    def _reply(self, envelope: list[bytes], message: dict[str, Any]) -> None:
        self._send(envelope, protocol.encode(message))

    def _send(self, envelope: list[bytes], payload: bytes) -> None:
        try:
            self._sock.send_multipart(envelope + [payload], zmq.NOBLOCK)
        except zmq.ZMQError as err:  # the client went away, or does not read its replies: drop it
            self.stats.replies_dropped += 1
            log.debug("control reply not delivered: %s", err)
