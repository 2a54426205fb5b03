"""Course hold's bookkeeping for one flight, shared by the service's supervisor and the simulator.

Course hold brings the vehicle back to the heading, the line and the altitude it was engaged at, once
the way has been clear for a while (:func:`~companion.core.command.setpoint_for` says how). What it
needs between setpoints lives here, once:

* the course: where the vehicle was engaged (the line's origin), its heading and altitude then;
* how long the decisions have been straight and CLEAR, and how far the vehicle has flown since
  (:func:`~companion.core.command.is_straight_clear`), and how long they have not turned
  (:func:`~companion.core.command.is_heading_clear`);
* where the current brake began (:class:`~companion.core.command.BrakeLatch`), where something was
  last overhead (:class:`~companion.core.command.OverheadMemory`) and the progress watchdog's clock
  (:class:`~companion.core.command.ProgressWatch`).

One clock: a decision's timers run from the capture time of the first frame that made it (the
``timestamp_s`` of a frame result), and every elapsed time is measured to the time of the setpoint
being made. The service and the simulator both pass those two times, so they wait the same.

Pure: positions, headings and times are passed in; nothing here reads a clock.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from companion.core.command import (
    BrakeLatch,
    OverheadMemory,
    ProgressWatch,
    along_course_m,
    horizontal_distance_m,
    horizontal_velocity_body_m_s,
    is_heading_clear,
    is_straight_clear,
    line_offset_m,
    setpoint_for,
)
from companion.core.types import Decision, VelocitySetpoint

if TYPE_CHECKING:
    from companion.config.core import CommandConfig, MemoryConfig


def _finite_position(position_ned_m: object) -> np.ndarray | None:
    """A float64 ``(3,)`` copy of a NED position in metres when it is one and finite, else None."""
    if position_ned_m is None:
        return None
    try:
        p = np.asarray(position_ned_m, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        return None
    return p.copy() if np.all(np.isfinite(p)) else None


def _finite(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


class CourseHold:
    """What course hold remembers during one flight (see the module doc).

    Built with no course; :meth:`engage` sets it. The clear timers run from construction on (a
    vehicle engaged after a clear stretch may hold its course at once), the latches and the
    progress clock from :meth:`engage`.
    """

    def __init__(self) -> None:
        self.origin_ned_m: np.ndarray | None = None
        self.heading_rad: float | None = None
        self.altitude_m: float | None = None
        self._clear_since_s: float | None = None
        self._clear_since_ned_m: np.ndarray | None = None
        self._heading_clear_since_s: float | None = None
        self.brake = BrakeLatch()
        self.overhead = OverheadMemory()
        self.progress = ProgressWatch()

    def engage(self, position_ned_m: object, heading_rad: float | None) -> None:
        """The course starts here: float ``(3,)`` NED metres (the line's origin and, as ``-down``, the
        altitude) and the heading (radians); an unknown or non-finite part stays unknown, and the
        hold that needs it stays off. Forgets any brake, overhead sighting and progress."""
        origin = _finite_position(position_ned_m)
        self.origin_ned_m = origin
        self.heading_rad = _finite(heading_rad)
        self.altitude_m = None if origin is None else -float(origin[2])
        self.brake.reset()
        self.overhead.reset()
        self.progress.reset()

    def observe(self, decision: Decision | None, decision_time_s: float | None, position_ned_m: object) -> None:
        """The decision in force, made from the frame captured at ``decision_time_s`` (seconds), with
        the vehicle at ``position_ned_m`` (float ``(3,)`` NED metres, or None). Call it before each
        :meth:`setpoint` (and may be called more often: the same decision again changes nothing)."""
        if decision is None or decision_time_s is None or not is_straight_clear(decision):
            self._clear_since_s = None
            self._clear_since_ned_m = None
        elif self._clear_since_s is None:
            self._clear_since_s = float(decision_time_s)
            self._clear_since_ned_m = None if position_ned_m is None else np.array(position_ned_m, dtype=np.float64)
        if decision is None or decision_time_s is None or not is_heading_clear(decision):
            self._heading_clear_since_s = None
        elif self._heading_clear_since_s is None:
            self._heading_clear_since_s = float(decision_time_s)

    def ready(self, position_ned_m: object) -> bool:
        """Whether the course (origin and heading) and the vehicle's position are known."""
        return self.origin_ned_m is not None and self.heading_rad is not None and position_ned_m is not None

    def no_progress(self, position_ned_m: object, now_s: float, cmd: CommandConfig) -> bool:
        """The progress watchdog fed the distance along the course now: True once the vehicle has got
        no ``cmd.progress_step_m`` farther for ``cmd.no_progress_timeout_s``
        (:class:`~companion.core.command.ProgressWatch`)."""
        along = None
        if self.ready(position_ned_m):
            along = along_course_m(position_ned_m, self.origin_ned_m, self.heading_rad)
        return self.progress.update(along, now_s, cmd)

    def setpoint(
        self,
        decision: Decision | None,
        now_s: float,
        since_last_frame_s: float,
        cmd: CommandConfig,
        *,
        position_ned_m: np.ndarray | None,
        yaw_rad: float | None,
        velocity_ned_m_s: np.ndarray | None = None,
        region_depths_m: np.ndarray | None = None,
        guard_m: np.ndarray | None = None,
        remembered_sides: tuple[bool, bool] | None = None,
        gap_offset_m: float | None = None,
        memory_cfg: MemoryConfig | None = None,
    ) -> VelocitySetpoint:
        """The setpoint for ``decision`` at ``now_s`` (seconds, the clock of :meth:`observe`'s times),
        its frame ``since_last_frame_s`` old, with the course hold's inputs from this flight's
        bookkeeping (:func:`~companion.core.command.setpoint_for`).

        Args:
            position_ned_m: float ``(3,)`` NED metres now, or None.
            yaw_rad: heading now, radians, or None.
            velocity_ned_m_s: float ``(3,)`` NED m/s now, or None (the guard's lean needs it).
            region_depths_m: float ``(9,)`` refined region depths, metres, NaN unknown, or None.
            guard_m, remembered_sides, gap_offset_m: the obstacle memory's inputs
                (:meth:`~companion.core.memory.ObstacleMemory.hold_inputs`), or None (memory off).
            memory_cfg: the ``[memory]`` config that goes with them.
        """
        yaw = _finite(yaw_rad)
        heading_error = altitude_error = line_offset = None
        if self.heading_rad is not None and yaw is not None:
            heading_error = self.heading_rad - yaw  # positive: the course lies to the right
        if self.altitude_m is not None and position_ned_m is not None:
            down = float(np.asarray(position_ned_m, dtype=np.float64)[2])
            if math.isfinite(down):
                altitude_error = self.altitude_m + down  # altitude then minus now; positive: climb back
        if self.ready(position_ned_m):
            line_offset = line_offset_m(position_ned_m, self.origin_ned_m, self.heading_rad)
        clear_since = self._clear_since_s
        heading_since = self._heading_clear_since_s
        return setpoint_for(
            decision,
            since_last_frame_s,
            cmd,
            heading_error_rad=heading_error,
            altitude_error_m=altitude_error,
            region_depths_m=region_depths_m,
            # Not straight and CLEAR now (a CLEAR decision still turning, as the release filter lets
            # an escape fade, included): course hold waits from zero. None here would mean "no wait",
            # and turning back in place then fought the escape's last turn.
            clear_for_s=0.0 if clear_since is None else max(0.0, now_s - clear_since),
            clear_for_m=0.0 if clear_since is None else horizontal_distance_m(self._clear_since_ned_m, position_ned_m),
            heading_clear_for_s=0.0 if heading_since is None else max(0.0, now_s - heading_since),
            brake_offset_body_m=self.brake.offset_body(decision, position_ned_m, yaw),
            brake_heading_error_rad=self.brake.heading_error_rad(yaw),
            line_offset_m=line_offset,
            since_up_near_m=self.overhead.update(region_depths_m, position_ned_m, cmd.hold_clear_depth_m),
            guard_m=guard_m,
            guard_cfg=memory_cfg,
            remembered_sides=remembered_sides,
            velocity_body_m_s=horizontal_velocity_body_m_s(velocity_ned_m_s, yaw),
            gap_offset_m=gap_offset_m,
        )
