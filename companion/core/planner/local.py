"""One planner on the local map: candidate directions scored by one cost function, a stopping-distance
speed law, and explicit modes (pure; time is passed in). docs/planner.md explains it with a figure.

Each tick (:meth:`LocalPlanner.plan`) takes one frozen :class:`Snapshot` and the map, and:

1. lays out candidate directions all round in yaw (``yaw_step_deg``) × five climbs round the way back
   to the goal's altitude (within ±``max_climb_deg``);
2. asks the map how far each is free (:meth:`~companion.core.planner.localmap.LocalMap.free_lengths`:
   seen free, the surfaces inflated by the vehicle's radius), cut where it would leave the band
   between floor and ceiling; a line is scored on where it leads (:mod:`~companion.core.planner.paths`):
   a descent cut by the floor levels off along it, a level line that ends at a surface turns onto
   the way round it;
3. scores each by ONE cost (:func:`costs`), a weighted sum of named terms: turn from the goal's
   direction (the way round the surfaces seen, :mod:`~companion.core.planner.way`), the way left after
   flying the candidate's length, shortness of that length,
   change from the last choice, difference from the fuzzy controller's steer, and places already
   flown through. A direction the camera has not looked along lately and that ends in unknown space is
   scored on a *hoped-for* length (half the map range): the planner turns to look there, and the speed
   law (which uses only what was seen free) does not fly there before it has looked. Plan hopeful, fly
   on what was seen;
4. flies the cheapest at the speed law's speed (:func:`speed_law`), turning the camera toward it;
5. names the mode (:data:`TRANSITIONS`): cruise, avoid, detour, or hold (a dead end or the goal; held
   until the operator commands again).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np

from companion.config.planner import PlannerConfig
from companion.core.planner.localmap import LocalMap
from companion.core.planner.paths import (
    SWING_CANDIDATES,
    along,
    angle_diff,
    bend_at_floor,
    bend_onto_way,
    directions,
    swing_profile,
    to_band,
)
from companion.core.planner.way import WayToGoal
from companion.core.types import Decision, DecisionKind

#: Climbs per yaw: the way back to the goal's altitude, and that -max, -max/2, +max/2, +max (within
#: ±max).
N_CLIMBS = 5
#: Added to the speed law's speed in the time term, m/s: a direction with no room to fly costs
#: length / this seconds, much but finite, so that it stays comparable.
CREEP_M_S = 0.2
#: Holding, the velocity back to the held point per metre away, 1/s, and at most, m/s.
HOLD_GAIN_PER_S = 1.0
HOLD_MAX_M_S = 0.5
#: The goal's altitude is taken back over the distance flown in this time, seconds: at any speed
#: (up to the climb's cap) the altitude error decays with this time constant.
ALTITUDE_RETURN_S = 3.0
#: A direction looked along from farther than this from here is not looked along from here, metres:
#: the space a line from here ends in was out of that view (a wall's opening passed along the wall
#: had been "looked at" from the start, 3.7 m away, and the way through it counted as closed).
LOOKED_FROM_M = 1.0
#: Side of the cells of the visited-places memory, metres.
VISITED_CELL_M = 0.5
#: The visited-places term looks this far along a candidate, metres.
VISITED_LOOKAHEAD_M = 1.5
#: Heading error to yaw rate, 1/s (a first-order turn toward the chosen direction).
YAW_GAIN_PER_S = 2.0
#: Arrived at a point goal within this, metres (horizontal).
ARRIVED_M = 0.5
#: A dead end is declared once it has been seen closed this long, seconds (one frame can be wrong).
DEAD_END_CONFIRM_S = 0.5


class Mode(str, enum.Enum):
    """What the planner is doing."""

    CRUISE = "cruise"  #: flying at the goal, or within 15° of it
    AVOID = "avoid"  #: steering round something, within 60° of the goal's direction
    DETOUR = "detour"  #: farther off the goal's direction, or turning to look
    HOLD = "hold"  #: a dead end, the goal reached or the flight stopped: the point held until the operator commands


#: The one transition table: (mode now, event) -> next mode. Events: "direct", "steer", "round"
#: (:func:`event_of`), "dead_end", "arrived", "stopped" (the service's progress watchdog) and "resumed"
#: (the operator's resume or new goal). HOLD is left only by "resumed" or a new engagement
#: (:meth:`LocalPlanner.engage`).
TRANSITIONS: dict[tuple[Mode, str], Mode] = {
    **{(m, "direct"): Mode.CRUISE for m in (Mode.CRUISE, Mode.AVOID, Mode.DETOUR)},
    **{(m, "steer"): Mode.AVOID for m in (Mode.CRUISE, Mode.AVOID, Mode.DETOUR)},
    **{(m, "round"): Mode.DETOUR for m in (Mode.CRUISE, Mode.AVOID, Mode.DETOUR)},
    **{(m, "dead_end"): Mode.HOLD for m in Mode},
    **{(m, "arrived"): Mode.HOLD for m in Mode},
    **{(m, "stopped"): Mode.HOLD for m in Mode},
    **{(m, "resumed"): Mode.CRUISE for m in Mode},
    **{(Mode.HOLD, e): Mode.HOLD for e in ("direct", "steer", "round")},
}


def speed_law(free_m: np.ndarray | float, cfg: PlannerConfig) -> np.ndarray | float:
    """The fastest speed that can still stop within ``free_m`` less ``stop_margin_m``: the root of
    ``v·t + v²/(2a) = d`` with ``t`` the latency and ``a`` the braking, capped at cruise, m/s (float or
    float64 array like ``free_m``)."""
    a, t = cfg.braking_accel_m_s2, cfg.latency_s
    d = np.maximum(np.asarray(free_m, dtype=np.float64) - cfg.stop_margin_m, 0.0)
    v = a * (-t + np.sqrt(t * t + 2.0 * d / a))
    out = np.minimum(v, cfg.cruise_speed_m_s)
    return float(out) if np.ndim(out) == 0 else out


def stopping_m(speed_m_s: float, cfg: PlannerConfig) -> float:
    """The length :func:`speed_law` keeps free ahead of a vehicle at ``speed_m_s``: its latency's run,
    braking at ``braking_accel_m_s2``, and ``stop_margin_m``, metres (the law's inverse below cruise)."""
    return speed_m_s * cfg.latency_s + speed_m_s * speed_m_s / (2.0 * cfg.braking_accel_m_s2) + cfg.stop_margin_m


def return_climb(below_goal_m: float, speed_m_s: float, cfg: PlannerConfig) -> float:
    """The climb back to the goal's altitude from ``below_goal_m`` metres below it (negative: above),
    radians (positive up), within half ``max_climb_deg``: over the distance flown at ``speed_m_s``
    (horizontal, m/s) in :data:`ALTITUDE_RETURN_S`, so that the altitude error decays in that time
    whatever the speed (measured in distance at cruise, a vehicle that flew slowly round a cabinet
    came down at 0.1 m/s and met a door's lintel at the altitude it had climbed to). An autopilot
    in offboard velocity control holds a vertical speed, not a height (PX4 SITL drifted 0.4 m up in
    4 s under zero vertical speed), and a climb chosen to pass over something must be taken back
    once past it (PX4 SITL flights climbed 1.7 m over 10 m and stayed there, into the wall over a
    door), so the altitude is held on the position; slowly, since a climb or descent past something
    is the planner's to choose (a return over a second pulled a vehicle up under an overhead block
    it was passing). At a hover the climb is the cap's: any speed flown then returns at most that
    steeply."""
    lim = 0.5 * math.radians(cfg.max_climb_deg)
    return max(-lim, min(lim, math.atan2(below_goal_m, max(speed_m_s, 0.0) * ALTITUDE_RETURN_S)))


@dataclass(frozen=True)
class Snapshot:
    """What one tick sees (frozen).

    Attributes:
        now_s: time, seconds.
        position_ned_m, velocity_ned_m_s: float ``(3,)`` NED metres and m/s.
        yaw_rad: heading, radians clockwise from north.
        goal_ned_m: float ``(3,)`` the point to reach (its down is the altitude to keep), or None (the
            paper's flight: the fuzzy controller is the whole policy).
        decision: the newest fuzzy decision, or None before the first.
        view_half_rad: half the camera's horizontal view, radians (what counts as looked at).
        in_flight_ned_m_s: float ``(3,)`` the velocity the vehicle was last told to fly (the
            setpoint sent, as it moves it), NED m/s, or None (none yet). An autopilot follows a
            setpoint late: for a while it chases the one sent, whatever the planner chooses now.
    """

    now_s: float
    position_ned_m: np.ndarray
    velocity_ned_m_s: np.ndarray
    yaw_rad: float
    goal_ned_m: np.ndarray | None
    decision: Decision | None
    view_half_rad: float = math.radians(40.0)
    in_flight_ned_m_s: np.ndarray | None = None


@dataclass(frozen=True)
class Plan:
    """A tick's answer.

    Attributes:
        mode: :class:`Mode`.
        velocity_ned_m_s: float64 ``(3,)`` the velocity to fly, NED m/s.
        yaw_rate_deg_s: the turn, deg/s (positive clockwise).
        direction_ned: float64 ``(3,)`` unit, the chosen direction.
        free_m: the seen-free length along it, metres.
        reason: one line.
        candidates: float64 ``(K, 5)`` yaw rad, climb rad, free m, hoped-for m, cost (for plots).
    """

    mode: Mode
    velocity_ned_m_s: np.ndarray
    yaw_rate_deg_s: float
    direction_ned: np.ndarray
    free_m: float
    reason: str
    candidates: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 5)))


