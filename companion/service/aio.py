"""Small asyncio helpers shared by the shell's MAVSDK users (the service's vehicle link, the SITL pilot)."""

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
