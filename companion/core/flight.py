"""The decision layer of one engagement, as the service's supervisor drives it (pure; time is passed in).

:class:`Flight` holds what one flight needs between control steps: the local stack
(:class:`~companion.core.planner.stack.LocalStack`: the map, the planner and the safety chain), the
goal and the progress watchdog (:class:`~companion.core.progress.GoalProgress`), and the vehicle's
recent poses, so that each frame's blocks enter the map from the pose the frame was captured at.
The supervisor (:mod:`companion.core.supervisor`) decides *whether* the vehicle is flown; this
decides *what* it is told.

The stack starts once the vehicle's position and heading are known (engaged without them, the
vehicle is told zero velocity until they are).
"""

from __future__ import annotations

import math
from collections import deque
from typing import TYPE_CHECKING

import numpy as np

from companion.core.goal import COURSE, GoalSpec
from companion.core.planner.stack import LocalStack
from companion.core.pose import Pose
from companion.core.progress import GoalProgress
from companion.core.types import ZERO_SETPOINT, VelocitySetpoint

if TYPE_CHECKING:
    from companion.config import CompanionConfig
    from companion.core.supervisor_io import FrameOutcome
    from companion.interfaces import VehicleState

#: Vehicle poses kept to place a frame's blocks from the pose it was captured at (20 Hz: 3 s).
POSE_HISTORY = 64
#: A frame's blocks enter the map only with a pose this near its capture time, seconds.
POSE_MATCH_S = 0.2


def finite_or_none(values: object, index: int) -> float | None:
    """``values[index]`` as a float when ``values`` is an array-like with a finite number there."""
    if values is None:
        return None
    try:
        x = float(values[index])  # type: ignore[index]
    except (TypeError, IndexError, ValueError):
        return None
    return x if math.isfinite(x) else None


