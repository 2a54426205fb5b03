"""The local map: a rolling 3D occupancy grid round the vehicle, cleared along the camera's rays
(pure NumPy; time is passed in).

Perception only, no control law. Each frame's block image (the largest valid disparity of each
``block_px`` square: the nearest surface on that block's ray, :class:`~companion.core.blocks.BlockMax`)
enters the map as rays from the camera (OctoMap's idea): the cubes a ray passes through before its
surface are seen free, the cube at its surface is hit. A cube's evidence is a log-odds number (a hit
adds :data:`HIT_LOG_ODDS`, a pass subtracts :data:`FREE_LOG_ODDS`), so that one false match is not an
obstacle and a surface once seen is cleared only after a few frames that see through it (a surface
seen solid, only by rays that end at a surface: :data:`SOLID_LOG_ODDS`). Evidence
decays with time (``occupied_memory_s`` after the last hit, ``free_memory_s`` after the last pass) and
with distance (the grid rolls with the vehicle and drops what falls off its edge).

Queries (:meth:`LocalMap.free_lengths`): how far the vehicle's centre can fly along a direction with
every occupied cube at least the vehicle's radius away (the occupied cubes inflated by it), and
**only as far as the body's whole width was seen free**: the centre line and the body's rim round it
(:data:`RIM_POINTS` points a radius off the line). Unknown space counts as near, beside the path as
on it, so a speed law built on these lengths never flies fast into space the camera has not looked
at, nor past it: a door's jamb in a plain wall is unknown, not free, until it is seen.

Frames: NED metres (x north, y east, z down); grid index ``(i, j, k)`` = floor(ned / voxel) less the
grid's origin index.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from companion.core.geometry import StereoGeometry
from companion.core.planner._layers import box_count, count_box, log_of, shift_fill
from companion.core.pose import Pose

#: Log-odds added by a hit and taken by a pass; a cube is occupied above OCCUPIED_LOG_ODDS: two hits
#: in a row (one false match is not an obstacle), and a surface hit often (the clamp, CLAMP_LOG_ODDS)
#: is cleared only after several frames see through it.
HIT_LOG_ODDS = 0.5
FREE_LOG_ODDS = 0.3
OCCUPIED_LOG_ODDS = 0.7
CLAMP_LOG_ODDS = (-1.0, 2.5)
#: A cube is not seen free by passes that came less than this after its hit before the last, s:
#: thin bars, a see-through fence, wires are hit in some frames and seen past in others, so their
#: log-odds sink while they stand there. Such mixed evidence is unknown, and unknown is near (a fence
#: of bars 10 cm apart read as free until 1.85 m off at 3 m/s). It stays so while no frame sees the
#: cube again: a fence the camera has turned away from is as unknown as when it was last seen. One
#: hit is not mixed evidence, as it is not a surface (a false match, depth noise at an edge);
#: occupancy is untouched.
MIXED_EVIDENCE_S = 0.5
#: A cube whose evidence is this high (four hits more than passes: a surface seen solid over several
#: frames) is seen through only by a ray that ends at a surface already in the map, or beyond the
#: range. A matcher reads a fence of bars closer than the baseline at its alias, three times farther,
#: in open space (the whole census window pairs each bar with its neighbour and the wall behind
#: with itself); the alias moves three times as fast as the vehicle and seldom lands on a surface the
#: map holds, so it does not erase the fence. A real opening shows what lies behind it frame after
#: frame, and clears as before.
SOLID_LOG_ODDS = 2.0
#: Rays are thinned to about this many pixels apart (the block image max-pooled: the nearer surface
#: wins): a cube at 0.15 m subtends about 6 px at 4 m on a 336 px, 90° image.
RAY_SPACING_PX = 8
#: The grid reaches this much beyond the map range round the vehicle, m, so that it rolls rarely.
ROLL_SLACK_M = 2.0
#: Half height of the grid round the vehicle, m.
HALF_HEIGHT_M = 2.6
#: Points of the body's rim checked round each sample of a line, evenly round it a radius off it.
RIM_POINTS = 8


@dataclass(frozen=True)
class FreeLengths:
    """Answers of :meth:`LocalMap.free_lengths` for K directions.

    Attributes:
        length_m: float64 ``(K,)`` how far the centre may fly along each direction, metres.
        blocked: bool ``(K,)`` True where the length ends at an occupied cube (a surface seen), False
            where it ends in unknown space or at the horizon.
        horizon: bool ``(K,)`` True where the length reaches the query's horizon.
    """

    length_m: np.ndarray
    blocked: np.ndarray
    horizon: np.ndarray


class LocalMap:
    """A rolling occupancy grid of ``voxel_m`` cubes round the vehicle.

    Args:
        voxel_m: cube edge, metres.
        range_m: depth out to which frames enter the map (and the horizon of queries), metres.
        radius_m: the vehicle's radius: occupied cubes are inflated by it for :meth:`free_lengths`.
        occupied_memory_s, free_memory_s: how long a hit and a pass count, seconds.
    """

    def __init__(self, voxel_m: float, range_m: float, radius_m: float, occupied_memory_s: float, free_memory_s: float):
        self.voxel_m = float(voxel_m)
        self.range_m = float(range_m)
        self.radius_m = float(radius_m)
        self.occupied_memory_s = float(occupied_memory_s)
        self.free_memory_s = float(free_memory_s)
        n_xy = int(math.ceil(2.0 * (range_m + ROLL_SLACK_M) / voxel_m))
        n_z = int(math.ceil(2.0 * HALF_HEIGHT_M / voxel_m))
        self.shape = (n_xy, n_xy, n_z)
        self.log_odds = np.zeros(self.shape, dtype=np.float32)
        self.hit_t = np.full(self.shape, -np.inf, dtype=np.float32)
        self.prev_hit_t = np.full(self.shape, -np.inf, dtype=np.float32)  # the hit before the last
        self.free_t = np.full(self.shape, -np.inf, dtype=np.float32)
        self.origin = None  # int64 (3,): world cube index of grid cube (0, 0, 0); None before the first use
        # The layers the queries read, kept up to the evidence at each frame (not at each query):
        # occupied, seen free, and per cube the number of occupied cubes within the radius (rounded up
        # to whole cubes; > 0: inflated), updated round the cubes whose occupancy changed.
        self._inflate_n = int(math.ceil(radius_m / voxel_m - 1e-9))
        self._occ = np.zeros(self.shape, dtype=bool)
        self._infl = np.zeros(self.shape, dtype=np.int16)
        # Seen free: cubes passed within free_memory_s (recent), and per cube the number of recent
        # cubes within one cube (> 0: seen, as the rays are up to a cube apart at the range).
        self._recent = np.zeros(self.shape, dtype=bool)
        self._fcnt = np.zeros(self.shape, dtype=np.int8)
        # And per cube, whether its own evidence lets it be seen free (no surface's, not mixed): it
        # changes only where a frame hits or passes, so it is kept up there and the queries read one
        # byte per cube instead of three numbers.
        self._evidence_ok = np.ones(self.shape, dtype=bool)
        # What may age out, in time order: (time s, int32 flat cube indices) of each frame's hits and passes
        # (a rebuild sorts the grid's into them), so that a refresh looks only at the cubes whose
        # time has come instead of scanning the grid.
        self._hit_log: deque[tuple[np.float32, np.ndarray]] = deque()
        self._pass_log: deque[tuple[np.float32, np.ndarray]] = deque()
        self._slot = np.zeros(int(np.prod(self.shape)), dtype=np.int32)  # scratch of _unique
        self._rebuild = True  # the next refresh recomputes every layer (first use, after a roll)
        r = np.arange(-self._inflate_n, self._inflate_n + 1)
        self._box = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)  # (B, 3) cube offsets
        r1 = np.arange(-1, 2)
        self._box1 = np.stack(np.meshgrid(r1, r1, r1, indexing="ij"), axis=-1).reshape(-1, 3)
        self._grid_shape = np.array(self.shape)
        self._body_mask = np.zeros(self.shape, dtype=bool)  # the cubes the body is in (mark_body_free)
        self._body_idx = np.zeros(0, np.int64)
        self._rays: dict[tuple, np.ndarray] = {}
        self._scratch = np.zeros(self.shape, dtype=bool)
        self.now_s = -math.inf
        self.version = 0  # counts the changes of the layers (frames in, rolls): what a query may cache on
        g = np.arange(-radius_m, radius_m + 1e-9, 0.5 * voxel_m)
        body = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
        self._body = body[np.linalg.norm(body, axis=1) <= radius_m]  # (B, 3) offsets inside the body, m
        rim_a = np.arange(RIM_POINTS) * (2.0 * math.pi / RIM_POINTS)  # round the line from its level side
        self._rim_cos, self._rim_sin = np.cos(rim_a), np.sin(rim_a)

    # -- the grid round the vehicle ------------------------------------------------------------
    def _cube(self, ned_m: np.ndarray) -> np.ndarray:
        return np.floor(np.asarray(ned_m, dtype=np.float64) / self.voxel_m).astype(np.int64)

    def centre_on(self, position_ned_m: np.ndarray) -> None:
        """Roll the grid so that ``position_ned_m`` (float ``(3,)`` NED m) lies near its middle (what
        falls off an edge is forgotten: the map is local)."""
        c = self._cube(position_ned_m)
        half = np.array(self.shape) // 2
        want = c - half
        if self.origin is None:
            self.origin = want
            return
        shift = want - self.origin
        # Roll only when the vehicle is a quarter of the grid off its middle.
        if np.all(np.abs(shift) < np.array(self.shape) // 4):
            return
        for arr, fill in ((self.log_odds, 0.0), (self.hit_t, -np.inf), (self.prev_hit_t, -np.inf), (self.free_t, -np.inf)):
            shift_fill(arr, -shift, fill)
        self.origin = want
        self.version += 1
        self._body_mask[...] = False  # marked again where the body is now
        self._body_idx = np.zeros(0, np.int64)
        self._rebuild = True
        self._refresh(None)

    def _index(self, ned_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat grid indices (int64 ``(...)``) of points ``ned_m`` (float ``(..., 3)``) and whether
        each lies inside the grid (bool ``(...)``)."""
        # In float (exact for these small integers) and per axis: this runs on every query's samples.
        q = np.floor(np.asarray(ned_m, dtype=np.float64) / self.voxel_m) - self.origin
        i, j, k = q[..., 0], q[..., 1], q[..., 2]
        nx, ny, nz = self.shape
        inside = (i >= 0) & (i < nx) & (j >= 0) & (j < ny) & (k >= 0) & (k < nz)
        flat = (i * ny + j) * nz + k
        return np.where(inside, flat, 0.0).astype(np.int64), inside

    # -- frames in ---------------------------------------------------------------------------------
    def _camera_rays(self, geometry: StereoGeometry, block_shape: tuple[int, int], block_px: int, pool: int) -> np.ndarray:
        """float64 ``(rows, cols, 3)`` camera-frame ray of each pooled block's centre, z = 1."""
        key = (geometry, block_shape, block_px, pool)
        rays = self._rays.get(key)
        if rays is None:
            rows, cols = -(-block_shape[0] // pool), -(-block_shape[1] // pool)
            step = block_px * pool
            u = np.minimum(np.arange(cols) * step + 0.5 * step - 0.5, geometry.width_px - 1)
            v = np.minimum(np.arange(rows) * step + 0.5 * step - 0.5, geometry.height_px - 1)
            rays = np.empty((rows, cols, 3))
            rays[..., 0] = ((u - geometry.cx_px) / geometry.focal_px)[None, :]
            rays[..., 1] = ((v - geometry.cy_px) / geometry.focal_px)[:, None]
            rays[..., 2] = 1.0
            self._rays[key] = rays
        return rays

    def integrate(
        self,
        blocks: np.ndarray,
        geometry: StereoGeometry,
        block_px: int,
        seen_from: Pose,
        t_s: float,
        num_disparities: int | None = None,
    ) -> None:
        """Enter one frame: ``blocks`` float32 ``(rows, cols)`` the largest valid disparity of each
        ``block_px`` square block (px, NaN none), seen with ``geometry`` from ``seen_from`` (the pose at
        capture) at ``t_s`` seconds. A block with no valid disparity says nothing (a plain wall stays
        unknown); one beyond the map range clears its ray to the range.

        A ray is evidence of free space only where the matcher could have seen a surface: the left
        image's column ``x`` matches disparities below ``min(x + 1, num_disparities)`` (None: no
        limit), so a surface nearer than ``f·B`` over that on the ray cannot be told from free space
        (it reads farther, or not at all: at the left edge a wall at grazing angle reads far). The
        ray's first stretch, to that depth from its block's leftmost column, is not cleared."""
        self.now_s = max(self.now_s, float(t_s))
        self.version += 1
        self.centre_on(np.asarray(seen_from.position_ned_m))
        pool = max(1, int(round(RAY_SPACING_PX / block_px)))
        b = np.asarray(blocks, dtype=np.float32)
        pr, pc = -(-b.shape[0] // pool), -(-b.shape[1] // pool)
        padded = np.full((pr * pool, pc * pool), np.nan, dtype=np.float32)
        padded[: b.shape[0], : b.shape[1]] = b
        pooled = np.fmax.reduce(np.fmax.reduce(padded.reshape(pr, pool, pc, pool), axis=3), axis=1)
        rays = self._camera_rays(geometry, b.shape, block_px, pool)
        valid = np.isfinite(pooled) & (pooled > 0.0)
        if not np.any(valid):
            self._refresh(None)
            return
        depth = geometry.focal_baseline_px_m / pooled[valid].astype(np.float64)
        r_cam = rays[valid]  # (n, 3), z = 1
        norm = np.linalg.norm(r_cam, axis=1)
        dist = depth * norm  # range along the ray to the surface, m
        if num_disparities is None:
            blind = np.zeros(len(dist))
        else:  # the nearest depth a pooled block's leftmost column can match, along its ray
            x0 = np.nonzero(valid)[1].astype(np.float64) * (pool * block_px)
            top = np.minimum(x0, float(num_disparities - 1))
            with np.errstate(divide="ignore"):
                blind = np.where(top > 0.0, geometry.focal_baseline_px_m / top, np.inf) * norm
        unit_ned = (r_cam / norm[:, None]) @ seen_from.ned_from_camera().T
        origin = np.asarray(seen_from.position_ned_m, dtype=np.float64)
        t = np.float32(t_s)
        # Hits: surfaces within the range.
        hit = dist <= self.range_m
        hit_pts = origin + unit_ned[hit] * dist[hit, None]
        h_idx, h_in = self._index(hit_pts)
        h_idx = h_idx[h_in]
        # Passes: samples every 0.7 cube along each ray, from the camera to a cube short of its surface.
        step = 0.7 * self.voxel_m
        s = np.arange(0.5 * step, self.range_m, step)
        end = np.minimum(dist, self.range_m) - self.voxel_m
        take = (s[None, :] < end[:, None]) & (s[None, :] >= blind[:, None])
        ray, k = np.nonzero(take)  # only the samples short of each ray's surface
        f_idx, f_in = self._index(origin + unit_ned[ray] * s[k, None])
        lo = self.log_odds.reshape(-1)
        ends_known = ~hit  # beyond the range, or at a surface the map holds (as of the last frame)
        ends_known[np.nonzero(hit)[0][h_in]] = self._occ.reshape(-1)[h_idx]
        f_idx, f_ray = f_idx[f_in], ray[f_in]
        f_idx = f_idx[ends_known[f_ray] | (lo[f_idx] < np.float32(SOLID_LOG_ODDS))]
        mark = self._scratch.reshape(-1)
        mark[h_idx] = True  # a cube hit in this frame is not passed in it
        f_idx = f_idx[~mark[f_idx]]
        mark[h_idx] = False
        lo[f_idx] = np.maximum(lo[f_idx] - FREE_LOG_ODDS, CLAMP_LOG_ODDS[0])
        self._pass(f_idx, t)
        lo[h_idx] = np.minimum(lo[h_idx] + HIT_LOG_ODDS, CLAMP_LOG_ODDS[1])
        hit_t = self.hit_t.reshape(-1)
        self.prev_hit_t.reshape(-1)[h_idx] = hit_t[h_idx]  # read before any write: repeats agree
        hit_t[h_idx] = t
        if len(h_idx):
            self._hit_log.append((t, h_idx.astype(np.int32)))
        touched = np.concatenate([h_idx, f_idx])
        self._evidence_ok.reshape(-1)[touched] = self._evidence_ok_at(touched)
        self._refresh(touched)

    def _evidence_ok_at(self, idx: np.ndarray | slice) -> np.ndarray:
        """bool: whether cubes ``idx`` (flat indices) may be seen free on their own evidence: log-odds
        at most :data:`OCCUPIED_LOG_ODDS`, and not mixed (their last pass at least
        :data:`MIXED_EVIDENCE_S` after their hit before the last)."""
        lo, prev, free = self.log_odds.reshape(-1)[idx], self.prev_hit_t.reshape(-1)[idx], self.free_t.reshape(-1)[idx]
        return (lo <= np.float32(OCCUPIED_LOG_ODDS)) & (prev <= free - np.float32(MIXED_EVIDENCE_S))

    def _pass(self, f_idx: np.ndarray, t: np.float32) -> None:
        """Cubes ``f_idx`` (int64 flat, repeats allowed) seen free at ``t``: their time, and the
        seen-free counts round those that were not recent."""
        if len(f_idx) == 0:
            return
        self.free_t.reshape(-1)[f_idx] = t
        self._pass_log.append((t, f_idx.astype(np.int32)))  # half the memory: the log holds seconds of frames
        if self._rebuild:
            return  # the refresh recomputes the layer whole
        rec = self._recent.reshape(-1)
        rising = f_idx[~rec[f_idx]]
        if len(rising):
            rising = self._unique(rising)
            rec[rising] = True
            count_box(self._fcnt, rising, self._box1, self._grid_shape, 1)

    def _refresh(self, touched: np.ndarray | None) -> None:
        """Bring the layers up to the evidence at ``now_s``: the occupancy of the ``touched`` cubes
        (int64 flat indices, repeats allowed) and of those whose last hit aged out, the inflation
        counts round the cubes that changed, and the seen-free counts round the cubes whose last
        pass aged out. ``touched`` None with nothing to rebuild: ageing only."""
        now = self.now_s
        lo, hit_t = self.log_odds.reshape(-1), self.hit_t.reshape(-1)
        occ = self._occ.reshape(-1)
        if self._rebuild:
            self._occ[...] = (self.log_odds > OCCUPIED_LOG_ODDS) & (self.hit_t >= now - self.occupied_memory_s)
            self._infl[...] = box_count(self._occ, self._inflate_n)
            self._body_mask &= ~self._occ
            self._recent[...] = self.free_t >= now - self.free_memory_s
            self._fcnt[...] = box_count(self._recent, 1)
            self._evidence_ok.reshape(-1)[...] = self._evidence_ok_at(slice(None))
            self._hit_log = log_of(occ, hit_t)
            self._pass_log = log_of(self._recent.reshape(-1), self.free_t.reshape(-1))
            self._rebuild = False
            return
        aged = self._aged(self._hit_log, occ, hit_t, now - self.occupied_memory_s)
        if touched is not None and len(touched):
            now_occ = (lo[touched] > OCCUPIED_LOG_ODDS) & (hit_t[touched] >= now - self.occupied_memory_s)
            rising = self._unique(touched[now_occ & ~occ[touched]])
            falling = self._unique(np.concatenate([touched[~now_occ & occ[touched]], aged]))
        else:
            rising, falling = np.zeros(0, np.int64), aged
        occ[rising] = True
        occ[falling] = False
        self._body_mask.reshape(-1)[rising] = False
        count_box(self._infl, rising, self._box, self._grid_shape, 1)
        count_box(self._infl, falling, self._box, self._grid_shape, -1)
        rec = self._recent.reshape(-1)
        stale = self._aged(self._pass_log, rec, self.free_t.reshape(-1), now - self.free_memory_s)
        rec[stale] = False
        count_box(self._fcnt, stale, self._box1, self._grid_shape, -1)

    def _aged(self, log: deque, flag: np.ndarray, times: np.ndarray, since: float) -> np.ndarray:
        """The cubes (int64 flat, unique) still ``flag``-ged whose time (``times``) is now before
        ``since``: found among the log's entries older than ``since`` (popped)."""
        thr = np.float32(since)
        found = []
        while log and log[0][0] < thr:
            found.append(log.popleft()[1])
        if not found:
            return np.zeros(0, np.int64)
        c = found[0] if len(found) == 1 else np.concatenate(found)
        return self._unique(c[flag[c] & (times[c] < thr)])

    def _unique(self, idx: np.ndarray) -> np.ndarray:
        """``idx`` (int64 flat cube indices) without repeats, in no particular order, in one pass
        (a slot per cube remembers which element claimed it; no sort)."""
        if len(idx) < 2:
            return idx
        n = np.arange(len(idx), dtype=np.int32)
        self._slot[idx] = n
        return idx[self._slot[idx] == n]

    def mark_body_free(self, position_ned_m: np.ndarray, t_s: float) -> None:
        """The cubes the vehicle's body is in now are free (it is there) at ``t_s``: those alone, not
        the cubes round them as round a ray's passes (no ray saw those). The grid rolls with the
        frames, not here (a control tick never pays for a roll): the body lies well inside it while
        frames come, and without frames the vehicle is stopped."""
        self.now_s = max(self.now_s, float(t_s))
        if self.origin is None:
            self.centre_on(np.asarray(position_ned_m))
        idx, inside = self._index(np.asarray(position_ned_m, dtype=np.float64) + self._body)
        idx = idx[inside]
        body = self._body_mask.reshape(-1)
        body[self._body_idx] = False
        self._body_idx = idx[~self._occ.reshape(-1)[idx]]
        body[self._body_idx] = True

    # -- queries -------------------------------------------------------------------------------------
    # The layers are as of the newest frame: evidence ages with the frames, not between them (the
    # safety chain stops the vehicle when the frames stop).
    def occupied(self) -> np.ndarray:
        """bool grid shape: cubes with a surface (enough hits, the last within occupied_memory_s)."""
        return self._occ

    def seen_free(self) -> np.ndarray:
        """bool grid shape: cubes within a cube of one passed within free_memory_s, with no surface's
        evidence and none mixed (:data:`MIXED_EVIDENCE_S`), or the body's; not occupied (a new array:
        queries read the layers at their samples instead)."""
        return self._free_at(np.arange(self.log_odds.size)).reshape(self.shape) & ~self._occ

    def _free_at(self, idx: np.ndarray) -> np.ndarray:
        seen = (self._fcnt.reshape(-1)[idx] > 0) & self._evidence_ok.reshape(-1)[idx]
        return seen | self._body_mask.reshape(-1)[idx]

    def inflated(self) -> np.ndarray:
        """bool grid shape: within the vehicle's radius (rounded up to whole cubes) of an occupied
        cube (a new array: queries read the counts at their samples instead)."""
        return self._infl > 0

    def _inflated_at(self, idx: np.ndarray) -> np.ndarray:
        return self._infl.reshape(-1)[idx] > 0

    def blocked_columns(self, level_down_m: float, top_down_m: float, bottom_down_m: float) -> np.ndarray:
        """bool ``(nx, ny)``: the grid's columns a centre at ``level_down_m`` (NED down, m) cannot pass
        level, within the radius of a surface seen there, and cannot pass over or under either: no
        cube of the column between ``top_down_m`` and ``bottom_down_m`` (the band the vehicle may fly
        in) is both seen free and out of every surface's radius. A low wall the camera saw over is
        passable; a wall whose top was never seen is not; unknown space at the level is (unknown is
        near for the speed law, not a wall for the way)."""
        nz = self.shape[2]
        oz = int(self.origin[2]) if self.origin is not None else 0
        k0 = int(math.floor(level_down_m / self.voxel_m)) - oz
        if self.origin is None or not 0 <= k0 < nz:
            return np.zeros(self.shape[:2], dtype=bool)
        from companion.core.planner import _mapkernels

        lo = max(0, int(math.floor(top_down_m / self.voxel_m)) - oz)
        hi = min(nz, int(math.floor(bottom_down_m / self.voxel_m)) - oz + 1)
        out = np.empty(self.shape[:2], dtype=bool)
        _mapkernels.blocked_columns(k0, lo, hi, self._infl, self._fcnt, self.log_odds, np.float32(OCCUPIED_LOG_ODDS), out)
        return out

    def within_radius(self, points_ned_m: np.ndarray) -> np.ndarray:
        """Whether a body centred at each of ``points_ned_m`` (float ``(..., 3)`` NED m) would be within
        the vehicle's radius (rounded up to whole cubes) of an occupied cube: touching, or nearly, a
        surface seen (bool ``(...)``)."""
        pts = np.asarray(points_ned_m, dtype=np.float64)
        if self.origin is None:
            return np.zeros(pts.shape[:-1], dtype=bool)
        if pts.shape == (3,) and all(math.isfinite(x) for x in pts.tolist()):
            # One point (each tick asks of the vehicle's): the same cube, without the arrays' overhead.
            nx, ny, nz = self.shape
            i, j, k = (math.floor(x / self.voxel_m) - int(o) for x, o in zip(pts.tolist(), self.origin.tolist()))
            if not (0 <= i < nx and 0 <= j < ny and 0 <= k < nz):
                return np.bool_(False)
            return np.bool_(self._infl.reshape(-1)[(i * ny + j) * nz + k] > 0)
        idx, inside = self._index(pts)
        return inside & self._inflated_at(idx)

    def nearest_surface(self, position_ned_m: np.ndarray, within_m: float) -> tuple[float, np.ndarray] | None:
        """The nearest surface seen to a point: the distance (metres) from ``position_ned_m`` (float
        ``(3,)`` NED m) to the nearest point of the nearest occupied cube, and the unit NED direction
        (float64 ``(3,)``) toward that point; None where no occupied cube comes within ``within_m``
        (or the point is inside one: no direction)."""
        if self.origin is None:
            return None
        p = np.asarray(position_ned_m, dtype=np.float64)
        n = int(math.ceil(within_m / self.voxel_m)) + 1
        c = self._cube(p) - self.origin
        lo = np.maximum(c - n, 0)
        hi = np.minimum(c + n + 1, self._grid_shape)
        if np.any(hi <= lo):
            return None
        sub = self._occ[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
        cubes = np.argwhere(sub)
        if len(cubes) == 0:
            return None
        corner = (cubes + lo + self.origin) * self.voxel_m  # (N, 3) each cube's least corner, NED m
        to = np.clip(p, corner, corner + self.voxel_m) - p  # to each cube's nearest point
        dist = np.linalg.norm(to, axis=1)
        i = int(np.argmin(dist))
        d = float(dist[i])
        if d > within_m or d <= 0.0:
            return None
        return d, to[i] / d

    def free_lengths(self, start_ned_m: np.ndarray, directions: np.ndarray, horizon_m: float | None = None) -> FreeLengths:
        """How far the centre may fly from ``start_ned_m`` (float ``(3,)`` NED m) along each of
        ``directions`` (float ``(K, 3)`` unit NED): up to the first sample whose cube is within the
        radius of a surface, or whose cube on the line, or on the body's rim round it, was not seen
        free (unknown is near), at most ``horizon_m`` (default the map range). Samples every cube.

        The rim is judged from two radii out: nearer, it is the vehicle's own surroundings, beside
        and above a camera that looks ahead and cannot see them (it flies there only once the line
        ahead has been judged, rim and all, from farther back).

        Where the start itself is within the radius of a surface (a gust, a late brake), the first
        radius of each line is judged on the surfaces alone, not their inflation, so that the way out
        is open and the way in is not."""
        d = np.ascontiguousarray(np.asarray(directions, dtype=np.float64).reshape(-1, 3))
        start = np.ascontiguousarray(np.asarray(start_ned_m, dtype=np.float64).reshape(3))
        if self.origin is None:
            return self._nothing_free(len(d))
        h = self.range_m if horizon_m is None else float(horizon_m)
        s = np.arange(self.voxel_m, h + 1e-9, self.voxel_m)
        if bool(self.within_radius(start)):
            # Only the first radius of each line (a few samples) is judged so.
            n = int(np.count_nonzero(s <= self.radius_m + self.voxel_m))
            pts = start + d[:, None, :] * s[None, :n, None]  # (K, n, 3)
            idx, _ = self._index(pts)
            near = self._occ.reshape(-1)[idx] | _moves_closer(self, start, pts)
        else:
            near = np.zeros((len(d), 0), dtype=bool)
        return self._walk(np.repeat(start[None, :], len(d), axis=0), d, s, h, near)  # writable: one compiled kernel

    def free_lengths_from(self, starts_ned_m: np.ndarray, directions: np.ndarray, horizon_m: float | None = None) -> FreeLengths:
        """:meth:`free_lengths` of K lines each from its own start (``starts_ned_m`` float ``(K, 3)``
        NED m), judged alike from the first sample: a start within a surface's radius ends its line
        there, blocked (the way out of a surface is judged only from where the vehicle is)."""
        d = np.ascontiguousarray(np.asarray(directions, dtype=np.float64).reshape(-1, 3))
        starts = np.ascontiguousarray(np.asarray(starts_ned_m, dtype=np.float64).reshape(-1, 3))
        if self.origin is None:
            return self._nothing_free(len(d))
        h = self.range_m if horizon_m is None else float(horizon_m)
        s = np.arange(self.voxel_m, h + 1e-9, self.voxel_m)
        blocked_at_start = self.within_radius(starts)
        fl = self._walk(starts, d, s, h, np.zeros((len(d), 0), dtype=bool))
        return FreeLengths(
            np.where(blocked_at_start, 0.0, fl.length_m), fl.blocked | blocked_at_start, fl.horizon & ~blocked_at_start
        )

    @staticmethod
    def _nothing_free(k: int) -> FreeLengths:
        return FreeLengths(np.zeros(k), np.zeros(k, bool), np.zeros(k, bool))

    def _walk(self, starts: np.ndarray, d: np.ndarray, s: np.ndarray, h: float, near: np.ndarray) -> FreeLengths:
        """The compiled walk of :meth:`free_lengths`: lines from ``starts`` (float64 ``(K, 3)``) along
        ``d`` (float64 ``(K, 3)``) sampled at ``s`` (float64 ``(S,)`` m) up to the horizon ``h`` (m);
        ``near`` (bool ``(K, n)``) replaces the inflation for the first n samples."""
        from companion.core.planner import _mapkernels

        first = np.empty(len(d), dtype=np.int64)
        blocked = np.empty(len(d), dtype=bool)
        _mapkernels.free_lengths(
            starts, d, s, self.radius_m, self._rim_cos, self._rim_sin, 2.0 * self.radius_m, near,
            self.voxel_m, np.asarray(self.origin, dtype=np.int64), self._grid_shape,
            self._infl.reshape(-1), self._fcnt.reshape(-1), self._evidence_ok.reshape(-1), self._body_mask.reshape(-1),
            first, blocked,
        )  # fmt: skip
        any_bad = first < len(s)
        length = np.where(first > 0, s[np.maximum(first - 1, 0)], 0.0)
        length = np.where(any_bad, length, h)
        return FreeLengths(length_m=length, blocked=blocked, horizon=~any_bad)

    def clear_along(
        self, start_ned_m: np.ndarray, velocities_ned_m_s: np.ndarray, directions: np.ndarray, speeds_m_s: np.ndarray,
        t_s: np.ndarray, lag_s: np.ndarray, tail: int, range_m: float,
    ) -> np.ndarray:
        """How far along the path the vehicle will fly from ``start_ned_m`` (float ``(3,)`` NED m) toward
        each command (``directions`` float ``(K, 3)`` unit NED, ``speeds_m_s`` ``(K,)``) the centre stays
        out of every surface's inflation, the least over the velocities it may start from (float
        ``(P, 3)`` NED m/s): arc length, metres (float64 ``(K,)``; inf where it never enters one). The
        paths are :func:`~companion.core.planner.paths.predicted_paths`: the swing's times ``t_s`` and
        lag factors ``lag_s`` (float64 ``(M,)``, :func:`~companion.core.planner.paths.swing_profile`),
        then ``tail`` samples a cube apart, judged within ``range_m`` of arc (m). Compiled: each path is
        followed to its first sample in a surface's inflation (a test compares it with whole-array
        NumPy).

        Only surfaces seen block here, not unknown space: this judges the swing of a lagging vehicle
        round a line whose own seen-free length is judged by :meth:`free_lengths`. As there, where the
        start is within the radius of a surface the first radius is judged on the surfaces alone."""
        d = np.ascontiguousarray(np.asarray(directions, dtype=np.float64).reshape(-1, 3))
        out = np.empty(len(d))
        if self.origin is None:
            out[...] = 0.0
            return out
        from companion.core.planner import _mapkernels

        start = np.ascontiguousarray(np.asarray(start_ned_m, dtype=np.float64).reshape(3))
        near_m = self.radius_m + self.voxel_m if bool(self.within_radius(start)) else -1.0
        _mapkernels.swing_clear(
            start, np.ascontiguousarray(np.asarray(velocities_ned_m_s, dtype=np.float64).reshape(-1, 3)), d,
            np.ascontiguousarray(np.asarray(speeds_m_s, dtype=np.float64).reshape(-1)),
            np.ascontiguousarray(t_s, dtype=np.float64), np.ascontiguousarray(lag_s, dtype=np.float64),
            self.voxel_m, int(tail), float(range_m) + 1e-9, near_m, self.voxel_m,
            np.asarray(self.origin, dtype=np.int64), self._grid_shape, self._infl.reshape(-1), self._occ.reshape(-1), out,
        )  # fmt: skip
        return out


def compile_kernels() -> None:
    """Compile the map's query kernels now (about a second, once per process)."""
    m = LocalMap(voxel_m=0.5, range_m=1.0, radius_m=0.25, occupied_memory_s=1.0, free_memory_s=1.0)
    m.centre_on(np.zeros(3))
    m.free_lengths(np.zeros(3), np.array([[1.0, 0.0, 0.0]]))
    m.blocked_columns(0.0, -0.5, 0.5)
    m.clear_along(np.zeros(3), np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0]]), np.ones(1), np.ones(1), np.ones(1), 1, 1.0)


def _moves_closer(m: LocalMap, start: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """bool ``(K, S)``: samples nearer to the nearest occupied cube round ``start`` than ``start`` is
    (the way in, from inside the inflation)."""
    n = int(math.ceil(m.radius_m / m.voxel_m)) + 1
    c = np.floor(start / m.voxel_m).astype(np.int64) - m.origin
    lo_ = np.maximum(c - n, 0)
    hi_ = np.minimum(c + n + 1, np.array(m.shape))
    occ = m.occupied()[lo_[0] : hi_[0], lo_[1] : hi_[1], lo_[2] : hi_[2]]
    cubes = np.argwhere(occ)
    if len(cubes) == 0:
        return np.zeros(pts.shape[:2], dtype=bool)
    centres = (cubes + lo_ + m.origin + 0.5) * m.voxel_m  # (M, 3)
    d0 = np.min(np.linalg.norm(centres - start, axis=1))
    dp = np.min(np.linalg.norm(pts[:, :, None, :] - centres[None, None, :, :], axis=-1), axis=-1)
    return dp < d0 - 1e-9
