"""The obstacle memory's points judged against a simulated course's true geometry (a measurement of
the rule stack's memory, not for suites: slow)."""

from __future__ import annotations

import numpy as np

from companion.config import CompanionConfig
from companion.core.memory import ObstacleMemory
from companion.sim.courses import Course
from companion.sim.render import Pose
from companion.sim.scoring import ClearanceField


#: A remembered point farther than this from every true surface is false, metres.
FALSE_POINT_TOLERANCE_M = 0.3


def audit_points(memory: ObstacleMemory, course: Course, now_s: float, seen_from: Pose, cfg: CompanionConfig) -> dict[str, int]:
    """The memory's points at ``now_s`` judged against the course's true geometry: ``points`` (all
    remembered), ``false`` (farther than :data:`FALSE_POINT_TOLERANCE_M` from every surface, ground
    included), ``trusted`` and ``trusted_false``; and the same for the points the detour layer maps
    with (``map_*``: trusted, not seen past, within ``memory.height_band_m`` of the vehicle and within
    the detour's reach of it) and those that guard (``near_*``: seen nearer than
    ``memory.max_depth_m``)."""
    field_ = ClearanceField(course.scene)
    pts, trusted = memory.points(now_s, cfg.memory)
    near = memory.near_mask(now_s, cfg.memory)
    dist = np.array([field_.distance_m(p) for p in pts])
    false = dist > FALSE_POINT_TOLERANCE_M
    pos = np.asarray(seen_from.position_ned_m, dtype=np.float64)
    reach = max(cfg.detour.radius_m, cfg.memory.map_depth_m) + cfg.detour.clearance_m
    rel = pts - pos
    mapped = trusted & ~memory.seen_past_mask(now_s, cfg.memory)
    mapped &= (np.abs(rel[:, 2]) <= cfg.memory.height_band_m) & (np.hypot(rel[:, 0], rel[:, 1]) < reach)
    return {
        "points": int(len(pts)),
        "false": int(np.count_nonzero(false)),
        "trusted": int(np.count_nonzero(trusted)),
        "trusted_false": int(np.count_nonzero(trusted & false)),
        "map_points": int(np.count_nonzero(mapped)),
        "map_false": int(np.count_nonzero(mapped & false)),
        "near_points": int(np.count_nonzero(near)),
        "near_false": int(np.count_nonzero(near & false)),
    }


def add_counts(total: dict[str, int], counts: dict[str, int]) -> None:
    """Add ``counts`` into ``total`` key by key (in place)."""
    for k, v in counts.items():
        total[k] = total.get(k, 0) + v
