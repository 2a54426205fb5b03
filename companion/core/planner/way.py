"""The way to the goal on the local map (pure; the map and the goal in, distances out).

The cost's progress terms need more than the goal's bearing: beside a wall, a candidate that ends at the
wall and one that leads back to the gap the camera saw in it are equally far from the goal as the crow
flies, and the goal's bearing points into the wall. :class:`WayToGoal` keeps, for the map's horizontal
plane at the vehicle's altitude, the length of the shortest way from each cell to the goal round every
surface seen (Dijkstra, 8-connected, on cells of the map's columns, :data:`POOL` cubes a side): a
column is closed where a surface's radius reaches the altitude and the camera saw no way over or under
it within the floor and ceiling; unknown space is open (the way is hopeful, like the planner's looks;
the speed law flies only on what was seen). A way close beside a closed cell counts longer than one
in the open, so that the way goes through the middle of a gap.
Beyond the grid the way is the straight line: every cell on its edge starts at its straight distance
to the goal.

Two answers: :meth:`WayToGoal.length_at` (the rest of the way from a candidate's end) and
:meth:`WayToGoal.bearing` (the way's direction from the vehicle: down the distances, then straight to
the farthest point of that walk in plain view, so that the way in the open is the goal's bearing and
not the grid's 45° steps).
"""

from __future__ import annotations

import math

import numpy as np

from companion.core.planner.localmap import LocalMap

#: The way's cells are this many of the map's cubes on a side (at 0.15 m cubes: 0.3 m), four times
#: fewer cells to search than the map's columns; a cell is closed only where all its columns are, so
#: a gap the cubes leave open stays open (the speed law and the free lengths judge the gap itself).
POOL = 2
#: The walk down the distances that sets the way's bearing, cells (at 0.3 m: 6 m).
WALK_CELLS = 20
#: A metre of way beside a closed cell counts this many metres more, less in proportion to the
#: clearance out to the caller's ``clearance_m``: the way keeps to the middle of a gap, not to the
#: edge of a surface's radius, where the free length of a line flickers with each frame's cubes and
#: the vehicle's response to that flicker carries it onto the surface.
EDGE_PENALTY = 1.0


def compile_kernels() -> None:
    """Compile the way's kernels now (about a second, once per process): a service does it at start-up,
    so that the first tick of its first flight does not wait for the compiler."""
    from companion.core.planner import _waykernels as k

    blocked = np.zeros((3, 3), dtype=bool)
    start = np.full((3, 3), np.inf)
    start[0, 0] = 0.0
    out = np.empty((3, 3))
    k.clearance(blocked, 1.0, 2.0, out)
    k.pool_all(blocked, 1, blocked.copy())
    k.pool_penalty(out, 1.0, 1.0, 1, 1.0, np.empty((3, 3)))
    k.dijkstra(blocked, start, 1.0, np.zeros((3, 3)), out, np.empty(73), np.empty(73, dtype=np.int64))
    path = np.zeros((4, 2), dtype=np.int64)
    k.descend(out, 2, 2, 4, path)
    k.farthest_in_view(blocked, 0.5, 0.5, path)
    k.bearings(out, blocked, np.zeros((1, 2)), 1.0, np.zeros(2), path, np.empty(1))


