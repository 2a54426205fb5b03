"""Ground-truth clearance and the outcome of a flight (pure: positions and times are passed in).

**Clearance** at a point = the Euclidean distance from the vehicle's centre to the nearest solid
surface (every obstacle, the ground and a ceiling if the scene has one: exactly
``Scene.distance_to_obstacles_m(p, include_ground=True)``) **minus the collision radius**. It is the
gap between the vehicle's collision sphere and the world: negative = a collision.

**Outcomes** (:class:`Outcome`), checked at every physics step in this order:

* ``collision``: clearance < 0;
* ``goal``: the centre entered the course's goal region;
* ``out_of_bounds``: the centre left the course's bounds;
* ``held``: stopped (speed < ``held_speed_m_s`` and |yaw rate| < 3 deg/s) for ``held_after_s``
  without a collision: the vehicle braked and holds position;
* ``timeout``: the course's time limit passed.

A flight succeeds on ``goal``, or on ``held`` where the course counts holding as success.
"""

from __future__ import annotations

import enum
import math

import numpy as np

from companion.core.render import Box, Pillar, Scene


class Outcome(str, enum.Enum):
    """How a flight ended."""

    GOAL = "goal"
    COLLISION = "collision"
    HELD = "held"
    TIMEOUT = "timeout"
    OUT_OF_BOUNDS = "out_of_bounds"


class ClearanceField:
    """Fast signed distance from one point to a scene's solids (obstacles, ground, ceiling).

    Vectorised over the obstacles (one NumPy pass per point instead of one per obstacle); equal to
    ``scene.distance_to_obstacles_m(point, include_ground=True)``.

    Args:
        scene: the world.
    """

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        boxes = [o for o in scene.obstacles if isinstance(o, Box)]
        pillars = [o for o in scene.obstacles if isinstance(o, Pillar)]
        self._box_c = np.array([b.centre_ned_m for b in boxes], dtype=np.float64).reshape(-1, 3)
        self._box_r = np.array([b.axes() for b in boxes], dtype=np.float64).reshape(-1, 3, 3)
        self._box_h = 0.5 * np.array([b.size_m for b in boxes], dtype=np.float64).reshape(-1, 3)
        self._pil_c = np.array([p.centre_ned_m for p in pillars], dtype=np.float64).reshape(-1, 3)
        self._pil_r = np.array([p.radius_m for p in pillars], dtype=np.float64)
        self._pil_hh = 0.5 * np.array([p.height_m for p in pillars], dtype=np.float64)
        self._pil_step = np.array([2.0 * math.pi / p.sides for p in pillars], dtype=np.float64)
        self._pil_half_edge = self._pil_r * np.tan(0.5 * self._pil_step)
        self._ground = scene.ground
        self._ceiling_z = None if scene.ceiling_altitude_m is None else -float(scene.ceiling_altitude_m)

    def distance_m(self, point_ned_m: np.ndarray) -> float:
        """Signed distance from ``point_ned_m`` (float ``(3,)`` NED metres) to the nearest solid surface,
        metres (negative inside an obstacle or below the ground); +inf when there is nothing."""
        p = np.asarray(point_ned_m, dtype=np.float64)
        best = math.inf
        if self._box_c.shape[0]:
            local = np.einsum("nij,nj->ni", self._box_r, p - self._box_c)
            q = np.abs(local) - self._box_h
            outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
            inside = np.minimum(q.max(axis=1), 0.0)
            best = min(best, float((outside + inside).min()))
        if self._pil_c.shape[0]:
            rel = p - self._pil_c
            ang = np.arctan2(rel[:, 1], rel[:, 0])
            phi = np.round(ang / self._pil_step) * self._pil_step
            rho = np.hypot(rel[:, 0], rel[:, 1])
            px = rho * np.cos(ang - phi)
            py = np.abs(rho * np.sin(ang - phi))
            out_x = px - self._pil_r
            d2 = np.where((out_x > 0.0) & (py > self._pil_half_edge), np.hypot(out_x, py - self._pil_half_edge), out_x)
            dz = np.abs(rel[:, 2]) - self._pil_hh
            outside = np.hypot(np.maximum(d2, 0.0), np.maximum(dz, 0.0))
            inside = np.minimum(np.maximum(d2, dz), 0.0)
            best = min(best, float((outside + inside).min()))
        if self._ground:
            best = min(best, float(-p[2]))
        if self._ceiling_z is not None:
            best = min(best, float(p[2] - self._ceiling_z))
        return best


def is_success(outcome: Outcome, hold_is_success: bool) -> bool:
    """Goal reached, or held safely where the course counts that as success."""
    return outcome is Outcome.GOAL or (outcome is Outcome.HELD and hold_is_success)
