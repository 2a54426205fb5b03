"""Ctrl-C while Numba compiles.

Numba's compiler calls back into Python through ctypes (llvmlite's object cache); a
``KeyboardInterrupt`` raised inside such a callback is printed as "Exception ignored" and dropped. A
Ctrl-C in the seconds a kernel compiles on the main thread (``companion sim``, ``companion demo``
before their first frame) was lost that way, and the command flew on. :func:`interrupt_after` holds
SIGINT for the length of a compile and delivers it once the compile is over.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType


@contextmanager
def interrupt_after() -> Iterator[None]:
    """Within the block, a SIGINT is recorded rather than handled; as the block ends without an error,
    the handler that was installed before it gets it (Python's default raises ``KeyboardInterrupt``
    there, where nothing swallows it). Off the main thread, where Python runs no signal handler, and
    where SIGINT has no Python handler (ignored, or the system's default), the block runs as it is."""
    old = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or not callable(old):
        yield
        return
    caught: list[int] = []

    def record(signum: int, frame: FrameType | None) -> None:
        caught.append(signum)

    signal.signal(signal.SIGINT, record)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
    if caught:
        old(signal.SIGINT, None)
