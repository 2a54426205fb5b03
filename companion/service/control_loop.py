"""The daemon's control loop part: the supervisor stepped at the setpoint rate, the setpoints sent, and
the systemd watchdog.

The loop never waits for the pipeline: it steps on a fixed grid (``vehicle.setpoint_rate_hz``)
whatever the vision rate, and also as soon as a new result or a request arrives (:meth:`ControlLoop.wake`),
so a decision reaches the vehicle without waiting for the next tick. Every change to the supervisor's
state happens on the loop. It is the ONLY place that feeds the systemd watchdog: if it stalls, systemd kills the
process (MAVSDK's re-sending dies with it) and the autopilot's offboard-loss failsafe takes over.

What health reads of it is :meth:`ControlLoop.counts` (the setpoints and their latencies).
"""

from __future__ import annotations

import asyncio
import collections
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from companion.config import CompanionConfig
from companion.core.supervisor import Action, ActionResult, State, Supervisor
from companion.core.types import ZERO_SETPOINT, VelocitySetpoint
from companion.errors import VehicleError
from companion.interfaces import VehicleState
from companion.service.aio import wait_event
from companion.service.capture import CaptureStatus
from companion.service.frames import Processed
from companion.service.parts import TaskPart

log = logging.getLogger(__name__)

#: Frame-to-setpoint latencies kept for health's median and p99.
_LATENCY_SAMPLES = 500


@dataclass(frozen=True)
class SetpointCounts:
    """The control loop's setpoints (health's ``setpoint`` and ``frame_to_setpoint_ms``).

    Attributes:
        last: the newest setpoint the link took, or None.
        last_s: when it was sent, monotonic seconds, or None.
        sent: setpoints the link took.
        latency_last_s: the newest frame-to-setpoint latency while engaged, seconds, or None.
        latencies_s: the recent ones (at most 500), seconds.
    """

    last: VelocitySetpoint | None
    last_s: float | None
    sent: int
    latency_last_s: float | None
    latencies_s: tuple[float, ...]


