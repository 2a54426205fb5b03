"""Procedural, seeded obstacle courses: the worlds the simulator flies the pipeline through.

Every course is a :class:`Course`: a :class:`~companion.sim.render.Scene` (textured boxes and pillars
on a textured ground, closed by a textured backdrop; the geometry is the ground truth for collisions
and clearance), a start pose, a goal region, bounds, a time limit and whether holding safely counts
as a success. Course ``kind`` + ``seed`` determine everything (same pair, same course).

All courses start at the origin heading north at ``START_ALTITUDE_M``; the goal is to pass a north
coordinate within the course's east bounds. Kinds (:data:`COURSE_KINDS`):

* ``corridor``: a walled corridor with boxes of random size, yaw and lateral position; every box
  leaves a gap of at least 1.5 m on one side.
* ``doorway``: a wall across the course with one door, 1.1 to 1.6 m wide and 2.1 m high, its centre
  up to 0.25 m off the start line (the paper's narrow passage, Fig. 10).
* ``forest``: 12 to 16 pillars (radius 0.1 to 0.3 m, centres at least 1.2 m + both radii apart)
  between 4 and 15 m north, 3.5 m either side of the line.
* ``pitch``: a barrier across the whole view that needs a pitch escape: even seeds a low wall (top
  0.15 to 0.45 m above the vehicle's bottom: climb over it), odd seeds a high block (bottom 0.2 to
  0.45 m below the vehicle's top: descend under it).
* ``side``: a long block reaching in from one side, its inner corner 0.03 to 0.2 m inside the
  vehicle's swept width: the obstacle stays in a side region until it is close (the paper's
  failure case, Fig. 11).
* ``deadend``: a closed channel 1.6 to 3 m wide that the vehicle starts 2 m inside; the goal lies
  beyond its end wall and the way out is behind, so the right answer is to brake and hold (holding
  counts as success).
* ``office``: the hard surfaces real stereo fails on: a room of plain painted walls (nearly
  textureless, some glossy, with a lamp's glare), a see-through fence of thin bars (a room divider)
  reaching across the line, a plain cabinet, a radiator's fins under a window, and a door in the
  far wall to fly through.
* ``detour``: a wall 20 m wide (wider than the view) and 3 m high across the course, 2.5 to 3 m
  ahead, with one opening 1.5 to 1.9 m wide whose middle lies 3 m to one side of the start line:
  at the start its middle is beyond the camera's ±45° (on the left, beyond the 26° that block
  matching measures at all). The reactive controller only brakes in front of it; the way is round
  (the local planner's detour mode, :mod:`companion.core.planner`). Holding is a failure here.

Pure: no clocks, no files; geometry in NED metres (x north, y east, z down; altitude = -z).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from companion.sim.render import Box, Obstacle, Pillar, Pose, Scene, Surface
from companion.errors import InputError

#: Course kinds, in the order the suite and the tables list them.
COURSE_KINDS: tuple[str, ...] = ("corridor", "doorway", "forest", "pitch", "side", "deadend", "office", "detour")
#: Altitude every course starts at, metres.
START_ALTITUDE_M = 1.5
#: The goal point the vehicle is sent to lies this far past the goal line, metres.
GOAL_POINT_BEYOND_M = 1.0
_KIND_ID = {name: i + 1 for i, name in enumerate(COURSE_KINDS)}
_KIND_ID["detour"] = 21  # fixed, whatever its place in COURSE_KINDS: its courses stay the same


@dataclass(frozen=True)
class Course:
    """One course.

    Attributes:
        kind: one of :data:`COURSE_KINDS` (or ``head-on``, the test course).
        seed: the seed it was generated from (also seeds textures, noise and exposure).
        scene: the world (ground truth).
        start: start pose of the vehicle (level, at rest).
        goal_north_m: the goal is reached when the vehicle's centre passes this north coordinate...
        goal_east_m: ...with its east coordinate inside this (low, high) range, metres (the course's
            east bounds: passing the line anywhere counts).
        bounds_min_ned_m, bounds_max_ned_m: the box the vehicle must stay inside (NED, metres; z is
            down, so ``bounds_min_ned_m[2]`` is minus the highest allowed altitude).
        time_limit_s: simulated time after which the flight is a timeout, seconds.
        hold_is_success: whether holding safely counts as a success.
        description: one line with the course's random parameters.
    """

    kind: str
    seed: int
    scene: Scene
    start: Pose
    goal_north_m: float
    goal_east_m: tuple[float, float]
    bounds_min_ned_m: tuple[float, float, float]
    bounds_max_ned_m: tuple[float, float, float]
    time_limit_s: float
    hold_is_success: bool
    description: str

    @property
    def name(self) -> str:
        """``{kind}-{seed}``: the course kind and its seed."""
        return f"{self.kind}-{self.seed}"

    @property
    def goal_point_ned_m(self) -> tuple[float, float, float]:
        """The goal as a point for the service (``engage`` with a goal): 1 m past the goal line, on
        the start line, at the start altitude, NED metres in the course frame."""
        return (self.goal_north_m + GOAL_POINT_BEYOND_M, 0.0, self.start.position_ned_m[2])

    def in_goal(self, position_ned_m: np.ndarray) -> bool:
        """Whether a position (float ``(3,)`` NED metres) is in the goal region."""
        n, e = float(position_ned_m[0]), float(position_ned_m[1])
        return n >= self.goal_north_m and self.goal_east_m[0] <= e <= self.goal_east_m[1]

    def started_at(self, start: Pose, clearance_m: float) -> Course:
        """This course flown from ``start`` instead of its own start pose (to replay a moment of a
        SITL or field flight where it went wrong); the goal line stays where it was (the goal as a
        point, :attr:`goal_point_ned_m`, takes the new start's altitude).

        Args:
            start: the new start pose (level, at rest; pitch and roll are ignored).
            clearance_m: the start must be at least this far from every obstacle and the ground,
                metres (the vehicle's collision radius).

        Raises:
            InputError: the start lies outside the course bounds, or nearer an obstacle than
                ``clearance_m`` (the message says how near).
        """
        n, e, d = start.position_ned_m
        at = np.array([n, e, d], dtype=np.float64)
        if not self.in_bounds(at):
            lo, hi = self.bounds_min_ned_m, self.bounds_max_ned_m
            raise InputError(
                f"start N {n:.2f} m, E {e:+.2f} m, altitude {-d:.2f} m is outside {self.name}'s bounds "
                f"(N {lo[0]:.1f}..{hi[0]:.1f} m, E {lo[1]:.1f}..{hi[1]:.1f} m, altitude up to {-lo[2]:.1f} m)"
            )
        gap = float(self.scene.distance_to_obstacles_m(at, include_ground=True))
        if gap < clearance_m:
            raise InputError(
                f"start N {n:.2f} m, E {e:+.2f} m, altitude {-d:.2f} m is {gap:.2f} m from an obstacle "
                f"in {self.name}; the vehicle needs {clearance_m:.2f} m"
            )
        return dataclasses.replace(self, start=Pose(position_ned_m=(n, e, d), yaw_rad=start.yaw_rad))

    def in_bounds(self, position_ned_m: np.ndarray) -> bool:
        """Whether a position (float ``(3,)`` NED metres) is inside the course bounds."""
        p = np.asarray(position_ned_m, dtype=np.float64)
        return bool(np.all(p >= np.asarray(self.bounds_min_ned_m)) and np.all(p <= np.asarray(self.bounds_max_ned_m)))


def _rng(kind: str, seed: int) -> np.random.Generator:
    return np.random.default_rng([seed, _KIND_ID[kind], 0x5C0])


def _course(
    kind: str,
    seed: int,
    obstacles: list[Obstacle],
    goal_north_m: float,
    half_width_m: float,
    description: str,
    *,
    hold_is_success: bool = True,
    max_altitude_m: float = 5.0,
    north_extent_m: float | None = None,
    light_ned_m: tuple[float, float, float] | None = None,
) -> Course:
    length = north_extent_m if north_extent_m is not None else goal_north_m + 2.0
    scene = Scene(
        obstacles=tuple(obstacles),
        ground=True,
        backdrop_centre_ne_m=(0.5 * length, 0.0),
        backdrop_half_size_m=0.5 * length + 30.0,
        sky_altitude_m=30.0,
        light_ned_m=light_ned_m,
    )
    # Time for the nominal path at 1 m/s (the default cruise), with room for detours and slowing.
    time_limit = max(30.0, 3.0 * goal_north_m + 10.0)
    return Course(
        kind=kind,
        seed=seed,
        scene=scene,
        start=Pose.at(0.0, 0.0, START_ALTITUDE_M),
        goal_north_m=goal_north_m,
        goal_east_m=(-half_width_m - 2.0, half_width_m + 2.0),
        bounds_min_ned_m=(-5.0, -half_width_m - 2.0, -max_altitude_m),
        bounds_max_ned_m=(length + 3.0, half_width_m + 2.0, 0.0),
        time_limit_s=time_limit,
        hold_is_success=hold_is_success,
        description=description,
    )


def corridor_course(seed: int) -> Course:
    """A walled corridor (4 to 5 m wide, 3 m walls) with 3 to 4 boxes, each passable on one side."""
    rng = _rng("corridor", seed)
    width = float(rng.uniform(4.0, 5.0))
    half = 0.5 * width
    n = int(rng.integers(3, 5))
    goal = 6.0 + 4.5 * n
    obstacles: list[Obstacle] = [
        Box.on_ground(0.5 * goal + 1.0, -half - 0.15, (goal + 6.0, 0.3, 3.0)),
        Box.on_ground(0.5 * goal + 1.0, half + 0.15, (goal + 6.0, 0.3, 3.0)),
    ]
    boxes = []
    for i in range(n):
        north = 5.0 + 4.5 * i + float(rng.uniform(-0.5, 0.5))
        depth, wide, height = float(rng.uniform(0.5, 1.0)), float(rng.uniform(0.6, 1.6)), float(rng.uniform(1.7, 3.0))
        # Every other box head-on (within 0.3 m of the line), the others anywhere with a 1.5 m gap.
        if i % 2 == 0:
            east = float(rng.uniform(-0.3, 0.3))
        else:
            east = float(rng.uniform(-half + 0.5 * wide, half - 0.5 * wide))
        gap = max(east - 0.5 * wide + half, half - east - 0.5 * wide)
        if gap < 1.5:  # slide it toward the nearer wall until one side has 1.5 m
            east = -half + 1.5 + 0.5 * wide if east > 0 else half - 1.5 - 0.5 * wide
        yaw = float(rng.uniform(-0.4, 0.4))
        obstacles.append(Box.on_ground(north, east, (depth, wide, height), yaw))
        boxes.append(f"{north:.1f}/{east:+.2f}")
    return _course(
        "corridor", seed, obstacles, goal, half - 0.3,
        f"corridor {width:.1f} m wide, {n} boxes at north/east {', '.join(boxes)} m",
    )


def doorway_course(seed: int) -> Course:
    """A wall across the course with one door (paper Fig. 10)."""
    rng = _rng("doorway", seed)
    wall_north = float(rng.uniform(6.0, 8.0))
    door_w = float(rng.uniform(1.1, 1.6))
    door_e = float(rng.uniform(-0.25, 0.25))
    door_h, wall_h, thick, span = 2.1, 3.0, 0.2, 8.0
    left_w = (door_e - 0.5 * door_w) + span
    right_w = span - (door_e + 0.5 * door_w)
    obstacles: list[Obstacle] = [
        Box.on_ground(wall_north, -span + 0.5 * left_w, (thick, left_w, wall_h)),
        Box.on_ground(wall_north, span - 0.5 * right_w, (thick, right_w, wall_h)),
        Box((wall_north, door_e, -0.5 * (door_h + wall_h)), (thick, door_w, wall_h - door_h)),
    ]
    goal = wall_north + 3.0
    return _course(
        "doorway", seed, obstacles, goal, span - 1.0,
        f"wall at {wall_north:.1f} m, door {door_w:.2f} m wide centred {door_e:+.2f} m east",
    )


def forest_course(seed: int) -> Course:
    """Pillars scattered between 4 and 15 m north, 3.5 m either side of the line; surfaces at least
    1.2 m apart."""
    rng = _rng("forest", seed)
    goal = 18.0
    pillars: list[tuple[float, float, float]] = []
    tries = 0
    target = int(rng.integers(12, 17))
    while len(pillars) < target and tries < 2000:
        tries += 1
        n, e = float(rng.uniform(4.0, 15.0)), float(rng.uniform(-3.5, 3.5))
        r = float(rng.uniform(0.1, 0.3))
        if all(math.hypot(n - pn, e - pe) >= 1.2 + r + pr for pn, pe, pr in pillars):
            pillars.append((n, e, r))
    obstacles: list[Obstacle] = [
        Pillar.on_ground(n, e, r, float(rng.uniform(3.0, 5.0)), sides=12) for n, e, r in pillars
    ]
    return _course(
        "forest", seed, obstacles, goal, 6.0,
        f"{len(pillars)} pillars (radius 0.1-0.3 m) between 4 and 15 m north",
    )


def pitch_course(seed: int) -> Course:
    """A barrier across the view: a low wall to climb over (even seeds) or a high block to pass
    under (odd seeds)."""
    rng = _rng("pitch", seed)
    north = float(rng.uniform(5.0, 7.0))
    depth = float(rng.uniform(0.4, 1.0))
    span = 16.0
    radius = 0.25  # the default collision radius: offsets below are relative to the vehicle's body
    if seed % 2 == 0:
        top = START_ALTITUDE_M - radius + float(rng.uniform(0.15, 0.45))
        obstacles: list[Obstacle] = [Box.on_ground(north, 0.0, (depth, span, top))]
        what = f"low wall, top at {top:.2f} m"
    else:
        bottom = START_ALTITUDE_M + radius - float(rng.uniform(0.2, 0.45))
        top = 4.0
        obstacles = [Box((north, 0.0, -0.5 * (bottom + top)), (depth, span, top - bottom))]
        what = f"overhead block, bottom at {bottom:.2f} m"
    return _course(
        "pitch", seed, obstacles, north + depth + 4.0, 0.5 * span - 1.0,
        f"{what}, {depth:.2f} m deep at {north:.1f} m north",
    )


def side_course(seed: int) -> Course:
    """A long block reaching in from one side, its inner corner just inside the vehicle's swept
    width (paper Fig. 11: the obstacle sits in a side region until it is close)."""
    rng = _rng("side", seed)
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    north = float(rng.uniform(5.0, 7.0))
    inside = float(rng.uniform(0.03, 0.2))  # how far the corner reaches into the swept width
    edge = side * (0.25 - inside)  # east of the inner corner (the default radius is 0.25 m)
    depth, reach = float(rng.uniform(0.8, 2.0)), 3.0
    obstacles: list[Obstacle] = [Box.on_ground(north + 0.5 * depth, edge + side * 0.5 * reach, (depth, reach, 3.0))]
    return _course(
        "side", seed, obstacles, north + depth + 4.0, 5.0,
        f"block from the {'right' if side > 0 else 'left'}, corner at {edge:+.2f} m east, {north:.1f} m north",
    )


def deadend_course(seed: int) -> Course:
    """A closed channel the vehicle starts in; the goal lies beyond its end wall, and the way out is
    behind: the right answer is to brake and hold.

    The vehicle starts 2 m inside the channel. A channel that begins ahead of it is no dead end: with
    room round its outside, the way to the goal is round it (as round the detour course's wall).
    """
    rng = _rng("deadend", seed)
    width = float(rng.uniform(1.6, 3.0))
    end = float(rng.uniform(6.0, 9.0))
    half = 0.5 * width
    height, entry = 3.0, -2.0
    length = end - entry
    obstacles: list[Obstacle] = [
        Box.on_ground(entry + 0.5 * length, -half - 0.15, (length, 0.3, height)),
        Box.on_ground(entry + 0.5 * length, half + 0.15, (length, 0.3, height)),
        Box.on_ground(end + 0.15, 0.0, (0.3, width + 0.6, height)),
    ]
    return _course(
        "deadend", seed, obstacles, end + 2.0, 3.0,
        f"channel {width:.2f} m wide, closed at {end:.1f} m north",
        north_extent_m=end + 4.0,
    )


def office_course(seed: int) -> Course:
    """An office of hard surfaces: plain walls (grain 1.5 to 3 grey levels, the far one glossy under
    a ceiling lamp), a see-through fence of bars (period 8 to 12.5 cm) from one side wall across the
    line, a plain cabinet, a radiator's fins under a window, and a door in the far wall, within
    0.25 m of the line (the goal lies beyond it)."""
    # Its own stream, not _rng's: the kind's id there is its place in COURSE_KINDS, which a kind
    # added beside it in parallel could change (and with it every office course).
    rng = np.random.default_rng([seed, 0x0FF1CE, 0x5C0])
    width = float(rng.uniform(4.0, 5.0))
    half = 0.5 * width
    height, thick = 3.0, 0.2
    fence_n = float(rng.uniform(4.0, 5.5))
    end_n = fence_n + float(rng.uniform(5.5, 6.5))
    wall = [Surface("plain", grain_grey=float(rng.uniform(1.5, 3.0))) for _ in range(2)]
    gloss = float(rng.choice([0.0, 60.0, 110.0]))
    end_surface = Surface("plain", grain_grey=float(rng.uniform(1.5, 3.0)), gloss=gloss)
    length = end_n + 1.0
    obstacles: list[Obstacle] = [
        Box.on_ground(0.5 * end_n - 0.5, -half - 0.5 * thick, (length, thick, height), surface=wall[0]),
        Box.on_ground(0.5 * end_n - 0.5, half + 0.5 * thick, (length, thick, height), surface=wall[1]),
    ]
    # The far wall with its door (1.1 to 1.4 m wide, 2.1 m high, on the line as in doorway) and the
    # door leaf open beyond it. On the line: the controller is reactive and flies back to the line
    # after a detour, so a door well off it is a dead end whatever the stereo sees.
    door_w = float(rng.uniform(1.1, 1.4))
    door_e = float(rng.uniform(-0.25, 0.25))
    door_h = 2.1
    wall_n = end_n + 0.5 * thick
    left_w = door_e - 0.5 * door_w + half + 0.3
    right_w = half + 0.3 - (door_e + 0.5 * door_w)
    obstacles += [
        Box.on_ground(wall_n, -half - 0.3 + 0.5 * left_w, (thick, left_w, height), surface=end_surface),
        Box.on_ground(wall_n, half + 0.3 - 0.5 * right_w, (thick, right_w, height), surface=end_surface),
        Box((wall_n, door_e, -0.5 * (door_h + height)), (thick, door_w, height - door_h), surface=end_surface),
    ]
    hinge = 1.0 if rng.uniform() < 0.5 else -1.0
    leaf_e = door_e + hinge * (0.5 * door_w + 0.03)
    obstacles.append(
        Box.on_ground(end_n + thick + 0.45 * door_w, leaf_e, (0.9 * door_w, 0.04, 2.0), surface=Surface("plain"))
    )
    # The fence: thin bars from one side wall, its free end (a post) up to 0.5 m across the line.
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    free_e = -side * float(rng.uniform(0.0, 0.5))
    span = abs(side * half - free_e)
    period = float(rng.choice([0.08, 0.1, 0.125]))
    bars = Surface("bars", bar_period_m=period, bar_width_m=float(rng.uniform(0.02, 0.03)))
    fence_h = 2.5
    mid_e = 0.5 * (side * half + free_e)
    obstacles += [
        Box.on_ground(fence_n, mid_e, (0.02, span, fence_h), surface=bars),
        Box((fence_n, mid_e, -fence_h - 0.025), (0.05, span, 0.05), surface=Surface("plain")),  # top rail
        Box.on_ground(fence_n, free_e - side * 0.03, (0.06, 0.06, fence_h + 0.05), surface=Surface("plain")),
    ]
    # A plain cabinet, head-on for even seeds, against a wall for odd ones.
    cab_w, cab_d, cab_h = float(rng.uniform(0.5, 0.9)), 0.5, float(rng.uniform(1.9, 2.2))
    cab_n = float(rng.uniform(fence_n + 2.5, end_n - 2.5))
    if seed % 2 == 0:
        cab_e = float(rng.uniform(-0.3, 0.3))
    else:
        cab_e = float(rng.choice([-1.0, 1.0])) * (half - 0.5 * cab_w)
    obstacles.append(
        Box.on_ground(cab_n, cab_e, (cab_d, cab_w, cab_h), surface=Surface("plain", grain_grey=2.0, gloss=80.0))
    )
    # A radiator (fins 5 to 7 cm apart) under a window (the view outside: rich texture) on one wall.
    rad_side = float(rng.choice([-1.0, 1.0]))
    rad_n = float(rng.uniform(fence_n + 1.5, end_n - 1.5))
    rad_l = float(rng.uniform(1.0, 1.6))
    fins = Surface("bars", bar_period_m=float(rng.uniform(0.05, 0.07)), bar_width_m=0.02, see_through=False)
    obstacles += [
        Box((rad_n, rad_side * (half - 0.05), -0.45), (rad_l, 0.1, 0.6), surface=fins),
        Box((rad_n, rad_side * (half - 0.005), -1.5), (rad_l + 0.2, 0.01, 1.2)),
    ]
    light = (float(rng.uniform(fence_n + 1.0, end_n - 1.0)), float(rng.uniform(-half + 0.5, half - 0.5)), -2.8)
    return _course(
        "office", seed, obstacles, end_n + 3.0, half - 0.3,
        f"office {width:.1f} m wide: fence (bars every {100 * period:.1f} cm) at {fence_n:.1f} m from the "
        f"{'right' if side > 0 else 'left'}, free end {free_e:+.2f} m east; cabinet at {cab_n:.1f}/{cab_e:+.2f} m; "
        f"door {door_w:.2f} m wide at {door_e:+.2f} m east in the wall at {end_n:.1f} m (gloss {gloss:.0f})",
        light_ned_m=light,
    )


def detour_course(seed: int) -> Course:
    """A wall wider than the view with one opening 3 m to one side, out of the camera's sight at the
    start: the way to the goal is round, through the opening."""
    rng = _rng("detour", seed)
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    wall_north = float(rng.uniform(2.5, 3.0))
    open_w = float(rng.uniform(1.5, 1.9))
    open_e = side * 3.0
    thick, height, span = 0.2, 3.0, 10.0
    lo, hi = open_e - 0.5 * open_w, open_e + 0.5 * open_w  # the opening, east metres
    obstacles: list[Obstacle] = [
        Box.on_ground(wall_north, 0.5 * (-span + lo), (thick, lo + span, height)),
        Box.on_ground(wall_north, 0.5 * (hi + span), (thick, span - hi, height)),
    ]
    goal = wall_north + 3.0
    course = _course(
        "detour", seed, obstacles, goal, span - 2.0,
        f"wall at {wall_north:.1f} m, opening {open_w:.2f} m wide centred {open_e:+.1f} m east",
        hold_is_success=False,
    )
    # Time for the way round at the detour's speed, with a look round.
    return dataclasses.replace(course, time_limit_s=60.0)


_BUILDERS = {
    "corridor": corridor_course,
    "doorway": doorway_course,
    "forest": forest_course,
    "pitch": pitch_course,
    "side": side_course,
    "deadend": deadend_course,
    "office": office_course,
    "detour": detour_course,
}

#: Largest seed accepted (seeds feed NumPy's SeedSequence; a bound keeps names short).
MAX_SEED = 2**31 - 1


def make_course(kind: str, seed: int) -> Course:
    """The course of ``kind`` (one of :data:`COURSE_KINDS`, ``head-on``: :func:`head_on_course`, or
    ``wall``: :func:`wall_course`) for
    ``seed`` (0 .. 2**31 - 1).

    Raises:
        InputError: unknown kind or a seed out of range.
    """
    if kind not in _BUILDERS and kind not in ("head-on", "wall"):
        raise InputError(f"unknown course {kind!r}; courses are {', '.join(COURSE_KINDS)}, head-on, wall")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) <= MAX_SEED:
        raise InputError(f"bad seed {seed!r}: expected an integer in 0..{MAX_SEED}")
    if kind == "head-on":
        return head_on_course(int(seed))
    if kind == "wall":
        return wall_course(int(seed))
    return _BUILDERS[kind](int(seed))


def head_on_course(seed: int = 0, box_north_m: float = 5.0, box_width_m: float = 0.6) -> Course:
    """A single box dead ahead on open ground, for tests and examples (not in the suite)."""
    obstacles: list[Obstacle] = [Box.on_ground(box_north_m, 0.0, (0.6, box_width_m, 2.5))]
    return _course(
        "head-on", seed, obstacles, box_north_m + 3.0, 4.0,
        f"one {box_width_m:.1f} m box at {box_north_m:.1f} m north, dead ahead",
    )


#: The wall course's wall: its front face this far north for seed 0, metres (seed s: 8 + s mod 5).
WALL_NORTH_M = 8.0


def wall_course(seed: int = 0) -> Course:
    """A wide wall straight across the course (30 m wide, 3 m high, 0.3 m thick), its front face
    ``8 + seed mod 5`` m north, on open ground: the collision-prevention scenario's target (not in the
    suite). The goal lies beyond it: stopping in front of it is success."""
    front = WALL_NORTH_M + float(int(seed) % 5)
    obstacles: list[Obstacle] = [Box.on_ground(front + 0.15, 0.0, (0.3, 30.0, 3.0))]
    return _course("wall", seed, obstacles, front + 2.0, 15.0, f"a 30 m wall across the course, {front:.1f} m north")
