"""The local stack for one flight: the map, the planner and the safety chain, fed one frame and one tick
at a time (pure; time is passed in). The simulator's loop and the service's control step both use it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from companion.core.track import TrackWatch
from companion.core.geometry import StereoGeometry
from companion.core.goal import GoalSpec, resolve_goal
from companion.core.planner.local import LocalPlanner, Mode, Plan, Snapshot
from companion.core.planner.localmap import LocalMap
from companion.core.planner.paths import floor_bent_lengths
from companion.core.planner.safety import SafetyContext, from_ned, to_ned, trace_chain
from companion.core.pose import Pose
from companion.core.types import REGION_INDEX, Decision, VelocitySetpoint

if TYPE_CHECKING:
    from companion.config import CompanionConfig

#: A course goal (no point) is flown as a point this far along the heading at engagement, metres.
COURSE_POINT_M = 1000.0
#: The motion the reported velocity does not explain is fitted over this window of the position's
#: track, seconds: long enough to average out a few samples' timing jitter, short against the way an
#: estimate's error changes (seconds).
TRACK_WINDOW_S = 0.5


@dataclass(frozen=True)
class StackStep:
    """One tick's outcome: the setpoint after the safety chain, the plan it came from, and the names of
    the chain's filters that changed it (:func:`~companion.core.planner.safety.trace_chain`)."""

    setpoint: VelocitySetpoint
    plan: Plan
    limited_by: tuple[str, ...] = ()


