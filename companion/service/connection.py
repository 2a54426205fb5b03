"""The daemon's vehicle part: the vehicle link and the task that waits for the autopilot.

:class:`VehicleConnection` owns the link (MAVSDK on ``vehicle.connection`` unless one is given): it
opens it at start (a bad URL fails the start), waits for the autopilot in its own task (saying "still
waiting" less and less often) and closes the link at stop, within its budget. Its state for health is
:meth:`VehicleConnection.link_status`.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

from companion.config import CompanionConfig
from companion.errors import VehicleError
from companion.interfaces import VehicleLink
from companion.service.backoff import LogBackoff
from companion.service.parts import StartupError, TaskPart

log = logging.getLogger(__name__)


class VehicleConnection(TaskPart):
    """The vehicle part: the link, and one task that connects it.

    Args:
        link: the vehicle link, or None for MAVSDK on ``vehicle.connection``.
        config: the config in force (read at each use: live changes apply).
        clock: monotonic seconds.
        on_error: records a one-line fault (health's ``last_error``).
        on_fatal: called with the reason when the connection can never succeed (a bad address): the
            service stops with STARTUP_FAILURE.
        on_connected: called once the autopilot is connected (health publishes at once).
        on_died: see :class:`~companion.service.parts.TaskPart`.
    """

    name = "vehicle connector"

    def __init__(
        self,
        link: VehicleLink | None,
        *,
        config: Callable[[], CompanionConfig],
        clock: Callable[[], float],
        on_error: Callable[[str], None],
        on_fatal: Callable[[str], None],
        on_connected: Callable[[], None],
        on_died: Callable[[str, BaseException], None] | None = None,
    ) -> None:
        super().__init__(on_died)
        self.link: Any = link
        self._config = config
        self._clock = clock
        self._on_error = on_error
        self._on_fatal = on_fatal
        self._on_connected = on_connected
        self.status = "connecting"  # connecting / waiting / connected

    async def open(self) -> None:
        """Make the link (unless given) and add its connection now.

        Raises:
            StartupError: the connection cannot be added (a bad URL).
        """
        if self.link is None:
            from companion.service.vehicle import make_vehicle_link

            self.link = make_vehicle_link(self._config().vehicle, clock=self._clock)
        opener = getattr(self.link, "open", None)  # MAVSDK: add the connection now, fail fast on a bad URL
        if opener is not None:
            try:
                await opener()
            except VehicleError as err:
                raise StartupError(str(err)) from None

    async def run(self) -> None:
        assert self.link is not None
        timeout_s = self._config().vehicle.connect_timeout_s
        # "still waiting": the first at once, then less and less often (up to every 10 min).
        backoff = LogBackoff(first_interval_s=timeout_s, max_interval_s=max(timeout_s, 600.0))
        while True:
            try:
                await self.link.connect(timeout_s)
            except VehicleError as err:
                if err.context.get("kind") == "connection":
                    self._on_error(str(err))
                    self._on_fatal(str(err))
                    return
                self.status = "waiting"
                now = self._clock()
                if backoff.due(now):
                    log.warning("%s; still waiting (%.0f s so far; next report in %.0f s)",
                                err, backoff.elapsed_s(now) + timeout_s, backoff.interval_s)
                else:
                    log.debug("%s; still waiting", err)
                continue
            self.status = "connected"
            self._on_connected()
            return

    def connected(self) -> bool:
        """Whether the autopilot is connected now (the link has heard it and says so)."""
        return self.link is not None and self.status == "connected" and self.link.state().connected

    def link_status(self, state: Any) -> str:
        """Health's ``vehicle.link`` for the link's ``state`` now: connecting, waiting, connected or lost."""
        if state is not None and self.status == "connected":
            return "connected" if state.connected else "lost"
        return self.status

    async def stop(self, budget_s: float) -> bool:
        """Stop waiting, then close the link (MAVSDK's calls run in threads; one that blocks must not
        hold the exit)."""
        stopped = await super().stop(budget_s)
        if self.link is not None:
            try:
                await asyncio.wait_for(self.link.close(), budget_s)
            except asyncio.TimeoutError:
                log.error("the vehicle link did not close within %.1f s; leaving it", budget_s)
                return False
            except Exception:
                log.exception("closing the vehicle link failed")
        return stopped
