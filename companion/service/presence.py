"""The service on the ground station's screen: its heartbeat, its STATUSTEXT lines and the
OBSTACLE_DISTANCE it feeds the autopilot's own collision prevention.

:class:`PresencePlane` is a part of :class:`~companion.service.daemon.Service` (a mixin). The control
loop calls :meth:`PresencePlane._presence_step` after each supervisor step; it decides (with the pure
:class:`~companion.core.announce.Announcer`) and queues. One task, :meth:`PresencePlane._presence_loop`,
does the sending through the vehicle link, so a slow send never delays a setpoint:

* the service's HEARTBEAT at ``vehicle.heartbeat_rate_hz`` with its MAV_STATE
  (:func:`~companion.core.announce.heartbeat_state`);
* STATUSTEXT lines in order, rate-limited by the announcer (``vehicle.status_text_min_interval_s``);
* OBSTACLE_DISTANCE once per processed frame (``obstacle_distance.send``: always, or only while
  engaged), stamped with the frame's capture time on the monotonic clock; when the previous one is
  still being sent, only the newest waits (counted as dropped).

Nothing is sent before the autopilot is connected; a failed send is counted and logged, never raised.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import math
from typing import Any

from companion.core.announce import Announcer, TextLimiter, heartbeat_state
from companion.core.types import REGION_INDEX
from companion.errors import VehicleError

log = logging.getLogger(__name__)

#: STATUSTEXT lines waiting at most (the announcer's rate limit keeps it far below this).
_MAX_QUEUED_TEXTS = 16


class PresencePlane:
    """The presence part of the service (mixed into :class:`~companion.service.daemon.Service`)."""

    def _presence_init(self) -> None:
        v = self.config.vehicle
        self._announcer = Announcer(TextLimiter(v.status_text_min_interval_s, v.status_text_burst))
        self._texts: collections.deque[tuple[int, str]] = collections.deque(maxlen=_MAX_QUEUED_TEXTS)
        self._obstacle_next: tuple[Any, int] | None = None  # (ObstacleDistance, time_usec) waiting
        self._presence_wake: asyncio.Event | None = None
        self._presence_camera_ok = True
        self._presence_frames_ok = True
        self.presence_stats = {
            "heartbeats_sent": 0,
            "status_texts_sent": 0,
            "status_texts_suppressed": 0,
            "obstacle_distance_sent": 0,
            "obstacle_distance_dropped": 0,
            "send_errors": 0,
        }
        self.last_status_text: str | None = None
        self.last_obstacle_distance: Any = None  # the newest ObstacleDistance queued (tests, health)

    def _presence_connected(self) -> bool:
        link = self.link
        return link is not None and self._vehicle_status == "connected" and link.state().connected

    def _presence_step(self, now_s: float, out: Any, latest: Any, new_frame: bool, camera_ok: bool) -> None:
        """After a supervisor step (on the loop): queue the lines to say and the frame's OBSTACLE_DISTANCE.
        Never raises: what the ground station is told must not stop the flight loop."""
        try:
            self._presence_decide(now_s, out, latest, new_frame, camera_ok)
        except Exception:
            self.presence_stats["send_errors"] += 1
            log.exception("presence step failed (the flight loop goes on)")

    def _presence_decide(self, now_s: float, out: Any, latest: Any, new_frame: bool, camera_ok: bool) -> None:
        cfg = self.config
        # A pipeline that stopped delivering (frames rejected, a stage failing) while the camera streams:
        # reported once the newest result is older than the failsafe timeout (not on a hiccup).
        frames_ok = out.frame_age_s <= cfg.command.failsafe_timeout_s
        self._presence_camera_ok, self._presence_frames_ok = camera_ok, frames_ok
        result = latest.result if latest is not None else None
        decision = getattr(result, "decision", None)
        ahead = None
        shown = getattr(result, "shown_depths_m", None)
        if shown is not None:
            ahead = float(shown()[REGION_INDEX["center"]])
            ahead = ahead if math.isfinite(ahead) else None
        if cfg.vehicle.status_text:
            limiter = self._announcer.limiter
            limiter.min_interval_s = cfg.vehicle.status_text_min_interval_s
            limiter.burst = cfg.vehicle.status_text_burst
            lines = self._announcer.step(
                now_s,
                out.state.value,
                out.reason,
                decision.kind.value if decision is not None else None,
                ahead,
                camera_ok,
                frames_ok,
            )
            self.presence_stats["status_texts_suppressed"] = limiter.suppressed
            if lines:
                self._texts.extend(lines)
                self._wake_presence()
        send = cfg.obstacle_distance.send
        obstacle = getattr(result, "obstacle", None)
        if new_frame and obstacle is not None and (send == "always" or (send == "engaged" and self.supervisor.engaged)):
            if self._obstacle_next is not None:
                self.presence_stats["obstacle_distance_dropped"] += 1
            self._obstacle_next = (obstacle, int(round(result.timestamp_s * 1e6)))
            self.last_obstacle_distance = obstacle
            self._wake_presence()

    def _wake_presence(self) -> None:
        if self._presence_wake is not None:
            self._presence_wake.set()

    async def _presence_send(self, what: str, name: str, *args: Any) -> bool:
        fn = getattr(self.link, name, None)
        if fn is None:
            return False  # a link without presence (tests' fakes)
        try:
            await fn(*args)
            return True
        except VehicleError as err:
            self.presence_stats["send_errors"] += 1
            log.debug("%s not sent: %s", what, err)
        except asyncio.CancelledError:
            raise
        except Exception:
            self.presence_stats["send_errors"] += 1
            log.exception("sending %s failed", what)
        return False

    async def _presence_loop(self) -> None:
        self._presence_wake = asyncio.Event()
        next_beat = self._clock()
        while True:
            timeout = next_beat - self._clock()
            if timeout > 0:
                try:
                    await asyncio.wait_for(self._presence_wake.wait(), timeout)
                except asyncio.TimeoutError:
                    pass
            self._presence_wake.clear()
            if not self._presence_connected():
                # Lines said before the autopilot was heard are kept (bounded); frames' bins are not.
                self._obstacle_next = None
                next_beat = self._clock() + 0.2
                continue
            now = self._clock()
            if now >= next_beat:
                next_beat = now + 1.0 / self.config.vehicle.heartbeat_rate_hz
                state = heartbeat_state(self.supervisor.state.value, self._presence_camera_ok, self._presence_frames_ok)
                if await self._presence_send("HEARTBEAT", "send_heartbeat", state):
                    self.presence_stats["heartbeats_sent"] += 1
            while self._texts:
                severity, text = self._texts.popleft()
                if await self._presence_send("STATUSTEXT", "send_status_text", severity, text):
                    self.presence_stats["status_texts_sent"] += 1
                    self.last_status_text = text
                    log.info("STATUSTEXT (severity %d): %s", severity, text)
            pending, self._obstacle_next = self._obstacle_next, None
            if pending is not None:
                if await self._presence_send("OBSTACLE_DISTANCE", "send_obstacle_distance", *pending):
                    self.presence_stats["obstacle_distance_sent"] += 1

    def presence_status(self) -> dict[str, Any]:
        """Health's ``mavlink``: counters, the last STATUSTEXT, the newest OBSTACLE_DISTANCE's nearest (m)."""
        od = self.last_obstacle_distance
        return {
            **self.presence_stats,
            "last_status_text": self.last_status_text,
            "obstacle_nearest_m": od.nearest_m if od is not None else None,
        }
