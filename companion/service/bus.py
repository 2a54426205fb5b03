"""ZeroMQ sockets of the control plane: health PUB and control ROUTER, each bounded, optionally CURVE-authenticated.

The health socket publishes one JSON object per message (subscribe to b""); publishing never blocks (a
slow subscriber loses old messages). The control socket is a ROUTER: a REQ client's message arrives as
[identity, b"", payload] and a DEALER's as [identity, payload]; the reply mirrors the envelope exactly.
It is read and written only by the control server's own thread (:class:`~companion.service.control.ControlServer`),
never by the flight loop.

What bounds a client: clients reach the control ROUTER through :class:`~companion.service.relay.ControlRelay`,
which listens on ``bus.control_endpoint`` and cuts a connection whose message has more than
:data:`MAX_MESSAGE_FRAMES` frames or more than twice ``bus.max_request_bytes`` in all, before ZeroMQ
buffers it (the ROUTER itself is bound on a private socket); in ZeroMQ itself, a frame larger than twice
``bus.max_request_bytes`` is cut off before it is buffered (``MAXMSGSIZE``); a connection queues at most :data:`QUEUE_MESSAGES` messages
each way; a connection that does not finish its handshake within :data:`HANDSHAKE_TIMEOUT_MS` is closed;
and more than ``bus.max_connections`` control connections are refused in the handshake (ZAP, the
:class:`Gatekeeper`). With ``bus.curve_server_secret_key_file`` and ``bus.curve_authorized_keys_dir``
both sockets are CURVE servers and only clients whose public certificate is in that folder get in.
``ipc://`` sockets are made mode 0660 (:func:`~companion.service.runtime.restrict_socket`).
"""

from __future__ import annotations

import asyncio
import logging
import shutil
import tempfile
import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import zmq
import zmq.auth
from zmq.auth.base import Authenticator
from zmq.utils.monitor import recv_monitor_message

from companion.config import BusConfig
from companion.errors import ConfigError
from companion.service.relay import ControlRelay, RelayLimits, private_endpoint
from companion.service.runtime import remove_socket, resolve_endpoint, restrict_socket, runtime_dir

log = logging.getLogger(__name__)

#: Messages queued per connection and direction (ZeroMQ's high-water marks): a client that floods or
#: never reads its replies fills its own small queue, and its further messages are dropped.
QUEUE_MESSAGES = 16
#: Health messages queued per subscriber before old ones are dropped.
HEALTH_QUEUE_MESSAGES = 100
#: A connection that has not completed the ZeroMQ handshake by then is closed (a raw TCP flood holds
#: its file descriptors no longer than this), milliseconds.
HANDSHAKE_TIMEOUT_MS = 2000
#: Connections the control relay holds at once at most (a flood of raw connections is cut after the
#: handshake timeout; the service raises its open-file limit to 65536).
RELAY_MAX_CONNECTIONS = 8192
#: Frames of one control message at most (a REQ client sends 2: the empty delimiter and the request).
MAX_MESSAGE_FRAMES = 4
#: The ZAP domains of the two sockets (the gatekeeper counts the control socket's connections).
CONTROL_DOMAIN = "companion-control"
HEALTH_DOMAIN = "companion-health"
#: How long closing the bus waits for the gatekeeper's thread, seconds.
STOP_TIMEOUT_S = 2.0


def load_server_keys(secret_file: Path) -> tuple[bytes, bytes]:
    """(public, secret) Z85 keys from a zmq.auth secret certificate.

    Raises:
        ConfigError: unreadable, or a public-only certificate.
    """
    try:
        public, secret = zmq.auth.load_certificate(str(secret_file))
    except (OSError, ValueError) as err:
        raise ConfigError(f"bus.curve_server_secret_key_file {secret_file}: cannot read it: {err}") from None
    if not secret:
        raise ConfigError(
            f"bus.curve_server_secret_key_file {secret_file}: has no secret key (use the .key_secret file)"
        )
    return public, secret


