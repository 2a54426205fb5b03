"""``companion bench --soak --flood``: the soak with a local process flooding the control socket.

The flood is another process (as an attacker's or a buggy client's would be), at the service's priority:
20 DEALER connections that send ``status`` requests as fast as ZeroMQ takes them and never read a
reply, and every second a message far over the request bound. What it costs the flight path is the
soak's own figures (setpoints per second, the longest gap between two setpoints, latency), row by row;
the test suite only checks that the flight path keeps running through a flood and that ``disengage``
is still answered (tests/test_control_flood.py), never how regular it stays.
"""

from __future__ import annotations

import json
import multiprocessing
import time
from typing import Any

#: Connections of the flooding process.
FLOOD_CONNECTIONS = 20
#: The oversize message's body, bytes (far over ``bus.max_request_bytes``).
OVERSIZE_BYTES = 8 * 1024 * 1024


#: A ``status`` request, as the flood sends it.
STATUS_REQUEST = json.dumps({"cmd": "status"}).encode()


def oversize_request(body_bytes: int) -> bytes:
    """A ``ping`` padded to ``body_bytes`` (far over ``bus.max_request_bytes``)."""
    return b'{"cmd":"ping","pad":"' + b"x" * body_bytes + b'"}'


def status_dealers(ctx: Any, endpoint: str, n: int = FLOOD_CONNECTIONS) -> list[Any]:
    """``n`` DEALER sockets of ZeroMQ context ``ctx`` connected to ``endpoint``, each queueing up to
    2000 requests it never reads the replies of (linger 0)."""
    import zmq

    dealers = []
    for _ in range(n):
        s = ctx.socket(zmq.DEALER)
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.SNDHWM, 2000)
        s.connect(endpoint)
        dealers.append(s)
    return dealers


def send_round(dealers: list[Any], request: bytes) -> int:
    """One ``request`` on each of ``dealers`` that takes it without blocking; returns how many went."""
    import zmq

    n = 0
    for s in dealers:
        try:
            s.send(request, zmq.NOBLOCK)
            n += 1
        except zmq.Again:
            pass
    return n


def send_oversize(ctx: Any, endpoint: str, message: bytes) -> Any:
    """``message`` on a new DEALER connection (the relay cuts the one that sends it); returns the socket."""
    import zmq

    s = ctx.socket(zmq.DEALER)
    s.setsockopt(zmq.LINGER, 0)
    s.connect(endpoint)
    s.send(message, copy=False)
    return s


def _flood(endpoint: str, stop: Any, counts: Any) -> None:
    """In the flooding process: flood ``endpoint`` until ``stop`` is set; ``counts`` gets what was sent."""
    import zmq

    ctx = zmq.Context()
    sent = {"status": 0, "oversize": 0}
    try:
        dealers = status_dealers(ctx, endpoint)
        big = oversize_request(OVERSIZE_BYTES)
        next_big = time.monotonic()
        while not stop.is_set():
            sent["status"] += send_round(dealers, STATUS_REQUEST)
            if time.monotonic() >= next_big:
                next_big += 1.0
                dealers.append(send_oversize(ctx, endpoint, big))
                sent["oversize"] += 1
    finally:
        ctx.destroy(linger=0)
        counts.put(sent)


class Flood:
    """A process flooding a control endpoint from :meth:`start` to :meth:`stop`."""

    def __init__(self, endpoint: str) -> None:
        mp = multiprocessing.get_context("spawn")
        self._stop = mp.Event()
        self._counts = mp.Queue()
        self._proc = mp.Process(target=_flood, args=(endpoint, self._stop, self._counts), name="flood", daemon=True)

    def start(self) -> None:
        self._proc.start()

    def stop(self, timeout_s: float = 30.0) -> dict[str, int]:
        """Stop the flood; returns what it sent (empty when the process did not report)."""
        self._stop.set()
        try:
            counts = self._counts.get(timeout=timeout_s)
        except Exception:  # queue.Empty: the process died or is too slow; the figures say so
            counts = {}
        self._proc.join(timeout_s)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(5.0)
        return counts
