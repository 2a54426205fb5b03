"""Scene description for the synthetic renderer and the simulator's ground truth.

All coordinates are world NED metres (x north, y east, z down): the ground is the plane ``z = 0``,
a point at altitude h has ``z = -h``. Obstacles are convex solids (oriented boxes and vertical
prisms); the world is closed by a textured backdrop box so that every camera ray hits something.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal, Union

import numpy as np

from companion.core.pose import _finite3


def _as_points(points_ned_m: np.ndarray | Iterable[float]) -> tuple[np.ndarray, bool]:
    """Points as float64 ``(N, 3)`` and whether the input was a single ``(3,)`` point."""
    pts = np.asarray(points_ned_m, dtype=np.float64)
    single = pts.ndim == 1
    pts = pts.reshape(-1, 3) if single else pts
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (3,) or (N, 3), got {np.shape(points_ned_m)}")
    return pts, single


SurfaceKind = Literal["textured", "plain", "bars"]


@dataclass(frozen=True)
class Surface:
    """How a box's faces look (the hard surfaces real stereo fails on, and the rich default).

    * ``textured``: the rich multi-scale texture every surface had before (the default);
    * ``plain``: a painted wall: smooth low-contrast shading (5 grey levels RMS over tens of
      centimetres) and a faint grain of ``grain_grey`` RMS at the texel scale; against the camera's
      sensor noise (2 grey levels per eye) a block matcher finds little to lock onto at 1.5 to 2, much
      more at 3, but it is never a constant that no matcher could match;
    * ``bars``: vertical bars of a regular period: a fence, a crib, a radiator's fins. See-through
      (``see_through``): the gaps show what is behind (a fence; the bars have the box's thickness and
      no sides of their own); opaque: the gaps are a darker recess (a radiator). A period shorter than
      the disparity search range lets a block matcher lock onto the wrong repeat.

    ``gloss`` > 0 adds a specular highlight of the scene's light (:attr:`Scene.light_ned_m`) where
    its mirror image is seen in the face: a Gaussian blob of peak ``gloss`` grey levels and standard
    deviation ``gloss_spread_deg`` (saturating), placed per eye at the light's mirror image, so it has
    the disparity of that virtual image behind the surface, not the surface's (glare reads far).

    Attributes:
        kind: ``textured``, ``plain`` or ``bars``.
        grain_grey: plain (and a bar box's top and bottom): RMS of the fine grain, grey levels
            (rounded to 0.1; 0 to 20).
        bar_period_m: bars: centre-to-centre spacing, metres (the renderer snaps it so that a whole
            number of periods fills its texture tile; within 2 % for periods of 4 to 20 cm).
        bar_width_m: bars: width of one bar, metres (0 < width < period).
        see_through: bars: the gaps are holes (a fence) rather than a dark recess (a radiator).
        gloss: peak grey levels of the specular highlight (0 = matte).
        gloss_spread_deg: angular standard deviation of the highlight, degrees (> 0).
    """

    kind: SurfaceKind = "textured"
    grain_grey: float = 2.0
    bar_period_m: float = 0.1
    bar_width_m: float = 0.025
    see_through: bool = True
    gloss: float = 0.0
    gloss_spread_deg: float = 4.0

    def __post_init__(self) -> None:
        if self.kind not in ("textured", "plain", "bars"):
            raise ValueError(f"Surface.kind must be textured, plain or bars, got {self.kind!r}")
        period, width = float(self.bar_period_m), float(self.bar_width_m)
        if not (0.0 < width < period <= 2.0 and math.isfinite(period)):
            raise ValueError(f"Surface bars need 0 < bar_width_m < bar_period_m <= 2, got {width}, {period}")
        if not (0.0 <= self.gloss <= 255.0 and 0.0 < self.gloss_spread_deg <= 45.0):
            raise ValueError(
                f"Surface.gloss must be in [0, 255] and gloss_spread_deg in (0, 45], got {self.gloss}, "
                f"{self.gloss_spread_deg}"
            )
        if not 0.0 <= self.grain_grey <= 20.0:
            raise ValueError(f"Surface.grain_grey must be in [0, 20], got {self.grain_grey}")
        object.__setattr__(self, "grain_grey", float(self.grain_grey))
        object.__setattr__(self, "bar_period_m", period)
        object.__setattr__(self, "bar_width_m", width)
        object.__setattr__(self, "gloss", float(self.gloss))
        object.__setattr__(self, "gloss_spread_deg", float(self.gloss_spread_deg))


#: The default surface: rich texture, matte.
TEXTURED = Surface()


@dataclass(frozen=True)
class Box:
    """An oriented box: yawed about the vertical axis only.

    Attributes:
        centre_ned_m: centre, NED metres.
        size_m: (length, width, height) metres: extent along the box's own x (north when yaw 0),
            its own y (east when yaw 0), and z (vertical). All > 0.
        yaw_rad: rotation about +z (down), positive clockwise seen from above, like vehicle yaw.
        surface: how its faces look (:class:`Surface`; rendering only: the geometry, and so
            collisions and clearance, is the solid box whatever it shows). Bars run vertically on
            the four side faces, spaced along the box's own y on the x faces: a fence panel is a
            thin box (x thin, y long).
    """

    centre_ned_m: tuple[float, float, float]
    size_m: tuple[float, float, float]
    yaw_rad: float = 0.0
    surface: Surface = TEXTURED

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre_ned_m", _finite3("Box.centre_ned_m", self.centre_ned_m))
        size = _finite3("Box.size_m", self.size_m)
        if min(size) <= 0.0:
            raise ValueError(f"Box.size_m must be > 0, got {size}")
        object.__setattr__(self, "size_m", size)
        object.__setattr__(self, "yaw_rad", float(self.yaw_rad))
        if not isinstance(self.surface, Surface):
            raise ValueError(f"Box.surface must be a Surface, got {type(self.surface).__name__}")

    @classmethod
    def on_ground(
        cls,
        north_m: float,
        east_m: float,
        size_m: tuple[float, float, float],
        yaw_rad: float = 0.0,
        surface: Surface = TEXTURED,
    ) -> Box:
        """A box standing on the ground (its bottom face at altitude 0)."""
        return cls((north_m, east_m, -0.5 * float(size_m[2])), size_m, yaw_rad, surface)

    def axes(self) -> np.ndarray:
        """Box axes as rows, float64 ``(3, 3)``: its x, y, z unit vectors in NED."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]], dtype=np.float64)

    def signed_distance_m(self, points_ned_m: np.ndarray) -> np.ndarray:
        """Exact Euclidean distance to the box surface, negative inside; float64 ``(N,)`` for ``(N, 3)``."""
        pts, _ = _as_points(points_ned_m)
        local = (pts - np.asarray(self.centre_ned_m)) @ self.axes().T
        q = np.abs(local) - 0.5 * np.asarray(self.size_m)
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        inside = np.minimum(q.max(axis=1), 0.0)
        return outside + inside


@dataclass(frozen=True)
class Pillar:
    """A vertical cylinder approximated by a regular prism with ``sides`` faces.

    The prism *circumscribes* the cylinder of ``radius_m`` (its flat faces are ``radius_m`` from the
    axis, its vertical edges ``radius_m / cos(pi / sides)``), so the rendered solid contains the
    nominal cylinder. :meth:`signed_distance_m` is exact for the rendered prism.

    Attributes:
        centre_ned_m: centre of the prism (on its axis, half-way up), NED metres.
        radius_m: apothem, metres (> 0).
        height_m: metres (> 0).
        sides: number of side faces (>= 3).
    """

    centre_ned_m: tuple[float, float, float]
    radius_m: float
    height_m: float
    sides: int = 16

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre_ned_m", _finite3("Pillar.centre_ned_m", self.centre_ned_m))
        if not (self.radius_m > 0.0 and self.height_m > 0.0 and math.isfinite(self.radius_m * self.height_m)):
            raise ValueError(f"Pillar radius and height must be > 0, got {self.radius_m}, {self.height_m}")
        if int(self.sides) != self.sides or self.sides < 3:
            raise ValueError(f"Pillar.sides must be an integer >= 3, got {self.sides}")
        object.__setattr__(self, "radius_m", float(self.radius_m))
        object.__setattr__(self, "height_m", float(self.height_m))
        object.__setattr__(self, "sides", int(self.sides))

    @classmethod
    def on_ground(
        cls, north_m: float, east_m: float, radius_m: float, height_m: float, sides: int = 16
    ) -> Pillar:
        """A pillar standing on the ground (its bottom at altitude 0)."""
        return cls((north_m, east_m, -0.5 * float(height_m)), radius_m, height_m, sides)

    def signed_distance_m(self, points_ned_m: np.ndarray) -> np.ndarray:
        """Exact Euclidean distance to the prism surface, negative inside; float64 ``(N,)``."""
        pts, _ = _as_points(points_ned_m)
        rel = pts - np.asarray(self.centre_ned_m)
        # Fold the point into the sector of the nearest face normal (face j's normal at 2*pi*j/sides).
        step = 2.0 * math.pi / self.sides
        ang = np.arctan2(rel[:, 1], rel[:, 0])
        phi = np.round(ang / step) * step
        rho = np.hypot(rel[:, 0], rel[:, 1])
        px = rho * np.cos(ang - phi)  # along the face normal
        py = np.abs(rho * np.sin(ang - phi))  # along the face, from its middle
        half_edge = self.radius_m * math.tan(math.pi / self.sides)
        # 2-D signed distance to the polygon: beyond a vertex the nearest point is that vertex.
        out_x = px - self.radius_m
        d2 = np.where(
            (out_x > 0.0) & (py > half_edge), np.hypot(out_x, py - half_edge), out_x
        )
        dz = np.abs(rel[:, 2]) - 0.5 * self.height_m
        outside = np.hypot(np.maximum(d2, 0.0), np.maximum(dz, 0.0))
        inside = np.minimum(np.maximum(d2, dz), 0.0)
        return outside + inside


Obstacle = Union[Box, Pillar]


@dataclass(frozen=True)
class Scene:
    """A static world: obstacles inside a textured backdrop box.

    The backdrop ("world box") spans ``backdrop_centre_ne_m +- backdrop_half_size_m`` horizontally;
    its floor is the ground (``z = 0``) when ``ground`` is true (else a sky-textured floor
    ``backdrop_half_size_m`` below), its top the ceiling at ``ceiling_altitude_m`` when given (else
    a sky-textured top at ``sky_altitude_m``). The camera must stay inside it.

    Attributes:
        obstacles: boxes and pillars.
        ground: whether the ground plane exists (drawn, and an obstacle for ``include_ground``).
        ceiling_altitude_m: altitude of an optional ceiling, metres (> 0), or None.
        backdrop_centre_ne_m: (north, east) of the world box centre, metres.
        backdrop_half_size_m: half the horizontal side of the world box, metres.
        sky_altitude_m: altitude of the world box's top when there is no ceiling, metres.
        light_ned_m: a small bright light (a lamp, a window's sun patch), NED metres, whose
            specular highlight glossy surfaces show (:class:`Surface`), or None.
    """

    obstacles: tuple[Obstacle, ...] = ()
    ground: bool = True
    ceiling_altitude_m: float | None = None
    backdrop_centre_ne_m: tuple[float, float] = (0.0, 0.0)
    backdrop_half_size_m: float = 100.0
    sky_altitude_m: float = 60.0
    light_ned_m: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        obstacles = tuple(self.obstacles)
        for ob in obstacles:
            if not isinstance(ob, (Box, Pillar)):
                raise ValueError(f"Scene.obstacles must be Box or Pillar, got {type(ob).__name__}")
        object.__setattr__(self, "obstacles", obstacles)
        if self.ceiling_altitude_m is not None and not self.ceiling_altitude_m > 0.0:
            raise ValueError(f"Scene.ceiling_altitude_m must be > 0, got {self.ceiling_altitude_m}")
        if not (self.backdrop_half_size_m > 0.0 and self.sky_altitude_m > 0.0):
            raise ValueError(
                f"Scene.backdrop_half_size_m ({self.backdrop_half_size_m}) and sky_altitude_m "
                f"({self.sky_altitude_m}) must be > 0"
            )
        ne = tuple(float(v) for v in self.backdrop_centre_ne_m)
        if len(ne) != 2:
            raise ValueError(f"Scene.backdrop_centre_ne_m must be (north, east), got {ne}")
        object.__setattr__(self, "backdrop_centre_ne_m", ne)
        if self.light_ned_m is not None:
            object.__setattr__(self, "light_ned_m", _finite3("Scene.light_ned_m", self.light_ned_m))

    @property
    def top_z_m(self) -> float:
        """NED z of the world's top face (ceiling or sky), metres (negative)."""
        alt = self.ceiling_altitude_m if self.ceiling_altitude_m is not None else self.sky_altitude_m
        return -float(alt)

    @property
    def floor_z_m(self) -> float:
        """NED z of the world's floor (the ground, or the sky-textured bottom), metres."""
        return 0.0 if self.ground else float(self.backdrop_half_size_m)

    def distance_to_obstacles_m(
        self, points_ned_m: np.ndarray | Iterable[float], include_ground: bool = False
    ) -> float | np.ndarray:
        """Signed distance from points to the nearest obstacle surface, metres (negative inside one).

        Args:
            points_ned_m: one point ``(3,)`` or points ``(N, 3)``, NED metres.
            include_ground: also count the ground (distance = altitude) and the ceiling, if present.

        Returns:
            A float for a single point, else float64 ``(N,)``; +inf when there is nothing to hit.
        """
        pts, single = _as_points(points_ned_m)
        best = np.full(pts.shape[0], np.inf)
        for ob in self.obstacles:
            np.minimum(best, ob.signed_distance_m(pts), out=best)
        if include_ground:
            if self.ground:
                np.minimum(best, -pts[:, 2], out=best)
            if self.ceiling_altitude_m is not None:
                np.minimum(best, pts[:, 2] + self.ceiling_altitude_m, out=best)
        return float(best[0]) if single else best


def corridor_scene(
    length_m: float = 80.0,
    width_m: float = 6.0,
    wall_height_m: float = 4.0,
    n_obstacles: int = 18,
    seed: int = 0,
    ceiling_altitude_m: float | None = None,
) -> Scene:
    """A straight corridor along +north from ``x = 0``: two walls and random boxes/pillars between.

    The walls are 0.3 m thick boxes just outside ``east = +-width_m / 2``; obstacles (every third a
    pillar, the others yawed boxes) stand at random stations from 4 m on. Not guaranteed passable.
    Deterministic in ``seed``. Used by the renderer benchmark, tests and example frames.
    """
    rng = np.random.default_rng([seed, 0xC0FF])
    half = 0.5 * width_m
    obstacles: list[Obstacle] = [
        Box.on_ground(0.5 * length_m, -half - 0.15, (length_m, 0.3, wall_height_m)),
        Box.on_ground(0.5 * length_m, half + 0.15, (length_m, 0.3, wall_height_m)),
    ]
    stations = np.sort(rng.uniform(4.0, length_m - 2.0, n_obstacles))
    for i, x in enumerate(stations):
        east = float(rng.uniform(-half + 0.4, half - 0.4))
        if i % 3 == 2:
            radius, height = float(rng.uniform(0.15, 0.4)), float(rng.uniform(2.0, 4.0))
            obstacles.append(Pillar.on_ground(float(x), east, radius, height))
        else:
            size = (float(rng.uniform(0.4, 1.5)), float(rng.uniform(0.4, 1.6)), float(rng.uniform(0.5, 3.0)))
            obstacles.append(Box.on_ground(float(x), east, size, float(rng.uniform(-0.6, 0.6))))
    return Scene(
        obstacles=tuple(obstacles),
        ground=True,
        ceiling_altitude_m=ceiling_altitude_m,
        backdrop_centre_ne_m=(0.5 * length_m, 0.0),
        backdrop_half_size_m=max(100.0, 0.5 * length_m + 40.0),
    )


__all__ = ["TEXTURED", "Box", "Obstacle", "Pillar", "Scene", "Surface", "SurfaceKind", "corridor_scene"]