class Flight:
    """The local stack, the goal and the progress watchdog of one engagement, and the recent poses.

    Args:
        cfg: the whole configuration the stack flies by.
    """

    def __init__(self, cfg: CompanionConfig) -> None:
        self.cfg = cfg
        self.stack: LocalStack | None = None
        self.progress = GoalProgress()
        self._goal: GoalSpec = COURSE
        self._poses: deque[tuple[float, Pose]] = deque(maxlen=POSE_HISTORY)  # (time s, pose)
        self._last_frame_s: float | None = None  # capture time of the newest frame put in the map

    # ------------------------------------------------------------------------------------ commands

    def engage(self, v: VehicleState, goal: GoalSpec = COURSE) -> None:
        """A new flight toward ``goal`` from the vehicle's pose now: a new map, the watchdog from zero."""
        self._goal = goal
        self.stack = None
        self.progress = GoalProgress()
        self._start(v)

    def set_goal(self, v: VehicleState, goal: GoalSpec) -> None:
        """The operator's ``goto``: a new goal from where the vehicle is now; the map stays, a hold ends."""
        self._goal = goal
        heading = finite_or_none(v.attitude_rad, 2)
        self.progress.set_goal(goal, v.position_ned_m, heading)
        if self.stack is not None and v.position_ned_m is not None and heading is not None:
            self.stack.set_goal(np.asarray(v.position_ned_m, dtype=np.float64), heading, goal)

    def resume(self) -> None:
        """The operator's ``resume``: a hold ends, the goal stays, the watchdog starts again."""
        self.progress.resume()
        if self.stack is not None:
            self.stack.resume()

    def stop(self, reason: str) -> None:
        """Hold the point where the vehicle is, for ``reason`` (the progress watchdog), unless the
        planner already holds for its own."""
        if self.stack is not None and self.stack.holding_reason is None:
            self.stack.stop(reason)

    def reconfigure(self, cfg: CompanionConfig) -> None:
        """New settings in flight (a live reload): the stack flies by them from the next tick."""
        self.cfg = cfg
        if self.stack is not None:
            self.stack.reconfigure(cfg)

    def _start(self, v: VehicleState) -> None:
        """Start the stack and the watchdog from the vehicle's pose, once its position and heading are known."""
        heading = finite_or_none(v.attitude_rad, 2)
        if self.stack is not None or v.position_ned_m is None or heading is None:
            return
        position = np.asarray(v.position_ned_m, dtype=np.float64)
        if position.shape != (3,) or not np.all(np.isfinite(position)):
            return
        self.progress.engage(position, heading, self._goal)
        self.stack = LocalStack(self.cfg)
        self.stack.engage(position, heading, self._goal)

    # ------------------------------------------------------------------------------------ per step

    def remember(self, now_s: float, latest: FrameOutcome | None, v: VehicleState) -> None:
        """Keep the vehicle's recent poses, and put a new frame's blocks (``near_blocks``) into the map
        from the pose nearest its capture time (none within :data:`POSE_MATCH_S`: not put)."""
        pose = Pose.from_telemetry(v.position_ned_m, v.attitude_rad)
        if pose is not None:
            t = v.position_timestamp_s if v.position_timestamp_s is not None else now_s
            if not self._poses or t > self._poses[-1][0]:
                self._poses.append((float(t), pose))
        blocks, geometry = getattr(latest, "near_blocks", None), getattr(latest, "geometry", None)
        if latest is None or blocks is None or geometry is None or latest.timestamp_s == self._last_frame_s:
            return
        self._last_frame_s = latest.timestamp_s
        if not self._poses or self.stack is None:
            return
        t_seen, seen_from = min(self._poses, key=lambda tp: abs(tp[0] - latest.timestamp_s))
        if abs(t_seen - latest.timestamp_s) <= POSE_MATCH_S:
            self.stack.add_frame(blocks, geometry, self.cfg.planner.block_px, seen_from, latest.timestamp_s)

    def setpoint(self, now_s: float, latest: FrameOutcome, age_s: float, v: VehicleState) -> VelocitySetpoint:
        """The local stack's setpoint for this tick (its safety chain ends it); holding, it holds the
        point where the hold began (an autopilot told zero velocity creeps on: PX4's velocity
        integrator, the position estimate's drift). Without a position, velocity and heading there is
        no plan: zero velocity."""
        self._start(v)
        heading = finite_or_none(v.attitude_rad, 2)
        if self.stack is None or heading is None or v.position_ned_m is None or v.velocity_ned_m_s is None:
            return ZERO_SETPOINT
        refined = getattr(latest, "refined", None)
        step = self.stack.step(
            now_s, age_s, latest.decision, getattr(refined, "depth_m", None),
            np.asarray(v.position_ned_m, dtype=np.float64), np.asarray(v.velocity_ned_m_s, dtype=np.float64), heading,
        )
        return step.setpoint

    def no_progress(self, now_s: float, v: VehicleState) -> bool:
        """The progress watchdog fed the position now: True once the vehicle has got no
        ``command.progress_step_m`` nearer its goal in the time to fly ``planner.no_progress_distance_m``
        at cruise. Flying away from the goal is no stall by itself: the planner's way round can lead
        away from the goal for seconds."""
        return self.progress.no_progress(
            v.position_ned_m, now_s, self.cfg.command.progress_step_m, self.cfg.planner.no_progress_timeout_s
        )

    def reset_watchdog(self) -> None:
        """Start the watchdog's time again (it times the automatic flight only)."""
        self.progress.watch.reset()

    # ------------------------------------------------------------------------------------ queries

    @property
    def holding_reason(self) -> str | None:
        """Why the planner holds (a dead end, the goal reached, the watchdog), or None."""
        return None if self.stack is None else self.stack.holding_reason

    def watchdog_reason(self) -> str:
        """Why the progress watchdog held, in the operator's words."""
        p, step_m = self.cfg.planner, self.cfg.command.progress_step_m
        return (
            f"no progress along the course for {p.no_progress_timeout_s:.0f} s (less than {step_m:g} m "
            f"in the time to fly {p.no_progress_distance_m:g} m at {p.cruise_speed_m_s:g} m/s: "
            "planner.no_progress_distance_m, command.progress_step_m): holding position; resume to try "
            "again, or take over"
        )

    def planner_status(self) -> dict[str, object] | None:
        """The stack's last tick (:meth:`~companion.core.planner.stack.LocalStack.status`), or None
        before the stack started."""
        return None if self.stack is None else self.stack.status()

    def goal_status(self, position_ned_m: object) -> dict[str, object]:
        """The goal for the health message (:meth:`~companion.core.progress.GoalProgress.status`)."""
        reason = self.holding_reason
        return self.progress.status(position_ned_m, reached=reason is not None and reason.startswith("arrived"))
