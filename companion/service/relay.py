"""The control socket's front door: bounds each whole message before ZeroMQ buffers it.

ZeroMQ bounds a frame (``MAXMSGSIZE``) and a queue of whole messages (the high-water marks), but not a
message still arriving: it keeps every frame of a multipart message until the last one, without limit.
One client sending a single message of thousands of frames, each under the frame limit, could take
hundreds of megabytes. So clients do not reach the control ROUTER directly: they connect to this relay,
which listens on the configured endpoint (the same ``ipc://`` file with its mode, or the same TCP port),
reads ZeroMQ's wire protocol (ZMTP 3) from each client, and passes it on to the ROUTER, bound on a
private socket of its own, one connection for each client.

From a client it passes the greeting, then one frame at a time: a frame larger than
:attr:`RelayLimits.max_frame_bytes`, a message of more frames than
:attr:`RelayLimits.max_message_frames` or more bytes than :attr:`RelayLimits.max_message_bytes`, and
more connections than :attr:`RelayLimits.max_connections` are cut, with a logged reason. What it holds
for a connection is one frame at most. Replies pass back unread.

With CURVE, a message's frames travel encrypted one by one and where a message ends is not visible on
the wire; there the relay bounds each frame and the connection's bytes per second
(:attr:`RelayLimits.curve_bytes_per_s`), and only the listed clients get in at all.
"""

from __future__ import annotations

import asyncio
import logging
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

_GREETING_BYTES = 64
_SIGNATURE_BYTES = 10
_MORE, _LONG, _COMMAND = 0x01, 0x02, 0x04
_COPY_BYTES = 65536
#: A client that has not sent its greeting by then is cut (ZeroMQ's own handshake timeout), seconds.
HANDSHAKE_TIMEOUT_S = 2.0
#: The relay thread's niceness above the process's (Linux).
_NICENESS = 5
#: Connections waiting to be accepted (a burst of connections must not be refused by the kernel).
_BACKLOG = 1024


@dataclass(frozen=True)
class RelayLimits:
    """What one control connection may send.

    Attributes:
        max_frame_bytes: one frame's body, bytes.
        max_message_frames: frames of one message (a REQ client sends 2, a DEALER 1).
        max_message_bytes: all frames of one message, bytes.
        max_connections: clients at once; a further one is cut at once.
        curve_bytes_per_s: with CURVE, bytes a connection may send per second (a burst of as many).
    """

    max_frame_bytes: int
    max_message_frames: int
    max_message_bytes: int
    max_connections: int
    curve_bytes_per_s: float


class _Cut(Exception):
    """A client broke a bound: its connection is closed (the message names the bound)."""


def parse_endpoint(endpoint: str) -> tuple[str, Any]:
    """(family, address) of a ``ipc://`` or ``tcp://`` endpoint to listen on: ``("unix", path)``
    (an abstract ``@name`` as ``"\\0name"``) or ``("tcp", (host, port))`` (``*`` = any)."""
    if endpoint.startswith("ipc://"):
        path = endpoint.removeprefix("ipc://")
        return "unix", "\0" + path[1:] if path.startswith("@") else path
    if endpoint.startswith("tcp://"):
        host, _, port = endpoint.removeprefix("tcp://").rpartition(":")
        host = host.strip("[]")
        return "tcp", ("" if host in ("*", "0.0.0.0") else host, 0 if port == "*" else int(port))
    raise ValueError(f"{endpoint!r}: the control relay serves ipc:// and tcp:// endpoints only")