class ControlLoop(TaskPart):
    """The control loop part: owns the supervisor and everything a step sends or starts.

    Args:
        supervisor: the service's state machine; only this part steps it.
        config: the config in force (read at each use: live changes apply).
        clock: monotonic seconds (the clock of frame timestamps).
        link: the vehicle link now, or None before there is one.
        latest: the newest processed frame, or None.
        capture: the capture thread's status, or None.
        after_step: called after each step with (now_s, step output, latest, new_frame, camera_ok)
            (the presence part's :meth:`~companion.service.presence.Presence.step`).
        on_changed: called when the supervisor's state changed, with its output (health, sd_notify).
        on_error: records a one-line fault (health's ``last_error``).
        feed_watchdog: called after every step with its time (the systemd watchdog).
        on_died: see :class:`~companion.service.parts.TaskPart`.
    """

    name = "control loop"
    stop_budget_s = 1.0

    def __init__(
        self,
        supervisor: Supervisor,
        *,
        config: Callable[[], CompanionConfig],
        clock: Callable[[], float],
        link: Callable[[], Any],
        latest: Callable[[], Processed | None],
        capture: Callable[[], CaptureStatus | None],
        after_step: Callable[[float, Any, Processed | None, bool, bool], None],
        on_changed: Callable[[Any], None],
        on_error: Callable[[str], None],
        feed_watchdog: Callable[[float], None],
        on_died: Callable[[str, BaseException], None] | None = None,
    ) -> None:
        super().__init__(on_died)
        self._config, self._clock, self._link, self._latest = config, clock, link, latest
        self._capture, self._after_step, self._on_changed = capture, after_step, on_changed
        self._on_error, self._feed_watchdog = on_error, feed_watchdog
        self.supervisor = supervisor  # stepped here only, on the loop
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wake: asyncio.Event | None = None
        self._pending: list[tuple[Any, asyncio.Future | None]] = []
        self._action_tasks: set[asyncio.Task] = set()
        self._last_stepped_seq: int | None = None
        self._last_setpoint: VelocitySetpoint | None = None
        self._last_setpoint_s: float | None = None
        self._setpoints_sent = 0
        self._last_latency_s: float | None = None
        self._latency_s: collections.deque = collections.deque(maxlen=_LATENCY_SAMPLES)
        self.latencies_s: list[float] = []  # every frame-to-setpoint latency (bench); bounded by its user
        self.record_latencies = False

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        """The loop it runs on (before requests are submitted or the task starts)."""
        self._loop = loop
        self._wake = asyncio.Event()

    @property
    def engaged_or_engaging(self) -> bool:
        """True from an accepted engage until the service stops commanding (live changes are limited then)."""
        return self.supervisor.state in (State.ENGAGING, State.ENGAGED, State.DEGRADED, State.PAUSED, State.OVERRIDE)

    def wake(self) -> None:
        """Step now (on the loop): a new result, a request or a camera change."""
        if self._wake is not None:
            self._wake.set()

    def submit(self, request: Any) -> asyncio.Future | None:
        """Queue a supervisor request for the next step; the future gets its :class:`Reply`."""
        if self._loop is None:
            return None
        fut = None if isinstance(request, ActionResult) else self._loop.create_future()
        self._pending.append((request, fut))
        self.wake()
        return fut

    def counts(self) -> SetpointCounts:
        return SetpointCounts(
            last=self._last_setpoint,
            last_s=self._last_setpoint_s,
            sent=self._setpoints_sent,
            latency_last_s=self._last_latency_s,
            latencies_s=tuple(self._latency_s),
        )

    # ------------------------------------------------------------------------------ the loop

    async def run(self) -> None:
        assert self._wake is not None
        next_tick = self._clock()
        while True:
            period = 1.0 / self._config().vehicle.setpoint_rate_hz
            wake_at = next_tick
            stale_at = self._stale_deadline()
            if stale_at is not None and self._clock() < stale_at < wake_at:
                # The zero for stale frames goes out when the newest frame turns stale, not up to a
                # setpoint period later (the promise is 0.5 s, not 0.5 s plus a tick).
                wake_at = stale_at
            timeout = wake_at - self._clock()
            if timeout > 0:
                await wait_event(self._wake, timeout)
            self._wake.clear()
            now = self._clock()
            ticked = now >= next_tick
            if ticked:
                next_tick += period
                if next_tick <= now:
                    next_tick = now + period  # we were late: no burst of catch-up steps
            try:
                await self.step(now, ticked)
            except asyncio.CancelledError:
                raise
            except Exception as err:
                # A bug here must not leave MAVSDK re-sending a stale setpoint: zero now, then a clean
                # shutdown (Hold if ours) and a restart by systemd, passive.
                log.exception("control step failed")
                self._on_error(f"internal error in the control loop: {type(err).__name__}: {err}")
                await self.link_call("send_setpoint", ZERO_SETPOINT)
                raise
            self._feed_watchdog(now)

    def _stale_deadline(self) -> float | None:
        """Clock time (s) just past the moment the newest frame turns stale, or None without one."""
        latest = self._latest()
        if latest is None:
            return None
        # Just past: the supervisor counts a frame exactly ``stale_frame_timeout_s`` old as fresh.
        return latest.result.timestamp_s + self._config().command.stale_frame_timeout_s + 1e-3

    async def step(self, now: float, ticked: bool) -> None:
        """One supervisor step at ``now`` (monotonic seconds): requests answered, the setpoint sent,
        actions started."""
        latest = self._latest()
        new_frame = latest is not None and latest.seq != self._last_stepped_seq
        pending, self._pending = self._pending, []
        capture = self._capture()
        link = self._link()
        vehicle = link.state() if link is not None else None
        if vehicle is None:
            vehicle = VehicleState()
        camera_ok = capture.ok if capture is not None else False
        out = self.supervisor.step(
            now,
            latest.result if latest is not None else None,
            vehicle,
            [r for r, _ in pending],
            camera_ok=camera_ok,
        )
        replies = iter(out.replies)
        for _, fut in pending:
            if fut is None:
                continue
            reply = next(replies)
            if not fut.done():
                fut.set_result(reply)
        if out.setpoint is not None:
            sent = await self.link_call("send_setpoint", out.setpoint)
            if sent:
                t_sent = self._clock()
                self._last_setpoint = out.setpoint
                self._last_setpoint_s = t_sent
                self._setpoints_sent += 1
                if new_frame and self.supervisor.engaged and latest is not None:
                    latency = t_sent - latest.result.timestamp_s
                    self._last_latency_s = latency
                    self._latency_s.append(latency)
                    if self.record_latencies:
                        self.latencies_s.append(latency)
        self._after_step(now, out, latest, new_frame, camera_ok)
        if new_frame and latest is not None:
            self._last_stepped_seq = latest.seq
        for action in out.actions:
            if action is Action.STOP_SETPOINTS:
                # Right after the final zero, on the loop: nothing non-zero is ever left to re-send.
                await self.link_call("stop_setpoints")
            else:
                self._run_action(action)
        if out.changed:
            log.info("state %s: %s", out.state.value, out.reason)
            self._on_changed(out)

    # ------------------------------------------------------------------------------ the vehicle

    def _run_action(self, action: Action) -> None:
        """START_OFFBOARD / HOLD wait for the autopilot's ack (seconds): run them beside the loop and
        report the outcome to the supervisor."""

        async def runner() -> None:
            link = self._link()
            assert link is not None
            try:
                if action is Action.START_OFFBOARD:
                    await link.start_offboard()
                else:
                    await link.hold()
                self.submit(ActionResult(action, True))
                log.info("%s accepted", action.value)
            except VehicleError as err:
                log.warning("%s failed: %s", action.value, err)
                self._on_error(f"{action.value}: {err}")
                self.submit(ActionResult(action, False, str(err)))
            except asyncio.CancelledError:
                raise
            except Exception as err:
                log.exception("%s failed", action.value)
                self._on_error(f"{action.value}: {type(err).__name__}: {err}")
                self.submit(ActionResult(action, False, f"{type(err).__name__}: {err}"))

        assert self._loop is not None
        task = self._loop.create_task(runner(), name=action.value)
        self._action_tasks.add(task)
        task.add_done_callback(self._action_tasks.discard)

    async def link_call(self, name: str, *args: Any) -> bool:
        """Call the vehicle link's ``name(*args)``; False (recorded, never raised) when it failed."""
        link = self._link()
        if link is None:
            return False
        try:
            await getattr(link, name)(*args)
            return True
        except VehicleError as err:
            self._on_error(f"vehicle: {err}")
            log.debug("%s: %s", name, err)
        except asyncio.CancelledError:
            raise
        except Exception as err:
            log.exception("vehicle link %s failed", name)
            self._on_error(f"vehicle link {name}: {type(err).__name__}: {err}")
        return False

    # ------------------------------------------------------------------------------ stop

    async def stop(self, budget_s: float) -> bool:
        """Cancel the loop and the actions under way."""
        stopped = await super().stop(budget_s / 2.0)
        tasks = list(self._action_tasks)
        for task in tasks:
            task.cancel()
        if tasks:
            _, stuck = await asyncio.wait(tasks, timeout=budget_s / 2.0)
            for task in stuck:
                log.error("task %s did not stop within %.1f s; leaving it", task.get_name(), budget_s / 2.0)
        self._action_tasks.clear()
        return stopped
