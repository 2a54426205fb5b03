"""The daemon's parts: each owns its state and has ``start()`` and ``stop(budget_s)``.

:class:`TaskPart` is a part that is one asyncio task (a loop of its own): :meth:`TaskPart.start`
creates it, :meth:`TaskPart.stop` cancels it and waits at most its budget (a task that does not stop is
logged and left, never waited for without limit). A task that dies with an error is reported to
``on_died`` (the daemon then stops cleanly); cancellation is not a death.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Protocol

log = logging.getLogger(__name__)


class Part(Protocol):
    """What the daemon's lifecycle asks of each part."""

    name: str

    def start(self) -> None: ...

    async def stop(self, budget_s: float) -> bool: ...


class TaskPart:
    """A part that runs :meth:`run` as one task on the running loop.

    Args:
        name: the task's name (in logs).
        on_died: called with (name, error) when :meth:`run` raises (not when cancelled).
    """

    name = "part"

    def __init__(self, on_died: Callable[[str, BaseException], None] | None = None) -> None:
        self._on_died = on_died
        self.task: asyncio.Task | None = None

    async def run(self) -> None:
        raise NotImplementedError

    def start(self) -> None:
        """Start :meth:`run` on the running loop (call on the loop)."""
        self.task = asyncio.get_running_loop().create_task(self.run(), name=self.name)
        self.task.add_done_callback(self._done)

    async def stop(self, budget_s: float) -> bool:
        """Cancel the task and wait at most ``budget_s`` seconds; True when it stopped."""
        task, self.task = self.task, None
        if task is None or task.done():
            return True
        task.cancel()
        await asyncio.wait({task}, timeout=budget_s)
        if not task.done():
            log.error("task %s did not stop within %.1f s; leaving it", self.name, budget_s)
            return False
        return True

    def _done(self, task: asyncio.Task) -> None:
        if task.cancelled():
            return
        err = task.exception()
        if err is not None and self._on_died is not None:
            self._on_died(self.name, err)
