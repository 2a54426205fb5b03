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


def _flood(endpoint: str, stop: Any, counts: Any) -> None:
    """In the flooding process: flood ``endpoint`` until ``stop`` is set; ``counts`` gets what was sent."""
    import zmq

    ctx = zmq.Context()
    sent = {"status": 0, "oversize": 0}
    try:
        dealers = []
        for _ in range(FLOOD_CONNECTIONS):
            s = ctx.socket(zmq.DEALER)
            s.setsockopt(zmq.LINGER, 0)
            s.setsockopt(zmq.SNDHWM, 2000)
            s.connect(endpoint)
            dealers.append(s)
        request = json.dumps({"cmd": "status"}).encode()
        big = b'{"cmd":"ping","pad":"' + b"x" * OVERSIZE_BYTES + b'"}'
        next_big = time.monotonic()
        while not stop.is_set():
            for s in dealers:
                try:
                    s.send(request, zmq.NOBLOCK)
                    sent["status"] += 1
                except zmq.Again:
                    pass
            if time.monotonic() >= next_big:
                next_big += 1.0
                s = ctx.socket(zmq.DEALER)  # a new connection each time: the relay cuts the one that sends it
                s.setsockopt(zmq.LINGER, 0)
                s.connect(endpoint)
                s.send(big, copy=False)
                dealers.append(s)
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