class LocalStack:
    """Map, planner and safety chain for one flight.

    Args:
        cfg: the whole configuration (``planner``, ``vehicle.radius_m``, ``command`` timeouts, ``envelope``).
    """

    def __init__(self, cfg: CompanionConfig):
        self.cfg = cfg
        self.map = self._new_map(cfg)
        self.planner = LocalPlanner(cfg.planner, cfg.vehicle.radius_m)
        self.goal_ned_m: np.ndarray | None = None
        self.view_half_rad = math.radians(40.0)
        self.track = TrackWatch(axes=3)
        self._unexplained = np.zeros(3)
        self._last: StackStep | None = None
        self._sent_ned: np.ndarray | None = None  # the last setpoint, NED m/s

    @staticmethod
    def _new_map(cfg: CompanionConfig) -> LocalMap:
        p = cfg.planner
        return LocalMap(p.voxel_m, p.map_range_m, cfg.vehicle.radius_m, p.occupied_memory_s, p.free_memory_s)

    def reconfigure(self, cfg: CompanionConfig) -> None:
        """New settings in flight (a live reload): the planner and the chain fly by them from the next
        tick, the flight's goal, mode and memories kept. The map keeps what it saw unless its grid or
        its memory changed (voxel, range, radius, memories): then it starts afresh, and what it has not
        seen is near."""
        old = self.cfg
        self.cfg = cfg
        grid = ("voxel_m", "map_range_m", "occupied_memory_s", "free_memory_s")
        if old.vehicle.radius_m != cfg.vehicle.radius_m or any(
            getattr(old.planner, k) != getattr(cfg.planner, k) for k in grid
        ):
            self.map = self._new_map(cfg)
        self.planner.reconfigure(cfg.planner, cfg.vehicle.radius_m)

    def engage(self, position_ned_m: np.ndarray, yaw_rad: float, goal: GoalSpec | None) -> None:
        """Start a flight at ``position_ned_m`` (float ``(3,)`` NED m) heading ``yaw_rad`` toward ``goal``
        (None: no goal, the fuzzy controller is the whole policy; the course: a point far along the
        heading, at the altitude now)."""
        pos = np.asarray(position_ned_m, dtype=np.float64)
        self.planner.engage()
        self.track.reset()
        self._sent_ned = None
        self.goal_ned_m = self._goal_point(pos, yaw_rad, goal)

    @staticmethod
    def _goal_point(pos: np.ndarray, yaw_rad: float, goal: GoalSpec | None) -> np.ndarray | None:
        """The NED point (float64 ``(3,)``) a goal is flown to from ``pos`` heading ``yaw_rad``, at the
        altitude now; None for no goal."""
        if goal is None:
            return None
        g = resolve_goal(goal, pos, yaw_rad)
        if g.point_ned_m is None:
            return pos + COURSE_POINT_M * np.array([math.cos(yaw_rad), math.sin(yaw_rad), 0.0])
        return np.array([g.point_ned_m[0], g.point_ned_m[1], pos[2]])

    def set_goal(self, position_ned_m: np.ndarray, yaw_rad: float, goal: GoalSpec | None) -> None:
        """A new goal in flight (the operator's goto): the map and the places flown through stay, a hold
        ends."""
        pos = np.asarray(position_ned_m, dtype=np.float64)
        self.goal_ned_m = self._goal_point(pos, yaw_rad, goal)
        self.planner.resume()

    def resume(self) -> None:
        """The operator's resume: a hold ends, the goal stays."""
        self.planner.resume()

    def stop(self, reason: str) -> None:
        """Hold the point where the vehicle is (the service's progress watchdog), for ``reason``."""
        self.planner.stop(reason)

    @property
    def holding_reason(self) -> str | None:
        """Why the planner holds (a dead end, the goal), or None."""
        return self.planner.reason if self.planner.mode is Mode.HOLD else None

    def add_frame(self, blocks: np.ndarray, geometry: StereoGeometry, block_px: int, seen_from: Pose, t_s: float) -> None:
        """A frame's block image (float32 ``(rows, cols)`` px, NaN none) seen from ``seen_from`` at its
        capture time ``t_s`` into the map; its horizontal view sets what counts as looked at."""
        self.map.integrate(blocks, geometry, block_px, seen_from, t_s, self.cfg.stereo.num_disparities)
        self.view_half_rad = math.atan(0.5 * geometry.width_px / geometry.focal_px) * 0.9

    def step(
        self,
        now_s: float,
        frame_age_s: float,
        decision: Decision | None,
        region_depths_m: np.ndarray | None,
        position_ned_m: np.ndarray,
        velocity_ned_m_s: np.ndarray,
        yaw_rad: float,
    ) -> StackStep:
        """One control tick: plan on the map, then the safety chain.

        The vehicle's motion is the reported velocity plus what the reported position's track shows
        it does not explain (at most ``vehicle.odometry_drift_m_s``): the planner predicts its paths
        and the speed law judges the way it moves with that motion, and the chain takes the
        unexplained part off the setpoint so that the vehicle moves as planned."""
        pos = np.asarray(position_ned_m, dtype=np.float64)
        self.track.observe(now_s, pos, np.asarray(velocity_ned_m_s, dtype=np.float64))
        u = self.track.unexplained_m_s(now_s, TRACK_WINDOW_S, self.cfg.vehicle.odometry_drift_m_s)
        unexplained = self._unexplained
        unexplained[:] = 0.0
        if u is not None:
            unexplained[:] = u
        vel = np.asarray(velocity_ned_m_s, dtype=np.float64) + unexplained
        self.map.mark_body_free(pos, now_s)
        # The last setpoint, as the vehicle flies it (plus the motion it does not explain).
        in_flight = None if self._sent_ned is None else self._sent_ned + unexplained
        snap = Snapshot(now_s, pos, vel, float(yaw_rad), self.goal_ned_m, decision, self.view_half_rad, in_flight)
        plan = self.planner.plan(snap, self.map)
        sp = from_ned(plan.velocity_ned_m_s, yaw_rad, plan.yaw_rate_deg_s)
        centre = math.nan if region_depths_m is None else float(region_depths_m[REGION_INDEX["center"]])
        env = self.cfg.envelope
        lmap = self.map

        # The chain asks along the command and along the motion: both in one query, the usual case.
        asked = np.zeros((2, 3))
        asked[0] = plan.direction_ned
        sp_m = float(np.linalg.norm(vel))
        if sp_m > 1e-9:
            asked[1] = vel / sp_m
        # A descent is judged as flown: levelling off at the floor (the floor filter's), not into the ground.
        floor = self.cfg.planner.floor_m

        def flown(u: np.ndarray, free_m: np.ndarray | None = None) -> np.ndarray:
            free_m = lmap.free_lengths(pos, u).length_m if free_m is None else free_m
            return floor_bent_lengths(lmap, pos, u, free_m, floor)

        both = lmap.free_lengths(pos, asked)
        known = flown(asked, both.length_m)

        def free_along(u: np.ndarray) -> float:
            u = np.asarray(u, dtype=np.float64)
            for k in range(2):
                if float(asked[k] @ u) > 1.0 - 1e-9:
                    return float(known[k])
            return float(flown(u[None, :])[0])

        planner = self.planner

        def free_swinging(v: np.ndarray) -> float:
            v = np.asarray(v, dtype=np.float64)
            s = float(np.linalg.norm(v))
            u = v / s
            swing = planner.swing_clear(lmap, pos, vel, in_flight, u[None, :], np.array([s]))
            out = min(free_along(u), float(swing[0]))
            # The swing leaves along the motion, and the map's swing judges surfaces alone: where the
            # motion's line ends in space not seen rather than at a surface, the swing is seen free no
            # farther (unknown is near).
            if sp_m > 1e-9 and not both.blocked[1]:
                out = min(out, float(both.length_m[1]))
            return out

        radius = self.cfg.vehicle.radius_m
        near = lmap.nearest_surface(pos, radius + self.cfg.planner.stop_margin_m)
        ctx = SafetyContext(
            frame_age_s=frame_age_s,
            stale_after_s=self.cfg.command.stale_frame_timeout_s,
            holding=plan.mode is Mode.HOLD,
            decision=decision,
            centre_depth_m=centre,
            yaw_rad=float(yaw_rad),
            altitude_m=float(-pos[2]),
            velocity_ned_m_s=vel,
            unexplained_ned_m_s=unexplained.copy(),
            free_along=free_along,
            planner=self.cfg.planner,
            max_horizontal_m_s=env.max_horizontal_speed_m_s,
            max_vertical_m_s=min(env.max_vertical_speed_m_s, self.cfg.planner.max_vertical_speed_m_s),
            max_yaw_rate_deg_s=min(env.max_yaw_rate_deg_s, self.cfg.planner.max_yaw_rate_deg_s),
            view_half_rad=self.view_half_rad,
            surface_gap_m=math.inf if near is None else near[0] - radius,
            surface_dir_ned=None if near is None else near[1],
            free_swinging=free_swinging,
        )
        setpoint, limited_by = trace_chain(sp, ctx)
        self._last = StackStep(setpoint, plan, limited_by)
        self._sent_ned = to_ned(setpoint, float(yaw_rad))
        return self._last

    def status(self) -> dict[str, object]:
        """What the planner did at the last tick, for the health message: ``mode`` (cruise, avoid,
        detour, hold), ``reason`` (the way it chose, or why it holds), ``free_m`` (seen free along that
        way, metres), ``speed_m_s`` (the speed law's speed on it), ``unexplained_m_s`` (the motion of
        the reported position its velocity does not show, NED m/s, which the setpoint counters),
        ``limited_by`` (the safety filters that changed the planner's setpoint, in the chain's order)."""
        last = self._last
        if last is None:
            return {"mode": self.planner.mode.value, "reason": self.planner.reason, "free_m": None,
                    "speed_m_s": None, "unexplained_m_s": [0.0, 0.0, 0.0], "limited_by": []}
        return {
            "mode": last.plan.mode.value,
            "reason": last.plan.reason,
            "free_m": last.plan.free_m if math.isfinite(last.plan.free_m) else None,
            "speed_m_s": float(np.linalg.norm(last.plan.velocity_ned_m_s)),
            "unexplained_m_s": [float(x) for x in self._unexplained],
            "limited_by": list(last.limited_by),
        }
