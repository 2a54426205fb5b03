"""Small asyncio helpers shared by the shell (the service's loops, its vehicle link, the SITL pilot)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Iterable


async def logged(coro: Awaitable[object], what: str, logger: logging.Logger) -> None:
    """Await ``coro``; an exception from it is logged (with its traceback) as "``what`` failed" and
    not raised, so one failing subscription does not take its owner down. Cancellation passes."""
    try:
        await coro
    except asyncio.CancelledError:
        raise
    except Exception:
        logger.exception("%s failed", what)


async def cancel_and_wait(tasks: Iterable[asyncio.Task]) -> None:
    """Cancel ``tasks`` and wait until each has finished."""
    tasks = list(tasks)
    for task in tasks:
        task.cancel()
    for task in tasks:
        try:
            await task
        except asyncio.CancelledError:
            pass


async def wait_event(event: asyncio.Event, timeout_s: float) -> None:
    """Wait until ``event`` is set or ``timeout_s`` passed (then the event is set by the timer: the
    callers re-check their own conditions).

    Not ``asyncio.wait_for``: before Python 3.12 it can swallow a cancellation that arrives as the
    awaited event fires, and a loop task that ignores its cancellation hangs the shutdown.
    """
    if event.is_set():
        return
    timer = asyncio.get_running_loop().call_later(max(0.0, timeout_s), event.set)
    try:
        await event.wait()
    finally:
        timer.cancel()