class Gatekeeper(Authenticator):
    """The ZAP handler of both sockets, in a thread of its own: CURVE (when configured), and a limit on
    the control socket's connections.

    The gatekeeper counts the control socket's connections itself, from the socket's monitor, and reads
    every event queued before it decides on a handshake. A connection's ``ACCEPTED`` event is queued
    before its handshake asks for a decision, so the count a decision reads is never behind: a burst of
    handshakes on a loaded machine cannot slip past the limit, as it could while another (lower
    priority) thread kept the count. The count includes the connection asking, so ``bus.max_connections``
    are let in and the next is refused.

    Lifecycle: :meth:`start` (the ZAP socket; handshakes wait), :meth:`watch` (count the control socket
    and start answering), :meth:`stop`.
    """

    def __init__(self, context: zmq.Context, max_connections: int) -> None:
        super().__init__(context)
        self.max_connections = max_connections
        self.live_connections = 0  # written by the gatekeeper's thread only
        self.refused = 0  # likewise
        self.error: BaseException | None = None  # what ended the thread, if it died
        #: Called from the gatekeeper's thread with what ended it, if it dies (see :attr:`error`).
        self.on_failure: Callable[[BaseException], None] | None = None
        self._monitor: zmq.Socket | None = None
        self._wake: zmq.Socket | None = None
        self._thread: threading.Thread | None = None

    def watch(self, control: zmq.Socket) -> None:
        """Count ``control``'s connections and start answering handshakes; call once, before a client
        can reach ``control``. The sockets pass to the gatekeeper's thread here (its start is the
        memory barrier ZeroMQ asks of a socket changing threads)."""
        assert self._thread is None and self.zap_socket is not None
        self._monitor = control.get_monitor_socket(zmq.EVENT_ACCEPTED | zmq.EVENT_DISCONNECTED)
        endpoint = f"inproc://companion-gatekeeper-{id(self)}"
        self._wake = self.context.socket(zmq.PAIR)
        self._wake.bind(endpoint)
        woken = self.context.socket(zmq.PAIR)
        woken.connect(endpoint)
        self._thread = threading.Thread(target=self._run, args=(woken,), name="gatekeeper", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """End the thread and close the gatekeeper's sockets (after the control socket is closed)."""
        if self._thread is not None:
            assert self._wake is not None
            if self._thread.is_alive():
                try:
                    self._wake.send(b"stop", zmq.NOBLOCK)
                except zmq.Again:
                    pass  # the thread's end of the pair is closed: it has ended already
            self._thread.join(STOP_TIMEOUT_S)
            if self._thread.is_alive():
                log.error("the gatekeeper's thread did not stop within %.1f s", STOP_TIMEOUT_S)
            self._thread = None
        for sock in (self._monitor, self._wake):
            if sock is not None:
                sock.close(linger=0)
        self._monitor = self._wake = None
        super().stop()

    def _run(self, woken: zmq.Socket) -> None:
        assert self._monitor is not None
        loop = asyncio.new_event_loop()  # the base class's ZAP handler is a coroutine
        poller = zmq.Poller()
        for sock in (woken, self.zap_socket, self._monitor):
            poller.register(sock, zmq.POLLIN)
        try:
            while True:
                ready = dict(poller.poll())
                if woken in ready:
                    return
                if self._monitor in ready:
                    self._count()
                if self.zap_socket in ready:
                    loop.run_until_complete(self._answer(self.zap_socket.recv_multipart()))
        except Exception as err:  # a bug: every handshake now waits unanswered, so say so loudly
            self.error = err
            log.exception("the gatekeeper's thread failed: no connection is let in any more")
            on_failure = self.on_failure
            if on_failure is not None:
                on_failure(err)
        finally:
            woken.close(linger=0)
            loop.close()

    def _count(self) -> None:
        assert self._monitor is not None
        while True:
            try:
                event = recv_monitor_message(self._monitor, zmq.NOBLOCK)
            except zmq.Again:
                return
            if event["event"] == zmq.EVENT_ACCEPTED:
                self.live_connections += 1
            elif event["event"] == zmq.EVENT_DISCONNECTED:
                self.live_connections = max(0, self.live_connections - 1)

    async def _answer(self, msg: list[bytes]) -> None:
        if len(msg) >= 6 and msg[2] == CONTROL_DOMAIN.encode():
            self._count()  # every connection accepted until now, the one asking included
            if self.live_connections > self.max_connections:
                self.refused += 1
                self._send_zap_reply(msg[1], b"400", b"too many connections")
                return
        await self.handle_zap_message(msg)


class Bus:
    """The two sockets, bound; :meth:`close` releases them (linger 0: nothing is held on exit).

    Args:
        cfg: the ``[bus]`` config.
        environ: the environment that resolves ``auto`` endpoints (the runtime directory).

    Raises (from :meth:`open`):
        ConfigError: an endpoint cannot be bound (in use, bad address) or the CURVE files are wrong.
    """

    def __init__(self, cfg: BusConfig, environ: Mapping[str, str] | None = None) -> None:
        self.cfg = cfg
        self._environ = environ
        self.ctx: zmq.Context | None = None
        self.health: zmq.Socket | None = None
        self.control: zmq.Socket | None = None
        self.gatekeeper: Gatekeeper | None = None
        self.health_endpoint = cfg.health_endpoint
        self.control_endpoint = cfg.control_endpoint
        self.relay: ControlRelay | None = None
        self._private_dir: Path | None = None
        self._publish_lock = threading.Lock()
        self._bound: list[str] = []  # the endpoints this bus bound (their socket files go on close)

    def open(self) -> None:
        self.ctx = zmq.Context()
        try:
            health_endpoint = resolve_endpoint(self.cfg.health_endpoint, "health", self._environ)
            control_endpoint = resolve_endpoint(self.cfg.control_endpoint, "control", self._environ)
            keys = None
            self.gatekeeper = Gatekeeper(self.ctx, self.cfg.max_connections)
            self.gatekeeper.start()
            if self.cfg.curve_enabled:
                assert self.cfg.curve_server_secret_key_file is not None
                assert self.cfg.curve_authorized_keys_dir is not None
                keys = load_server_keys(self.cfg.curve_server_secret_key_file)
                allowed = self.cfg.curve_authorized_keys_dir
                if not allowed.is_dir():
                    raise ConfigError(f"bus.curve_authorized_keys_dir {allowed}: not a folder")
                for domain in (CONTROL_DOMAIN, HEALTH_DOMAIN):  # pyzmq's "*" covers only an empty domain
                    self.gatekeeper.configure_curve(domain=domain, location=str(allowed))
            self.health = self._bind(zmq.PUB, health_endpoint, "bus.health_endpoint", keys, HEALTH_DOMAIN)
            self.health.setsockopt(zmq.SNDHWM, HEALTH_QUEUE_MESSAGES)  # a slow subscriber loses old health
            # The ROUTER on a socket of its own in a private folder; clients come through the relay.
            # The folder is in the runtime directory, which systemd removes when the service stops,
            # even killed (a folder in /tmp would outlive a killed service).
            self._private_dir = Path(tempfile.mkdtemp(prefix="control-", dir=runtime_dir(self._environ)))
            private = private_endpoint(self._private_dir)
            self.control = self._bind(zmq.ROUTER, private, "bus.control_endpoint", keys, CONTROL_DOMAIN)
            self.control.setsockopt(zmq.ROUTER_MANDATORY, 1)  # a reply to a gone client raises, never blocks
            self.control.setsockopt(zmq.SNDHWM, QUEUE_MESSAGES)
            self.control.setsockopt(zmq.RCVHWM, QUEUE_MESSAGES)
            self.gatekeeper.watch(self.control)  # before the relay: no client can reach the socket yet
            limits = RelayLimits(
                max_frame_bytes=2 * self.cfg.max_request_bytes,
                max_message_frames=MAX_MESSAGE_FRAMES,
                max_message_bytes=2 * self.cfg.max_request_bytes,
                # A backstop only (each takes two descriptors): the gatekeeper refuses ZeroMQ clients
                # beyond bus.max_connections in their handshake, and one that never speaks ZeroMQ is
                # cut after the handshake timeout, as ZeroMQ itself does.
                max_connections=RELAY_MAX_CONNECTIONS,
                curve_bytes_per_s=self.cfg.requests_per_s_per_client * 2 * self.cfg.max_request_bytes,
            )
            self.relay = ControlRelay(control_endpoint, private, limits)
            try:
                self.relay.start()
            except (OSError, ValueError) as err:
                self.relay = None
                raise ConfigError(f"bus.control_endpoint {control_endpoint!r}: cannot bind: {err}") from None
            # What the endpoints really are (a tcp port 0 is bound to an ephemeral port).
            self.health_endpoint = self.health.getsockopt_string(zmq.LAST_ENDPOINT)
            self.control_endpoint = self.relay.endpoint
            restrict_socket(self.health_endpoint)
            restrict_socket(self.control_endpoint)
        except BaseException:
            self.close()
            raise
        log.info(
            "health on %s, control on %s%s",
            self.health_endpoint,
            self.control_endpoint,
            " (CURVE)" if keys else "",
        )

    def _bind(
        self, kind: int, endpoint: str, field: str, keys: tuple[bytes, bytes] | None, domain: str
    ) -> zmq.Socket:
        assert self.ctx is not None
        sock = self.ctx.socket(kind)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.MAXMSGSIZE, 2 * self.cfg.max_request_bytes)
        sock.setsockopt(zmq.HANDSHAKE_IVL, HANDSHAKE_TIMEOUT_MS)
        sock.setsockopt_string(zmq.ZAP_DOMAIN, domain)
        if keys is not None:
            sock.curve_server = True
            sock.curve_publickey, sock.curve_secretkey = keys
        try:
            sock.bind(endpoint)
        except zmq.ZMQError as err:
            sock.close(linger=0)
            raise ConfigError(f"{field} {endpoint!r}: cannot bind: {err}") from None
        self._bound.append(sock.getsockopt_string(zmq.LAST_ENDPOINT))
        return sock

    def publish(self, payload: bytes) -> None:
        """Publish one health message; never blocks (a full queue drops it)."""
        with self._publish_lock:
            if self.health is None:
                return
            try:
                self.health.send(payload, flags=zmq.NOBLOCK)
            except zmq.Again:
                log.debug("health message dropped: subscribers are slow")

    def close(self) -> None:
        """Close both sockets and the context (the control server's thread must have stopped)."""
        if self.relay is not None:
            self.relay.stop()
            self.relay = None
        with self._publish_lock:
            for name in ("health", "control"):
                sock = getattr(self, name)
                if sock is not None:
                    sock.close(linger=0)
                    setattr(self, name, None)
        if self.gatekeeper is not None:
            self.gatekeeper.stop()
            self.gatekeeper = None
        if self.ctx is not None:
            self.ctx.destroy(linger=0)
            self.ctx = None
        for endpoint in self._bound:  # a file left behind would look like a running service to a client
            remove_socket(endpoint)
        self._bound = []
        if self._private_dir is not None:
            shutil.rmtree(self._private_dir, ignore_errors=True)
            self._private_dir = None

    def stats(self) -> dict[str, Any]:
        """The gatekeeper's counts, for health (control connections open or in their handshake, refused
        handshakes)."""
        g = self.gatekeeper
        return {"connections": g.live_connections if g else 0, "refused_connections": g.refused if g else 0}