class ControlRelay:
    """Listens on ``endpoint`` in a thread of its own and relays each client to ``target`` (the
    ROUTER's private ``ipc://`` endpoint). :meth:`start` binds (raises OSError when it cannot);
    :attr:`endpoint` is then what clients connect to (a TCP port 0 resolved); :meth:`stop` ends it.
    """

    def __init__(self, endpoint: str, target: str, limits: RelayLimits) -> None:
        self._family, self._address = parse_endpoint(endpoint)
        self._target = target.removeprefix("ipc://")
        self.limits = limits
        self.endpoint = endpoint
        self.connections = 0
        self.cut = 0  # connections cut for breaking a bound
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: asyncio.base_events.Server | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._writers: set[asyncio.StreamWriter] = set()

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="control relay", daemon=True)
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            self._thread.join()
            raise self._error

    def stop(self, timeout_s: float = 1.0) -> None:
        """Close the listener and every connection; wait at most ``timeout_s`` for the thread."""
        loop = self._loop
        if loop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self._shutdown)
            except RuntimeError:
                pass  # the loop closed between the check and the call
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.error("the control relay's thread did not stop within %.1f s", timeout_s)
        if self._family == "unix" and not self._address.startswith("\0"):
            try:
                os.unlink(self._address)
            except FileNotFoundError:
                pass

    # ------------------------------------------------------------------ the thread

    def _run(self) -> None:
        try:
            # Under load the flight loop's threads come first (as for the control server's thread).
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), os.getpriority(os.PRIO_PROCESS, 0) + _NICENESS)
        except (AttributeError, OSError) as err:  # not Linux, or not allowed: the bounds still hold
            log.debug("control relay niceness unchanged: %s", err)
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._listen())
        except BaseException as err:  # handed to start(), which raises it in the caller
            self._error = err
            self._ready.set()
            loop.close()
            return
        self._ready.set()
        try:
            loop.run_forever()
        finally:
            loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()

    async def _listen(self) -> None:
        if self._family == "unix":
            self._server = await asyncio.start_unix_server(self._serve, path=self._address, backlog=_BACKLOG)
        else:
            host, port = self._address
            self._server = await asyncio.start_server(
                self._serve, host=host or None, port=port, reuse_address=True, backlog=_BACKLOG
            )
            bound = self._server.sockets[0].getsockname()
            shown = f"[{bound[0]}]" if ":" in bound[0] else bound[0]
            host_text = "*" if not host else shown
            self.endpoint = f"tcp://{host_text}:{bound[1]}"

    def _shutdown(self) -> None:
        if self._server is not None:
            self._server.close()
        for writer in list(self._writers):
            writer.transport.abort()
        assert self._loop is not None
        self._loop.call_later(0.05, self._loop.stop)

    async def _serve(self, client_r: asyncio.StreamReader, client_w: asyncio.StreamWriter) -> None:
        if self.connections >= self.limits.max_connections:
            self.cut += 1
            log.warning("control connection refused: %d connections already (bus.max_connections)", self.connections)
            client_w.transport.abort()
            return
        self.connections += 1
        self._writers.add(client_w)
        router_w: asyncio.StreamWriter | None = None
        try:
            try:
                # The ROUTER is reached only once the client has said it speaks ZeroMQ: a flood of raw
                # connections costs an accept and a timer each.
                async with asyncio.timeout(HANDSHAKE_TIMEOUT_S):
                    signature = await client_r.readexactly(_SIGNATURE_BYTES)
            except (TimeoutError, asyncio.IncompleteReadError, ConnectionError):
                return
            if signature[0] != 0xFF or signature[9] != 0x7F:
                self.cut += 1
                log.debug("control connection cut: not a ZeroMQ (ZMTP 3) client")
                return
            try:
                router_r, router_w = await asyncio.open_unix_connection(self._target)
            except OSError as err:
                log.error("control relay: cannot reach the control socket: %s", err)
                return
            self._writers.add(router_w)
            up = asyncio.ensure_future(self._upstream(client_r, router_w, signature))
            down = asyncio.ensure_future(self._copy(router_r, client_w))
            done, pending = await asyncio.wait({up, down}, return_when=asyncio.FIRST_COMPLETED)
            for task in pending:
                task.cancel()
            for task in done:
                err = task.exception()
                if isinstance(err, _Cut):
                    self.cut += 1
                    log.warning("control connection cut: %s", err)
                elif isinstance(err, TimeoutError):
                    self.cut += 1
                    log.debug("control connection cut: no ZeroMQ greeting within %.0f s", HANDSHAKE_TIMEOUT_S)
                elif err is not None and not isinstance(err, (ConnectionError, asyncio.IncompleteReadError)):
                    log.error("control relay: %s", err, exc_info=err)
            await asyncio.gather(*pending, return_exceptions=True)
        finally:
            self.connections -= 1
            for writer in (client_w, router_w):
                if writer is not None:
                    self._writers.discard(writer)
                    writer.transport.abort()

    async def _copy(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while True:
            data = await reader.read(_COPY_BYTES)
            if not data:
                return
            writer.write(data)
            await writer.drain()

    async def _upstream(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, signature: bytes) -> None:
        """Client -> ROUTER: the greeting, then the frames, read in chunks and passed on once every frame
        header in the chunk is within the bounds (raises _Cut). Only the headers are looked at, so a
        flood of small requests costs little more than copying it."""
        lim = self.limits
        async with asyncio.timeout(HANDSHAKE_TIMEOUT_S):  # as ZeroMQ closes a silent connection
            writer.write(signature)
            await writer.drain()  # the server answers the signature before the client sends the rest
            rest = await reader.readexactly(_GREETING_BYTES - _SIGNATURE_BYTES)
        if rest[0] < 3:
            raise _Cut(f"ZMTP version {rest[0]}.{rest[1]} (3 or later needed)")
        curve = rest[2:22].rstrip(b"\0") == b"CURVE"
        writer.write(rest)
        await writer.drain()
        loop = asyncio.get_running_loop()
        frames = message_bytes = body_left = 0
        head = bytearray()
        tokens, t_s = lim.curve_bytes_per_s, loop.time()
        while True:
            data = await reader.read(_COPY_BYTES)
            if not data:
                return
            pos, n = 0, len(data)
            while pos < n:
                if body_left:
                    take = min(body_left, n - pos)
                    pos += take
                    body_left -= take
                    continue
                head.append(data[pos])
                pos += 1
                flags = head[0]
                need = 9 if flags & _LONG else 2
                if len(head) < need:
                    continue
                size = int.from_bytes(head[1:need], "big")
                head.clear()
                if size > lim.max_frame_bytes:
                    raise _Cut(f"a frame of {size} bytes (at most {lim.max_frame_bytes})")
                if curve:
                    now = loop.time()
                    tokens = min(lim.curve_bytes_per_s, tokens + (now - t_s) * lim.curve_bytes_per_s) - size
                    t_s = now
                    if tokens < -lim.curve_bytes_per_s:
                        raise _Cut(f"more than {lim.curve_bytes_per_s:.0f} bytes per second")
                elif not flags & _COMMAND:
                    frames += 1
                    message_bytes += size
                    if frames > lim.max_message_frames:
                        raise _Cut(f"a message of more than {lim.max_message_frames} frames")
                    if message_bytes > lim.max_message_bytes:
                        raise _Cut(f"a message of more than {lim.max_message_bytes} bytes")
                    if not flags & _MORE:
                        frames = message_bytes = 0
                body_left = size
            writer.write(data)
            await writer.drain()


def private_endpoint(folder: Path) -> str:
    """The ROUTER's own ``ipc://`` endpoint inside ``folder`` (a private folder, mode 0700)."""
    return f"ipc://{folder / 'router.sock'}"