def costs(
    yaw: np.ndarray,
    climb: np.ndarray,
    hoped_m: np.ndarray,
    blocked: np.ndarray,
    goal_yaw: float,
    goal_climb: float,
    goal_dist_m: float,
    prev: tuple[float, float] | None,
    fuzzy: tuple[float, float] | None,
    visited: np.ndarray,
    motion: tuple[float, float, float] | None,
    cfg: PlannerConfig,
    way_yaw: float | None = None,
    way_left_m: np.ndarray | None = None,
) -> np.ndarray:
    """The one cost of each candidate (float64 ``(K,)``; lower is better): the weighted sum of

    * goal: turn from the way to the goal (``way_yaw``, the bearing of the way round the surfaces
      seen, :class:`~companion.core.planner.way.WayToGoal`; None: the goal's bearing) and from the
      goal's climb, per half turn;
    * time: the time to the goal along the candidate: its hoped-for length at the speed law's speed
      on it (plus :data:`CREEP_M_S`, so that a short length costs much but not infinitely), then the
      rest of the way at cruise (``way_left_m``, float ``(K,)`` m from each candidate's end round the
      surfaces seen; NaN or None: the straight line), or where the length ends at a surface (``blocked``) at that same speed; less the least possible, per time to fly the map range at cruise. One
      term for progress and for room: a way that must crawl is slow, a way round may be quicker;
    * clearance: 1 - hoped-for length / map range;
    * smooth: change from the last chosen direction, plus change from the direction of motion in
      proportion to the speed over cruise (per half turn): a lagging vehicle turns its velocity slowly,
      the faster the wider;
    * fuzzy: difference from the fuzzy controller's steer (per half turn);
    * visited: seconds already spent where the candidate leads (at most 1).
    """
    r = cfg.map_range_m
    cruise = cfg.cruise_speed_m_s
    toward = goal_yaw if way_yaw is None else way_yaw
    goal = (angle_diff(yaw, toward) + np.abs(climb - goal_climb)) / math.pi
    reach = np.minimum(hoped_m, goal_dist_m)
    # Distance left, in the plane of the candidate: law of cosines on the horizontal part.
    dh = reach * np.cos(climb)
    ang = angle_diff(yaw, goal_yaw)
    left = np.sqrt(np.maximum(goal_dist_m**2 + dh**2 - 2.0 * goal_dist_m * dh * np.cos(ang), 0.0))
    if way_left_m is not None:
        left = np.where(np.isfinite(way_left_m), way_left_m, left)
    v = speed_law(hoped_m, cfg) + CREEP_M_S
    # A way that ends at a surface leads no farther at its own speed: the rest is costed at it too.
    t_go = np.where(blocked, (reach + left) / v, reach / v + left / cruise)
    time = (t_go - goal_dist_m / cruise) / (r / cruise)
    clearance = 1.0 - np.minimum(hoped_m, r) / r
    smooth = 0.0 if prev is None else (angle_diff(yaw, prev[0]) + np.abs(climb - prev[1])) / math.pi
    if motion is not None:  # momentum: turning the velocity costs in proportion to the speed
        smooth = smooth + motion[2] / cruise * (angle_diff(yaw, motion[0]) + np.abs(climb - motion[1])) / math.pi
    steer = 0.0 if fuzzy is None else (angle_diff(yaw, fuzzy[0]) + np.abs(climb - fuzzy[1])) / math.pi
    return (
        cfg.weight_goal * goal
        + cfg.weight_time * time
        + cfg.weight_clearance * clearance
        + cfg.weight_smooth * smooth
        + cfg.weight_fuzzy * steer
        + cfg.weight_visited * np.minimum(visited, 1.0)
    )


