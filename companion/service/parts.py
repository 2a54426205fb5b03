"""The daemon's parts: each owns its state and has ``start()`` and ``stop(budget_s)``.

:class:`TaskPart` is a part that is one asyncio task (a loop of its own): :meth:`TaskPart.start`
creates it, :meth:`TaskPart.stop` cancels it and waits at most its budget (a task that does not stop is
logged and left, never waited for without limit). A task that dies with an error is reported to
``on_died`` (the daemon then stops cleanly); cancellation is not a death.

:class:`Parts` is what the daemon's lifecycle keeps of them: the started parts in order, stopped in
reverse within one total budget (the way an exit stack unwinds). :class:`LastError` is the one fault
every part may report (health's ``last_error``).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from typing import Any, Protocol

from companion.errors import CompanionError

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

    @property
    def running(self) -> bool:
        """Whether the task was started and has not ended."""
        return self.task is not None and not self.task.done()

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


class StartupError(CompanionError):
    """The service could not start; the process exits with STARTUP_FAILURE (78)."""


class LastError:
    """Health's ``last_error``: the newest fault a part reported, in one line.

    ``kind`` "config" marks a rejected config change: a good change clears it (:meth:`clear`), a fault
    stays until the next one.
    """

    def __init__(self) -> None:
        self.message: str | None = None
        self.kind: str | None = None

    def record(self, message: str, kind: str = "fault") -> None:
        self.message = message
        self.kind = kind

    def clear(self, kind: str) -> None:
        """Forget the message when it is of ``kind``."""
        if self.kind == kind:
            self.message = None
            self.kind = None


def call_on_loop(loop: asyncio.AbstractEventLoop | None, fn: Callable[..., None], *args: Any) -> None:
    """From another thread: run ``fn(*args)`` on ``loop`` (dropped once the loop is gone)."""
    if loop is None or loop.is_closed():
        return
    try:
        loop.call_soon_threadsafe(fn, *args)
    except RuntimeError:
        pass  # the loop closed between the check and the call: we are shutting down


async def stop_in_thread(what: str, fn: Callable[[float], Any], budget_s: float) -> bool:
    """Run ``fn(timeout_s)`` (a thread's blocking stop) in the loop's executor and wait at most
    ``budget_s``; ``fn`` gets half of it for its own join. False (logged) when it did not finish."""
    loop = asyncio.get_running_loop()
    try:
        await asyncio.wait_for(asyncio.shield(loop.run_in_executor(None, fn, budget_s / 2.0)), budget_s)
        return True
    except asyncio.TimeoutError:
        log.error("%s did not finish within its %.1f s; leaving it", what, budget_s)
        return False


class Parts:
    """The started parts, in the order they started; :meth:`stop_all` stops them in reverse.

    Each part gets its ``stop_budget_s`` (default ``step_s``), never more than what is left of the
    total; a part whose stop fails is logged and the next one still stops.
    """

    def __init__(self) -> None:
        self._started: list[Part] = []

    def started(self, part: Part) -> None:
        self._started.append(part)

    @property
    def names(self) -> list[str]:
        return [p.name for p in self._started]

    async def stop_all(self, total_s: float, step_s: float) -> None:
        deadline = time.monotonic() + total_s
        while self._started:
            part = self._started.pop()
            own_s = getattr(part, "stop_budget_s", step_s)
            budget_s = max(0.05, min(own_s, deadline - time.monotonic()))
            try:
                await part.stop(budget_s)
            except Exception:
                log.exception("stopping %s failed", part.name)