class WayToGoal:
    """The shortest way to a goal round the surfaces seen: one Dijkstra over the map's columns, searched
    again when the closed columns at the level, the goal, the level or the grid's place change."""

    def __init__(self) -> None:
        self._key: tuple | None = None
        self.dist: np.ndarray | None = None  # float64 (nx, ny) metres to the goal, inf: no way
        self.blocked: np.ndarray | None = None
        self._blocked = np.zeros((0, 0), dtype=bool)  # the buffer ``blocked`` is (nx, ny) once searched
        self._origin = np.zeros(2)  # the grid's cell (0, 0), in cells from the NED origin
        self._cell_m = 1.0
        self._start: np.ndarray | None = None
        self._keys: np.ndarray | None = None
        self._clear = np.zeros((0, 0))  # float64, the map's columns: metres to the nearest closed one
        self._penalty = np.zeros((0, 0))  # float64 (nx, ny): what a step into each cell costs extra, per metre
        self._cells: np.ndarray | None = None
        self._path = np.zeros((WALK_CELLS, 2), dtype=np.int64)
        self._search: tuple | None = None  # the goal, level, band, clearance and grid place of ``dist``
        self._fine: np.ndarray | None = None  # bool: the map's closed columns ``dist`` was made from

    def update(
        self,
        lmap: LocalMap,
        goal_ned_m: np.ndarray,
        level_down_m: float,
        floor_m: float,
        ceiling_m: float,
        clearance_m: float = 0.0,
    ) -> None:
        """The way over ``lmap`` to ``goal_ned_m`` (float ``(3,)`` NED m) at the altitude ``level_down_m``
        (NED down, m), the band between ``floor_m`` and ``ceiling_m`` (altitudes, m) the ways over and
        under, kept ``clearance_m`` (m) off closed cells where the space allows (:data:`EDGE_PENALTY`);
        kept while the map, the goal and the level's cube are the ones it was made for."""
        if lmap.origin is None:
            self.dist = None
            return
        level = int(math.floor(level_down_m / lmap.voxel_m))
        key = (id(lmap), lmap.version, float(goal_ned_m[0]), float(goal_ned_m[1]), level, floor_m, ceiling_m, clearance_m)
        if key == self._key:
            return
        from companion.core.planner import _waykernels as k  # loads Numba at the first way

        self._key = key
        fine = lmap.blocked_columns(level_down_m, -ceiling_m, -floor_m)
        # A frame changes the map's cubes, seldom its closed columns at one level: where they, the
        # grid's place and the goal are the ones the distances were made from, they stand.
        search = (key[2:], tuple(lmap.origin[:2]))
        if search == self._search and self._fine is not None and np.array_equal(fine, self._fine):
            return
        self._search = search
        self._fine = fine
        fx, fy = fine.shape
        if fx % POOL or fy % POOL:  # open past the map's edge
            fine = np.pad(fine, ((0, -fx % POOL), (0, -fy % POOL)))
        nx, ny = fine.shape[0] // POOL, fine.shape[1] // POOL
        if self._start is None or self._start.shape != (nx, ny):
            self._blocked = np.empty((nx, ny), dtype=bool)
            self._start = np.full((nx, ny), np.inf)
            self.dist = np.full((nx, ny), np.inf)
            self._clear = np.empty(fine.shape)
            self._penalty = np.empty((nx, ny))
            self._keys = np.empty(8 * nx * ny + 1)
            self._cells = np.empty(8 * nx * ny + 1, dtype=np.int64)
        assert self.dist is not None and self._keys is not None and self._cells is not None
        blocked = self._blocked
        k.pool_all(fine, POOL, blocked)
        v = POOL * lmap.voxel_m
        # The map's origin is a whole number of cubes; the way's cells start there.
        origin = lmap.origin[:2].astype(np.float64) / POOL
        start = self._start
        start[...] = np.inf
        self._origin = origin
        self._cell_m = v
        # Edge cells: the straight line on from there; the goal's own cell, when on the grid: 0.
        ii = np.arange(nx)
        jj = np.arange(ny)
        g = np.asarray(goal_ned_m, dtype=np.float64)
        for sl, (ci, cj) in (
            ((0, slice(None)), (np.zeros(ny), jj)),
            ((nx - 1, slice(None)), (np.full(ny, nx - 1), jj)),
            ((slice(None), 0), (ii, np.zeros(nx))),
            ((slice(None), ny - 1), (ii, np.full(nx, ny - 1))),
        ):
            cn = (ci + self._origin[0] + 0.5) * v
            ce = (cj + self._origin[1] + 0.5) * v
            start[sl] = np.hypot(g[0] - cn, g[1] - ce)
        gi = int(math.floor(g[0] / v - self._origin[0]))
        gj = int(math.floor(g[1] / v - self._origin[1]))
        if 0 <= gi < nx and 0 <= gj < ny:
            start[gi, gj] = 0.0
            blocked[gi, gj] = False
        # The clearance is judged on the map's own columns, finer than the way's cells: a door two
        # cells wide has a cell nearer its middle. Between columns' edges (a column beside a closed one
        # has none), as a share of clearance_m; a cell's penalty is its columns' mean.
        penalty = self._penalty
        if clearance_m > 0.0:
            f, clear = lmap.voxel_m, self._clear
            k.clearance(fine, f, clearance_m + f, clear)
            k.pool_penalty(clear, f, clearance_m, POOL, EDGE_PENALTY, penalty)
        else:
            penalty[...] = 0.0
        k.dijkstra(blocked, start, v, penalty, self.dist, self._keys, self._cells)
        self.blocked = blocked

    def _cell(self, points_ned_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q = np.floor(np.asarray(points_ned_m, dtype=np.float64)[..., :2] / self._cell_m - self._origin)
        assert self.dist is not None
        nx, ny = self.dist.shape
        inside = (q[..., 0] >= 0) & (q[..., 0] < nx) & (q[..., 1] >= 0) & (q[..., 1] < ny)
        i = np.where(inside, q[..., 0], 0).astype(np.int64)
        j = np.where(inside, q[..., 1], 0).astype(np.int64)
        return i, j, inside

    def length_at(self, points_ned_m: np.ndarray) -> np.ndarray:
        """float64 ``(K,)``: the way's length from each of ``points_ned_m`` (float ``(K, 3)`` NED m) to
        the goal, metres (those close beside a surface counted longer, :data:`EDGE_PENALTY`); NaN where
        the point is off the grid, closed or cut off (the caller falls back on the straight line), or
        before the first :meth:`update`."""
        pts = np.asarray(points_ned_m, dtype=np.float64)
        if self.dist is None:
            return np.full(len(pts), np.nan)
        i, j, inside = self._cell(pts)
        d = self.dist[i, j]
        return np.where(inside & np.isfinite(d), d, np.nan)

    def bearing(self, position_ned_m: np.ndarray) -> float | None:
        """The way's bearing from ``position_ned_m`` (float ``(3,)`` NED m), radians clockwise from north:
        toward the farthest cell of a walk down the distances (:data:`WALK_CELLS`) that the straight
        line from here reaches through open cells only; None where there is no way from here (the
        caller keeps the goal's bearing)."""
        b = float(self.bearings(np.asarray(position_ned_m, dtype=np.float64)[None, :])[0])
        return None if math.isnan(b) else b

    def bearings(self, points_ned_m: np.ndarray) -> np.ndarray:
        """float64 ``(K,)``: :meth:`bearing` from each of ``points_ned_m`` (float ``(K, 3)`` NED m), NaN
        where there is no way (or before the first :meth:`update`). A point within a surface's radius
        (a pass close by) starts from the nearest open cell round it."""
        pts = np.asarray(points_ned_m, dtype=np.float64)
        out = np.full(len(pts), np.nan)
        if self.dist is None or self.blocked is None or len(pts) == 0:
            return out
        from companion.core.planner import _waykernels as k

        k.bearings(self.dist, self.blocked, np.ascontiguousarray(pts[:, :2]), self._cell_m, self._origin, self._path, out)
        return out