def _cell_codes(north_east_m: np.ndarray) -> np.ndarray:
    """One int64 code per visited-memory cell of each point (float64 ``(N, 2)`` north, east m): the
    cell's north index in the high 32 bits, its east index in the low (each well within 2^31)."""
    keys = np.floor(north_east_m / VISITED_CELL_M).astype(np.int64)
    return (keys[:, 0] << 32) + (keys[:, 1] & 0xFFFFFFFF)


def event_of(turn_from_goal_rad: float, looking: bool) -> str:
    """The event a choice is: "direct" within 15° of the goal, "steer" within 60°, else "round"
    (and "round" while turning to look)."""
    if looking or turn_from_goal_rad > math.radians(60.0):
        return "round"
    return "direct" if turn_from_goal_rad <= math.radians(15.0) else "steer"


class LocalPlanner:
    """The planner's state for one flight: the mode, the last choice, where the camera looked and
    when, and the places flown through.

    Args:
        cfg: the planner section.
        radius_m: the vehicle's radius, metres.
    """

    def __init__(self, cfg: PlannerConfig, radius_m: float):
        self._set(cfg, radius_m)
        self.engage()

    def _set(self, cfg: PlannerConfig, radius_m: float) -> None:
        self.cfg = cfg
        self.radius_m = float(radius_m)
        n_yaw = max(4, int(round(360.0 / cfg.yaw_step_deg)))
        self._yaw_off = np.arange(n_yaw) * (2.0 * math.pi / n_yaw)
        self._climbs = np.linspace(-1.0, 1.0, N_CLIMBS) * math.radians(cfg.max_climb_deg)
        # Which candidates (yaw-major, as ``plan`` lays them) are level with the goal's altitude.
        self._level = np.broadcast_to(self._climbs == 0.0, (n_yaw, N_CLIMBS)).reshape(-1)
        self._swing: tuple[float, tuple[np.ndarray, np.ndarray, int]] | None = None  # (step_m, swing_profile)

    def reconfigure(self, cfg: PlannerConfig, radius_m: float) -> None:
        """New settings from the next tick (a live reload), the flight's mode, choice and places kept;
        where the looks are binned anew (``yaw_step_deg`` changed), no direction counts as looked at."""
        n_before = len(self._yaw_off)
        self._set(cfg, radius_m)
        if len(self._yaw_off) != n_before:
            self._looked_t = np.full(len(self._yaw_off), -np.inf)
            self._looked_from = np.zeros((len(self._yaw_off), 2))

    def engage(self) -> None:
        """Start a flight: forget the mode, the choice, the looks and the places."""
        self.mode = Mode.CRUISE
        self.reason = ""
        self._prev: tuple[float, float] | None = None  # the last choice: yaw, climb from "level" (rad)
        self._looked_t = np.full(len(self._yaw_off), -np.inf)  # per absolute yaw bin
        self._looked_from = np.zeros((len(self._yaw_off), 2))  # north, east m the bin was looked along from
        # The visited places: each cell's code (see _cell_codes), sorted, and its seconds flown in it.
        self._visited_codes = np.empty(0, dtype=np.int64)
        self._visited_s = np.empty(0, dtype=np.float64)
        self._last_t: float | None = None
        self._closed_since: float | None = None
        self._held_at: np.ndarray | None = None
        self._way = WayToGoal()

    def stop(self, reason: str) -> None:
        """Hold the point where the vehicle is from the next tick on (the service's progress watchdog),
        for ``reason``."""
        self.mode = TRANSITIONS[(self.mode, "stopped")]
        self.reason = reason

    def resume(self) -> None:
        """Leave a hold and plan again (the operator's resume or new goal), keeping what was learnt of
        the places and the looks: a dead end is declared again only once it is seen closed again."""
        self.mode = TRANSITIONS[(self.mode, "resumed")]
        self.reason = ""
        self._held_at = None
        self._closed_since = None

    def _bin(self, yaw: np.ndarray | float) -> np.ndarray:
        n = len(self._yaw_off)
        return np.round(np.asarray(yaw) % (2.0 * math.pi) / (2.0 * math.pi / n)).astype(np.int64) % n

    def _remember(self, snap: Snapshot) -> None:
        """Where the camera looks now, from where, and where the vehicle is (the visited places)."""
        looked = angle_diff(self._yaw_off, snap.yaw_rad) <= snap.view_half_rad
        self._looked_t[looked] = snap.now_s
        self._looked_from[looked] = snap.position_ned_m[:2]
        dt = 0.0 if self._last_t is None else max(0.0, min(snap.now_s - self._last_t, 0.5))
        self._last_t = snap.now_s
        code = _cell_codes(np.asarray(snap.position_ned_m, dtype=np.float64)[None, :2])[0]
        i = int(np.searchsorted(self._visited_codes, code))
        if i < len(self._visited_codes) and self._visited_codes[i] == code:
            self._visited_s[i] += dt
        else:  # a cell entered for the first time (a few a second at most)
            self._visited_codes = np.insert(self._visited_codes, i, code)
            self._visited_s = np.insert(self._visited_s, i, dt)

    def _visited_at(self, points: np.ndarray) -> np.ndarray:
        """Seconds flown in the cell of each of ``points`` (float64 ``(N, 3)`` NED m) → float64 ``(N,)``."""
        codes = _cell_codes(points[:, :2])
        known = self._visited_codes
        if len(known) == 0:
            return np.zeros(len(points))
        i = np.minimum(np.searchsorted(known, codes), len(known) - 1)
        return np.where(known[i] == codes, self._visited_s[i], 0.0)

    def plan(self, snap: Snapshot, lmap: LocalMap) -> Plan:
        """One tick (see the module doc)."""
        cfg = self.cfg
        self._remember(snap)
        pos = np.asarray(snap.position_ned_m, dtype=np.float64)
        if self.mode is Mode.HOLD:
            return self._hold(self.reason, pos, lmap)
        # The goal: a point, or (none) the fuzzy controller's steer from the heading.
        d = snap.decision
        fuzzy = None
        if d is not None and d.kind is not DecisionKind.BRAKE:
            fuzzy = (snap.yaw_rad + d.yaw * math.radians(cfg.fuzzy_yaw_deg), d.pitch * math.radians(cfg.max_climb_deg))
        if snap.goal_ned_m is None:
            if fuzzy is None:
                return self._stop("the fuzzy controller brakes (no goal: it is the whole policy)")
            goal_yaw, goal_dist = fuzzy[0], cfg.map_range_m
            goal_climb = fuzzy[1]
        else:
            g = np.asarray(snap.goal_ned_m, dtype=np.float64)
            goal_dist = math.hypot(g[0] - pos[0], g[1] - pos[1])
            if goal_dist < ARRIVED_M:
                self.mode = TRANSITIONS[(self.mode, "arrived")]
                self.reason = "arrived at the goal"
                return self._hold(self.reason, pos, lmap)
            goal_yaw = math.atan2(g[1] - pos[1], g[0] - pos[0])
            # The speed flown: the larger of the measured and the commanded (the vehicle lags the
            # command, and at the command's speed a climb set from the lagging one returns too fast).
            flown = math.hypot(*snap.velocity_ned_m_s[:2])
            if snap.in_flight_ned_m_s is not None:
                flown = max(flown, math.hypot(*snap.in_flight_ned_m_s[:2]))
            goal_climb = return_climb(float(pos[2] - g[2]), flown, cfg)
            # The way keeps the stop margin beyond the radius off surfaces where the gap allows.
            self._way.update(lmap, g, float(pos[2]), cfg.floor_m, cfg.ceiling_m, lmap.radius_m + cfg.stop_margin_m)
        # The climbs are laid round the goal's: "level" is the way back to the goal's altitude, so
        # that the map judges that way too (it must not descend onto a wall it is passing over).
        lim = math.radians(cfg.max_climb_deg)
        base = goal_climb if snap.goal_ned_m is not None else 0.0  # within half the steepest: both ways stay
        # "Level" is that way for every term that compares climbs: the fuzzy controller's pitch steers
        # up or down from it, and the last choice is kept relative to it (else, when the way back
        # steepens as the vehicle slows, a level line kept or steered to would cost less than it).
        if fuzzy is not None:
            fuzzy = (fuzzy[0], fuzzy[1] + base)
        prev = None if self._prev is None else (self._prev[0], self._prev[1] + base)
        yaw = (goal_yaw + self._yaw_off)[:, None] * np.ones((1, N_CLIMBS))
        climb = np.ones((len(self._yaw_off), 1)) * np.clip(base + self._climbs, -lim, lim)[None, :]
        yaw, climb = yaw.reshape(-1), climb.reshape(-1)
        dirs = directions(yaw, climb)
        fl = lmap.free_lengths(pos, dirs)
        free = fl.length_m.copy()
        # The band between floor and ceiling bounds a climb's length like a surface does.
        to_edge = to_band(pos, dirs, cfg.floor_m, cfg.ceiling_m)
        band_cut = to_edge < free
        free = np.minimum(free, to_edge)
        # A climb cut by the ceiling ends there, closed (no way over a wall that high). A descent cut
        # by the floor levels off and flies on along it: the floor bounds the height, it is no surface
        # to stop at (the floor filter takes the descent off over the last metre). That bent path is
        # the candidate: its length and whether it ends at a surface (a wall down to the ground) or
        # passes on (under an overhead block), scored and flown at the speed law's speed on it, as the
        # safety chain judges a descent. Braked toward the floor as toward a wall, a vehicle passing
        # under a block slowed on every descent to it.
        path = free.copy()
        knee = np.full(len(free), np.inf)  # where each path leaves its line (m), and its direction on
        onward = dirs.copy()
        bend_at_floor(lmap, pos, yaw, dirs, to_edge, band_cut, path, knee, onward)
        levels = np.isfinite(knee)
        free = np.where(levels, path, free)
        blocked = np.where(levels, band_cut, fl.blocked | band_cut)
        blocked_line = blocked  # on the candidates' own paths (the swing below widens ``blocked``)
        bins = self._bin(yaw)
        moved = np.hypot(*(self._looked_from[bins] - pos[None, :2]).T)
        unlooked = (snap.now_s - self._looked_t[bins] > cfg.look_memory_s) | (moved > LOOKED_FROM_M)
        v = np.asarray(snap.velocity_ned_m_s, dtype=np.float64)
        sp = float(np.linalg.norm(v))
        motion = None
        if sp > 0.3:
            motion = (math.atan2(v[1], v[0]), math.asin(max(-1.0, min(1.0, -v[2] / sp))), min(sp, cfg.cruise_speed_m_s))

        way_yaw = self._way.bearing(pos) if snap.goal_ned_m is not None else None
        if way_yaw is not None and angle_diff(way_yaw, goal_yaw) > math.radians(cfg.dead_end_cone_deg):
            # A way that leads back beyond the dead end's cone is a closed pocket's: it is held (below),
            # not flown out of; the operator chooses.
            way_yaw = None
        if way_yaw is not None:
            # A level line that ends at a surface short of the goal leads on along the way round it.
            blocked = blocked.copy()
            may_bend = self._level & ~band_cut
            bend_onto_way(
                lmap, self._way, pos, yaw, dirs, may_bend, way_yaw, goal_dist, cfg.stop_margin_m, blocked, path, knee, onward
            )

        # What lies where each candidate leads, by its hoped-for length: the seconds already flown there
        # and the way left from its end (from a cube short of it: a line ends at a surface's radius).
        # Kept between the two scorings, and looked up again only where the length changed.
        led_to: dict[str, np.ndarray] = {}

        def look_up(hoped: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
            at = np.flatnonzero(hoped != led_to["hoped"]) if led_to else slice(None)
            h, d, kn, on = hoped[at], dirs[at], knee[at], onward[at]
            visited = led_to["visited"].copy() if led_to else np.empty(len(hoped))
            visited[at] = self._visited_at(along(pos, d, kn, on, np.minimum(h, VISITED_LOOKAHEAD_M)))
            way_left = None
            if way_yaw is not None:
                way_left = led_to["way_left"].copy() if led_to else np.empty(len(hoped))
                way_left[at] = self._way.length_at(along(pos, d, kn, on, np.maximum(np.minimum(h, goal_dist) - lmap.voxel_m, 0.0)))
                led_to["way_left"] = way_left
            led_to["hoped"], led_to["visited"] = hoped, visited
            return visited, way_left

        def score(
            free: np.ndarray, path: np.ndarray, blocked: np.ndarray, swung: np.ndarray | bool = False
        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            # Hoped-for length: unknown space not looked at lately is worth a look.
            hopeful = unlooked & ~blocked & ~swung & ~fl.horizon
            hoped = np.where(hopeful, np.maximum(path, 0.5 * cfg.map_range_m), path)
            visited, way_left = look_up(hoped)
            c = costs(
                yaw, climb, hoped, blocked & (free < goal_dist), goal_yaw, goal_climb, goal_dist, prev, fuzzy,
                visited, motion, cfg, way_yaw, way_left,
            )
            # A candidate the speed law cannot fly (within the stop margin, or not a cube's length) is
            # out, unless hoped for: chosen, the vehicle would hover facing what it already sees, and
            # the same frames would choose it again.
            short = free < max(lmap.voxel_m, cfg.stop_margin_m + 1e-9)
            return hopeful, hoped, np.where(short & ~hopeful, np.inf, c)

        hopeful, hoped, c = score(free, path, blocked)
        # The path the vehicle will fly (its velocity lags the command), for the cheapest candidates:
        # a swing that enters a surface's inflation shortens the candidate like a surface on its line,
        # so that a sharp turn at speed costs speed, not clearance. The others cost more already, and
        # a swing only shortens.
        top = np.argsort(c)[:SWING_CANDIDATES]
        top = top[np.isfinite(c[top])]
        if len(top):
            clear = np.full(len(free), np.inf)
            clear[top] = self.swing_clear(lmap, pos, v, snap.in_flight_ned_m_s, dirs[top], speed_law(free[top], cfg))
            swung = clear < free
            if np.any(swung):
                # Swung short, the way still leads on once slower: its time is the short length at
                # the low speed, then the rest at cruise (not the rest at the low speed, as past a
                # surface on the line).
                free = np.where(swung, clear, free)
                hopeful, hoped, c = score(free, np.minimum(path, clear), blocked, swung)
                blocked = blocked | swung
        table = np.stack([yaw, climb, free, hoped, c], axis=1)
        # A dead end: every direction within the cone of the goal's is closed short by surfaces seen,
        # and no way round them leads on within the cone (a door off the line is no dead end, nor a
        # fence's end beside a gap, though every straight line from here meets a surface's radius).
        in_cone = angle_diff(yaw, goal_yaw) <= math.radians(cfg.dead_end_cone_deg)
        # On the lines themselves (a swing at speed is no dead end).
        closed = in_cone & (path < cfg.dead_end_free_m) & (blocked_line | ~unlooked)
        if snap.goal_ned_m is not None and way_yaw is None and np.all(closed[in_cone]):
            if self._closed_since is None:
                self._closed_since = snap.now_s
            if snap.now_s - self._closed_since >= DEAD_END_CONFIRM_S:
                self.mode = TRANSITIONS[(self.mode, "dead_end")]
                self.reason = (
                    f"dead end: no direction within {cfg.dead_end_cone_deg:.0f} deg of the goal is free for "
                    f"{cfg.dead_end_free_m:.1f} m, nor does a way round what was seen lead on within them"
                )
                return self._hold(self.reason, pos, lmap)
        else:
            self._closed_since = None
        if not np.any(np.isfinite(c)):
            return self._stop("no direction free for a cube's length")
        i = int(np.argmin(c))
        self._prev = (float(yaw[i]), float(climb[i]) - base)
        speed = float(speed_law(free[i], cfg))
        u = dirs[i]
        vel = u * speed
        vmax = cfg.max_vertical_speed_m_s
        if abs(vel[2]) > vmax:
            vel = vel * (vmax / abs(vel[2]))
        err = float((yaw[i] - snap.yaw_rad + math.pi) % (2.0 * math.pi) - math.pi)
        rate = max(-cfg.max_yaw_rate_deg_s, min(cfg.max_yaw_rate_deg_s, math.degrees(YAW_GAIN_PER_S * err)))
        looking = bool(hopeful[i]) and free[i] < cfg.dead_end_free_m
        turn = float(angle_diff(yaw[i], goal_yaw))
        self.mode = TRANSITIONS[(self.mode, event_of(turn, looking))]
        self.reason = (
            f"{'looking' if looking else 'flying'} {math.degrees(turn):.0f} deg off the goal, climb "
            f"{math.degrees(climb[i]):.0f} deg, {free[i]:.1f} m seen free, {speed:.1f} m/s"
        )
        return Plan(self.mode, vel, rate, u, float(free[i]), self.reason, table)

    def swing_clear(
        self, lmap: LocalMap, pos: np.ndarray, velocity_ned_m_s: np.ndarray, in_flight_ned_m_s: np.ndarray | None,
        dirs: np.ndarray, speeds_m_s: np.ndarray,
    ) -> np.ndarray:
        """How far the vehicle at ``pos`` (float ``(3,)`` NED m) flies toward each command ``dirs ·
        speeds_m_s`` (unit NED ``(K, 3)``, m/s ``(K,)``) before its centre enters a surface's inflation,
        float64 ``(K,)`` arc metres (inf: never, within the map's range): its path swings from its
        velocity (float ``(3,)`` NED m/s) onto the command
        (:func:`~companion.core.planner.paths.predicted_paths`), judged from that velocity and from the
        one it was last told to fly (``in_flight_ned_m_s``, None: none yet), which it chases until the
        autopilot's delay has passed: the vehicle lies between the two. The safety chain asks it too."""
        cfg = self.cfg
        starts = np.asarray(velocity_ned_m_s, dtype=np.float64)[None, :]
        if in_flight_ned_m_s is not None:
            starts = np.concatenate([starts, np.asarray(in_flight_ned_m_s, dtype=np.float64)[None, :]])
        if self._swing is None or self._swing[0] != lmap.voxel_m:
            self._swing = (lmap.voxel_m, swing_profile(cfg, lmap.voxel_m))
        t, lag, tail = self._swing[1]
        return lmap.clear_along(pos, starts, dirs, speeds_m_s, t, lag, tail, cfg.map_range_m)

    def _hold(self, reason: str, pos: np.ndarray, lmap: LocalMap) -> Plan:
        """Hold the point where the hold began (:meth:`_hold_point`): back toward it at
        HOLD_GAIN_PER_S times the distance (the position estimate's drift moves a vehicle that is only
        told zero velocity)."""
        if self._held_at is None:
            self._held_at = self._hold_point(pos, lmap)
        back = -HOLD_GAIN_PER_S * (pos - self._held_at)
        n = float(np.linalg.norm(back))
        if n > HOLD_MAX_M_S:
            back *= HOLD_MAX_M_S / n
        return Plan(Mode.HOLD, back, 0.0, np.zeros(3), 0.0, reason)

    def _hold_point(self, pos: np.ndarray, lmap: LocalMap) -> np.ndarray:
        """Where to hold, from ``pos`` (float ``(3,)`` NED m): there, unless a body there is within the
        vehicle's radius of a surface seen (a stop that ended late). Then just out of it, by the
        shortest level way out that the map leaves free from here (judged from inside: the way out is
        open, the way in is not; of equally short ones, the one leading farthest free). PX4 SITL
        flights held a dead end declared 0.3 m from a wall and crept on into it at 0.1 m/s while told
        to hold that point: its velocity loop winds down over seconds, and a hold begun inside the
        radius has no room for that."""
        if not bool(lmap.within_radius(pos)):
            return pos.copy()
        dirs = directions(self._yaw_off, np.zeros(len(self._yaw_off)))
        free = lmap.free_lengths(pos, dirs).length_m
        s = np.arange(1, int(math.ceil(self.radius_m / lmap.voxel_m)) + 3) * lmap.voxel_m  # out to radius + 2 cubes
        within = lmap.within_radius(pos + dirs[:, None, :] * s[None, :, None])  # (K, S)
        out_at = np.where(within.all(axis=1), np.inf, s[np.argmin(within, axis=1)])
        ok = np.isfinite(out_at) & (free >= out_at)
        if not np.any(ok):
            return pos.copy()  # boxed in: hold here
        k = int(np.lexsort((-free, np.where(ok, out_at, np.inf)))[0])
        return pos + dirs[k] * float(out_at[k])

    def _stop(self, reason: str) -> Plan:
        self.reason = reason
        return Plan(self.mode, np.zeros(3), 0.0, np.zeros(3), 0.0, reason)
