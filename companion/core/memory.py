"""Obstacle memory and the out-of-view guard (pure NumPy; time is passed in).

The camera measures only ahead (ZED: about ±44°, less on the left, :func:`view_limits`). An obstacle
the vehicle turned away from, or is flying past, leaves the view while it is still beside the vehicle,
and a multicopter drifts with its position estimate's error (PX4 SITL: ~0.2 m/s) sideways into it. So
what the camera saw near is kept (``memory.duration_s`` after it was last seen) as points in the local
NED frame, one per 5 cm cube (:class:`ObstacleMemory`), and a point that is out of the measured view
(or nearer than the rig can see) and within ``memory.guard_distance_m`` of the vehicle, horizontally,
guards it: :func:`apply_guard` pushes the vehicle away, and removes the velocity toward the point
when the point is on its path (see :func:`~companion.core.command.setpoint_for`). Course hold also
neither turns nor slides toward a side with a point within ``memory.hold_clear_m``, abreast or
ahead (:meth:`ObstacleMemory.sides_near`), and between points on both sides of a narrow gap (a
doorway) a clear decision slides toward the gap's middle, and does not fly on into it until it is
lined up with it (:func:`find_gap`). The autopilot follows a setpoint late (PX4: ~0.85 s), so
the guard also counts the path the vehicle is actually flying (and, with
``memory.counter_velocity_fraction``, leans against its motion toward a point on it).

From one frame to points (:func:`block_max`, :class:`NearCells`):

1. :class:`BlockMax`: the disparity image reduced to the largest valid disparity of each
   ``block_px``-square block (the nearest surface in it), float32, NaN for none. The GPU estimator
   computes this on the device; :func:`block_max` is the CPU reference it must match.
2. cells: the block image split into ``grid_rows × grid_cols`` cells; a cell with fewer valid blocks
   than ``min_valid_fraction`` is empty, else its disparity is the ``k``-th largest valid block with
   ``k = max(1, ceil(robust_percentile_pct/100 · n_valid))`` (as the regions do), its depth
   ``f·B/d``.
3. confirmation: a cell's depth is the median of its last ``confirm_frames`` depths, an empty cell
   counting as far, so that a false match lasting one frame is not remembered.
4. points: each cell nearer than ``max_depth_m`` gives one point at that depth, on the ray of the block
   it came from, in the camera frame (x right, y down, z forward, metres).
5. seeing through (:class:`FarView`, :meth:`ObstacleMemory.see_through`): a remembered point that
   ``map_clear_after_frames`` frames in a row see well past (every valid block round its ray measures
   at least ``map_clear_depth_ratio`` times its depth) leaves the detour layer's map
   (:meth:`ObstacleMemory.map_points`) until it is seen again. A false match (a door's jamb smeared
   into its opening, an alias on a fence) is not there when looked at again; a true surface is seen
   again at its depth, or not measured at all (a plain wall: no valid block), which never clears it.
   It still guards: the position estimate's drift moves true points off their surfaces too, where
   they are seen past, and the guard needs them. Only ``guard_clear_after_s`` of seeing past in a row (4 s; each
   frame counts the time since the one before, at most :data:`LONGEST_COUNTED_FRAME_S`) take a
   point out of the guard as well: seconds, so that it means the same at any camera rate.

The memory lives in the vehicle's position estimate; a real estimate drifts against the world, which
is why points are forgotten.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from companion.config.core import MemoryConfig
from companion.core.frames import ned_to_body_horizontal
from companion.core.geometry import StereoGeometry
from companion.core.pose import Pose

#: The most one frame that sees past a point adds to the time it has been seen past, seconds (a 5 fps
#: camera's interval): after a camera stall one frame is one look, not the stall's length.
LONGEST_COUNTED_FRAME_S = 0.2

#: Tolerance when the summed frame intervals meet ``guard_clear_after_s``, seconds: 60 frames at 15 Hz
#: sum to 4 s give or take float rounding, and must count as 4 s.
_SUM_TOLERANCE_S = 1e-6

#: Sectors (of the full circle around the vehicle) the guard keeps one nearest point from.
GUARD_SECTORS = 8


class Gap(NamedTuple):
    """A narrow gap beside and ahead of the vehicle (:func:`find_gap`), body frame."""

    offset_m: float  # where its middle lies, sideways from the vehicle, metres (positive = right)
    width_m: float  # between the nearest bounding points left and right, metres


class HoldInputs(NamedTuple):
    """What the memory gives :func:`~companion.core.command.setpoint_for` for one setpoint."""

    guard_m: np.ndarray | None  # :meth:`ObstacleMemory.guard` rows, or None
    sides: tuple[bool, bool] | None  # :meth:`ObstacleMemory.sides_near`, or None
    gap: Gap | None  # :func:`find_gap`, or None
    ahead_m: float | None = None  # :func:`path_ahead_m`, or None


class BlockMax:
    """The largest valid disparity of each ``block_px × block_px`` block (the nearest surface in it),
    into buffers allocated once for one image shape.

    With ``erode_px`` = k > 0, each pixel first takes the smallest disparity of its row's pixels
    ``x - k .. x + k`` inside the image (an invalid one, NaN, is the smallest): a pixel counts only
    where its neighbours see something as near. A lone too-near pixel and a foreground edge smeared
    ``k`` px onto what is behind it (a semi-global matcher's, across a door's jamb) then give no block
    its depth; a true surface loses ``k`` px at each side.

    Args:
        shape: ``(H, W)`` of the disparity images, pixels.
        block_px: block side, pixels (>= 1).
        erode_px: k, pixels (>= 0).
    """

    def __init__(self, shape: tuple[int, int], block_px: int, erode_px: int = 0) -> None:
        b = int(block_px)
        if b < 1:
            raise ValueError(f"block_px must be >= 1, got {block_px}")
        k = int(erode_px)
        if k < 0:
            raise ValueError(f"erode_px must be >= 0, got {erode_px}")
        h, w = int(shape[0]), int(shape[1])
        self.shape = (h, w)
        self.block_px = b
        self.erode_px = k
        self._eroded = np.empty((h, w), dtype=np.float32) if k else None
        self.out_shape = (-(-h // b), -(-w // b))
        oh, ow = self.out_shape
        # Partial edge blocks: the image is copied into a NaN-filled buffer of whole blocks; an image
        # of whole blocks (ZED VGA and HD at 4 px) is reduced in place.
        self._pad = None if (h % b == 0 and w % b == 0) else np.full((oh * b, ow * b), np.nan, dtype=np.float32)
        self._cols = np.empty((oh * b, ow), dtype=np.float32)
        self._out = np.empty((oh, ow), dtype=np.float32)

    def __call__(self, disparity: np.ndarray) -> np.ndarray:
        """``disparity``: float32 ``(H, W)`` pixels, NaN invalid → float32 ``out_shape``, NaN where a
        block has no valid pixel. The result is a buffer reused by the next call."""
        if disparity.shape != self.shape:
            raise ValueError(f"disparity must be {self.shape}, got {disparity.shape}")
        h, w = self.shape
        b = self.block_px
        src = disparity
        if self._eroded is not None:
            src = erode_rows(disparity, self.erode_px, out=self._eroded)
        if self._pad is not None:
            np.copyto(self._pad[:h, :w], src, casting="same_kind")
            src = self._pad
        # b strided column slices, then b strided row slices: a few whole-array ufunc calls, far
        # faster than a reduction over a length-b axis.
        cols, out = self._cols, self._out
        np.copyto(cols, src[:, 0::b], casting="same_kind")
        for k in range(1, b):
            np.fmax(cols, src[:, k::b], out=cols)
        np.copyto(out, cols[0::b, :])
        for k in range(1, b):
            np.fmax(out, cols[k::b, :], out=out)
        return out


def block_max(disparity: np.ndarray, block_px: int, erode_px: int = 0) -> np.ndarray:
    """:class:`BlockMax` of one image, as a new float32 ``(ceil(H/b), ceil(W/b))`` array: the CPU
    reference of the GPU estimator's device-side reduction."""
    d = np.asarray(disparity, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f"disparity must be 2-D, got shape {d.shape}")
    return BlockMax((d.shape[0], d.shape[1]), block_px, erode_px)(d).copy()


def erode_rows(disparity: np.ndarray, erode_px: int, out: np.ndarray | None = None) -> np.ndarray:
    """Each pixel the smallest of its row's ``x - k .. x + k`` inside the image, NaN (invalid) the
    smallest of all: float32 ``(H, W)`` px, into ``out`` (a new array if None; not ``disparity``)."""
    d = disparity
    if out is None:
        out = np.empty(d.shape, dtype=np.float32)
    np.copyto(out, d, casting="same_kind")
    for j in range(1, int(erode_px) + 1):
        np.minimum(out[:, j:], d[:, :-j], out=out[:, j:])  # np.minimum propagates NaN
        np.minimum(out[:, :-j], d[:, j:], out=out[:, :-j])
    return out


class NearCells:
    """Per frame: disparity blocks → confirmed near points in the camera frame (module doc, 2-4).

    Built once per (config, geometry, block image shape): the index tables and every block's ray are
    precomputed, and the per-frame history is a fixed-length deque.

    Args:
        cfg: the memory section.
        geometry: the rectified rig (focal length, principal point, f·B), pixels.
        block_shape: ``(rows, cols)`` of the block image :class:`BlockMax` makes of one frame.
    """

    def __init__(self, cfg: MemoryConfig, geometry: StereoGeometry, block_shape: tuple[int, int]) -> None:
        self.cfg = cfg
        self._fb = float(geometry.focal_baseline_px_m)
        self._geometry = geometry
        bh, bw = int(block_shape[0]), int(block_shape[1])
        self.block_shape = (bh, bw)
        rows, cols = min(cfg.grid_rows, bh), min(cfg.grid_cols, bw)
        r_edges = np.round(np.linspace(0, bh, rows + 1)).astype(np.int64)
        c_edges = np.round(np.linspace(0, bw, cols + 1)).astype(np.int64)
        per_cell = int(np.max(np.diff(r_edges))) * int(np.max(np.diff(c_edges)))
        # Flat block indices of each cell; padding points at an extra block that is always NaN.
        pad = bh * bw
        index = np.full((rows * cols, per_cell), pad, dtype=np.int64)
        count = np.zeros(rows * cols, dtype=np.int64)
        for r in range(rows):
            for c in range(cols):
                yy, xx = np.mgrid[r_edges[r] : r_edges[r + 1], c_edges[c] : c_edges[c + 1]]
                flat = (yy * bw + xx).reshape(-1)
                index[r * cols + c, : flat.size] = flat
                count[r * cols + c] = flat.size
        self._index = index
        self._count = count
        # The ray (x/z, y/z) through each block's centre (pixel centres at integers); a point is put
        # on the ray of the block that gave its cell's depth, not the cell's centre, so that a wall
        # seen at a grazing angle is not placed nearer the vehicle's path than it is.
        b = cfg.block_px
        f, cx, cy = float(geometry.focal_px), float(geometry.cx_px), float(geometry.cy_px)
        by, bx = np.mgrid[0:bh, 0:bw]
        rays = np.zeros((pad + 1, 2))
        rays[:pad, 0] = ((bx.reshape(-1) + 0.5) * b - 0.5 - cx) / f
        rays[:pad, 1] = ((by.reshape(-1) + 0.5) * b - 0.5 - cy) / f
        self._block_rays = rays
        self._flat = np.full(pad + 1, np.nan, dtype=np.float32)
        self._gather = np.empty(index.shape, dtype=np.float32)
        self._rows = np.arange(rows * cols)
        self._depths: deque[np.ndarray] = deque(maxlen=cfg.confirm_frames)
        self._rays: deque[np.ndarray] = deque(maxlen=cfg.confirm_frames)

    def reset(self) -> None:
        """Forget the confirmation history (camera reconnect, reconfigure)."""
        self._depths.clear()
        self._rays.clear()

    def cell_depths(self, blocks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One frame's cells, unconfirmed, from its block image (float32 ``block_shape`` pixels, NaN
        none): depth float64 ``(cells,)`` metres (+inf for an empty cell) and the ray the depth was
        seen along, float64 ``(cells, 2)`` (x/z, y/z)."""
        if blocks.shape != self.block_shape:
            raise ValueError(f"block image must be {self.block_shape}, got {blocks.shape}")
        self._flat[:-1] = blocks.reshape(-1)
        vals = self._gather
        np.take(self._flat, self._index, out=vals)
        valid = vals > 0.0  # NaN compares False
        n_valid = valid.sum(axis=1)
        vals[~valid] = -np.inf
        order = np.argsort(vals, axis=1)  # ascending: the k-th largest is at per_cell - k
        k = np.maximum(1, np.ceil(self.cfg.robust_percentile_pct * n_valid / 100.0)).astype(np.int64)
        pick = order[self._rows, vals.shape[1] - np.minimum(k, vals.shape[1])]
        d = vals[self._rows, pick].astype(np.float64)
        ok = (n_valid > 0) & (n_valid >= self.cfg.min_valid_fraction * self._count) & (d > 0.0)
        depth = np.full(d.shape, np.inf)
        depth[ok] = self._fb / d[ok]
        return depth, self._block_rays[self._index[self._rows, pick]]

    def points(self, blocks: np.ndarray) -> np.ndarray:
        """This frame's confirmed points out to ``max(max_depth_m, map_depth_m)``, float64 ``(K, 3)``
        camera frame (x right, y down, z forward) metres, ``K <= cells``; call once per frame, in
        order (it keeps the history). Those beyond ``max_depth_m`` are for the detour layer's map
        only (:class:`ObstacleMemory` keeps each point's depth)."""
        depth, rays = self.cell_depths(blocks)
        self._depths.append(depth)
        self._rays.append(rays)
        n = self.cfg.confirm_frames
        if len(self._depths) < n:
            return np.empty((0, 3))
        # The median frame of each cell (an empty cell, inf, counts as far), and the ray it saw.
        stack = np.stack(self._depths)
        which = np.argsort(stack, axis=0, kind="stable")[n // 2]
        z = stack[which, self._rows]
        near = z <= max(self.cfg.max_depth_m, self.cfg.map_depth_m)
        ray = np.stack(self._rays)[which, self._rows][near]
        z = z[near]
        return np.stack([ray[:, 0] * z, ray[:, 1] * z, z], axis=1)

    def far_view(self, blocks: np.ndarray, view: ViewLimits) -> FarView:
        """This frame's :class:`FarView` from its block image (float32 ``block_shape``, NaN none), for
        :meth:`ObstacleMemory.see_through`."""
        if blocks.shape != self.block_shape:
            raise ValueError(f"block image must be {self.block_shape}, got {blocks.shape}")
        return FarView(window_max(blocks, CLEAR_WINDOW_BLOCKS), self._geometry, self.cfg.block_px, view)


@dataclass(frozen=True)
class ViewLimits:
    """What the rig measures: bearings off the optical axis (radians, both positive) out to which
    the left and right sides are matched, and the nearest depth it can match, metres."""

    left_rad: float
    right_rad: float
    min_range_m: float

    def covers(self, bearing_rad: np.ndarray, range_m: np.ndarray) -> np.ndarray:
        """bool, broadcast: whether the rig measures a point ``bearing_rad`` off the optical axis
        (positive right) and ``range_m`` metres away."""
        return (bearing_rad >= -self.left_rad) & (bearing_rad <= self.right_rad) & (range_m >= self.min_range_m)


def view_limits(geometry: StereoGeometry, num_disparities: int) -> ViewLimits:
    """What the rig measures (:class:`ViewLimits`): the image's sides, where the left image's first
    ``num_disparities - 1`` columns count as unseen (no match can be searched there: their partners
    would lie left of the right image, so block matching leaves them invalid; 64 disparities at
    336 px: the left 19° of a 90° view), and ``f·B / (num_disparities - 1)`` metres."""
    f, cx = float(geometry.focal_px), float(geometry.cx_px)
    return ViewLimits(
        left_rad=math.atan(max(0.0, cx - (num_disparities - 1)) / f),
        right_rad=math.atan(max(0.0, geometry.width_px - 1 - cx) / f),
        min_range_m=float(geometry.focal_baseline_px_m) / max(1, num_disparities - 1),
    )


#: A remembered point counts as seen past only if every valid block within this many blocks of its
#: ray (a 5 × 5 window at 2) measures beyond it: the point's place in the image is uncertain by the
#: pose's error and the block it came from, and a thin surface beside the ray must keep it.
CLEAR_WINDOW_BLOCKS = 2


@dataclass(frozen=True)
class FarView:
    """What one frame measured, for :meth:`ObstacleMemory.see_through`.

    Attributes:
        nearest_disparity_px: float32 ``(rows, cols)`` of the block image: the largest valid block
            disparity within :data:`CLEAR_WINDOW_BLOCKS` of each block (the nearest surface round
            its ray), pixels; NaN where the block itself has no valid disparity (not measured).
        geometry: the rectified rig the frame was seen with (pixel centres at integers).
        block_px: the block side, pixels.
        view: what the rig measures (:class:`ViewLimits`): points outside it, or nearer than its
            nearest depth, are not judged.
    """

    nearest_disparity_px: np.ndarray
    geometry: StereoGeometry
    block_px: int
    view: ViewLimits


def window_max(blocks: np.ndarray, radius: int) -> np.ndarray:
    """The largest valid value within ``radius`` blocks of each block of ``blocks`` (float ``(rows,
    cols)``, NaN or <= 0 invalid), float32 of the same shape; NaN where the block itself is invalid."""
    b = np.asarray(blocks, dtype=np.float32)
    valid = b > 0.0  # NaN compares False
    src = np.where(valid, b, -np.inf).astype(np.float32)
    rows, cols = src.shape
    # Separable: the window's maximum is the maximum over rows of the maximum over columns.
    pad = np.full((rows, cols + 2 * radius), -np.inf, dtype=np.float32)
    pad[:, radius : radius + cols] = src
    across = np.full((rows + 2 * radius, cols), -np.inf, dtype=np.float32)
    mid = across[radius : radius + rows]
    for dx in range(2 * radius + 1):
        np.maximum(mid, pad[:, dx : dx + cols], out=mid)
    out = np.full((rows, cols), -np.inf, dtype=np.float32)
    for dy in range(2 * radius + 1):
        np.maximum(out, across[dy : dy + rows], out=out)
    out[~valid] = np.nan
    return out


def camera_points_to_ned(points_cam_m: np.ndarray, pose: Pose) -> np.ndarray:
    """Camera-frame points (float ``(K, 3)`` metres) seen from ``pose`` → NED, float64 ``(K, 3)`` m."""
    p = np.asarray(points_cam_m, dtype=np.float64).reshape(-1, 3)
    return p @ pose.ned_from_camera().T + np.asarray(pose.position_ned_m, dtype=np.float64)


def _pack_cubes(q: np.ndarray) -> np.ndarray:
    """int64 ``(K,)`` keys of integer cube indices ``q`` (int64 ``(K, 3)``)."""
    q = q + (1 << 20)  # ±52 km at 5 cm: never wraps
    return (q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2]


class _CellViews:
    """How often, how long and from how far apart each ``memory.trust_cell_m`` cube has been seen:
    sorted cube keys, first and last time seen, frames seen in, the first viewpoint (north, east) and
    the largest horizontal distance of a later viewpoint from it. A new cube side starts again."""

    def __init__(self) -> None:
        self._clear(None)

    def _clear(self, cell_m: float | None) -> None:
        self.cell_m = cell_m
        self.keys = np.empty(0, dtype=np.int64)
        self.first = np.empty(0)
        self.last = np.empty(0)
        self.count = np.empty(0, dtype=np.int64)
        self.vp = np.empty((0, 2))
        self.spread = np.empty(0)

    @staticmethod
    def _keys_of(p: np.ndarray, cell_m: float) -> np.ndarray:
        return _pack_cubes(np.floor(p / cell_m).astype(np.int64))

    def update(self, p: np.ndarray, t_s: float, duration_s: float, vp: np.ndarray, cfg: MemoryConfig) -> None:
        """Count the cubes of ``p`` (float ``(K, 3)`` NED metres) as seen at ``t_s`` from ``vp`` (float
        ``(2,)`` north, east metres, NaN unknown); forget those unseen for ``duration_s``."""
        cell_m = cfg.trust_cell_m
        if self.cell_m != cell_m:
            self._clear(cell_m)
        keep = (t_s - self.last) <= duration_s
        if not np.all(keep):
            self.keys, self.first, self.last = self.keys[keep], self.first[keep], self.last[keep]
            self.count, self.vp, self.spread = self.count[keep], self.vp[keep], self.spread[keep]
        if not len(p):
            return
        seen = np.unique(self._keys_of(p, cell_m))
        at = np.searchsorted(self.keys, seen)
        known = at < self.keys.size
        known[known] = self.keys[at[known]] == seen[known]
        i = at[known]
        self.last[i] = t_s
        self.count[i] += 1
        vp0 = self.vp[i]
        missing = ~np.all(np.isfinite(vp0), axis=1)
        if np.all(np.isfinite(vp)):
            vp0[missing] = vp  # the first viewpoint known
            self.vp[i] = vp0
            self.spread[i] = np.maximum(self.spread[i], np.hypot(vp0[:, 0] - vp[0], vp0[:, 1] - vp[1]))
        fresh = seen[~known]
        if fresh.size:
            keys = np.concatenate([self.keys, fresh])
            order = np.argsort(keys, kind="stable")
            n = fresh.size
            self.keys = keys[order]
            self.first = np.concatenate([self.first, np.full(n, float(t_s))])[order]
            self.last = np.concatenate([self.last, np.full(n, float(t_s))])[order]
            self.count = np.concatenate([self.count, np.ones(n, dtype=np.int64)])[order]
            self.vp = np.concatenate([self.vp, np.tile(vp, (n, 1))])[order]
            self.spread = np.concatenate([self.spread, np.zeros(n)])[order]

    def seen(
        self, points_ned_m: np.ndarray, cfg: MemoryConfig, baseline_m: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """bool ``(K,)`` twice: each point's cube seen from two positions ``baseline_m`` apart (None:
        ``cfg.trust_baseline_m``); seen in ``cfg.trust_min_frames`` frames spanning
        ``cfg.trust_persist_s``. All False when the cubes were not kept at ``cfg.trust_cell_m``."""
        baseline = cfg.trust_baseline_m if baseline_m is None else baseline_m
        cell_m = cfg.trust_cell_m
        p = np.asarray(points_ned_m, dtype=np.float64).reshape(-1, 3)
        if not len(p) or self.cell_m != cell_m or not self.keys.size:
            none = np.zeros(len(p), dtype=bool)
            return none, none.copy()
        keys = self._keys_of(p, cell_m)
        at = np.minimum(np.searchsorted(self.keys, keys), self.keys.size - 1)
        found = self.keys[at] == keys
        by_place = found & (self.spread[at] >= baseline) & (self.count[at] >= 2)
        by_time = found & (self.count[at] >= cfg.trust_min_frames) & (self.last[at] - self.first[at] >= cfg.trust_persist_s)
        return by_place, by_time


class ObstacleMemory:
    """Remembered points, NED metres, one per ``voxel_m`` cube, with the time each cube was last seen
    occupied and the nearest depth it was seen at (re-seeing a cube refreshes it instead of adding a
    copy, so a vehicle that hovers in front of a wall does not fill the memory with it).

    Only points seen nearer than ``memory.max_depth_m`` guard the vehicle and keep course hold from a
    side (:meth:`guard`, :meth:`sides_near`, :meth:`hold_inputs`); the farther ones (out to
    ``memory.map_depth_m``) are for the detour layer's map (:meth:`map_points`).

    **Trust.** A false stereo match moves with the view where a surface does not, so a point is
    *trusted* (:meth:`map_points`, slowing for the path) only once the ``memory.trust_cell_m`` cube it
    lies in has been seen from two camera positions at least ``memory.trust_baseline_m`` apart, or in
    ``memory.trust_min_frames`` frames spanning at least ``memory.trust_persist_s``. Untrusted points
    still guard, but only by stopping the motion toward them: the guard's push away moves the vehicle
    sideways into what the camera does not see (a false point in the air, seen for a moment from one
    place, could push the vehicle into a pillar out of view). So a point
    *may push* (and bound a gap to centre in, :meth:`may_push`) only once its cube has been seen from
    two positions ``memory.push_baseline_m`` apart, more than a cube's width: a false match that
    follows the vehicle (StereoBM's alias on a fence's bars, a smudge on the lens) persists, and stays
    in one cube only while the vehicle moves less than that. Trusted by persistence alone, such an
    alias would push the vehicle into the wall across from it.

    Args:
        max_points: most cubes kept; beyond it the least recently seen are dropped.
        voxel_m: the cube side, metres.
    """

    def __init__(self, max_points: int = 20000, voxel_m: float = 0.05) -> None:
        self.max_points = int(max_points)
        self.voxel_m = float(voxel_m)
        self.reset()

    def __len__(self) -> int:
        return int(self._keys.size)

    def reset(self) -> None:
        self._keys = np.empty(0, dtype=np.int64)
        self._pts = np.empty((0, 3))
        self._t = np.empty(0)
        self._range = np.empty(0)
        self._misses = np.empty(0, dtype=np.int64)  # frames in a row that saw past each point
        self._past_s = np.empty(0)  # seconds in a row seen past (LONGEST_COUNTED_FRAME_S a frame)
        self._judged_t_s: float | None = None  # when see_through last judged
        self._trust = _CellViews()  # trust_cell_m cubes: where from, how often, how long

    def _key(self, p: np.ndarray) -> np.ndarray:
        return _pack_cubes(np.floor(p / self.voxel_m).astype(np.int64))

    def add_frame(
        self,
        points_cam_m: np.ndarray,
        seen_from: Pose,
        t_s: float,
        cfg: MemoryConfig,
        far_view: FarView | None = None,
    ) -> None:
        """One frame's points (float ``(K, 3)`` camera frame metres, :meth:`NearCells.points`) seen from
        ``seen_from`` at ``t_s`` seconds: first :meth:`see_through` with the frame's ``far_view`` (None:
        not judged), then :meth:`add` with their depths and the viewpoint."""
        if far_view is not None:
            self.see_through(far_view, seen_from, t_s, cfg)
        p = np.asarray(points_cam_m, dtype=np.float64).reshape(-1, 3)
        self.add(
            camera_points_to_ned(p, seen_from),
            t_s,
            cfg.duration_s,
            ranges_m=p[:, 2],
            viewpoint_ned_m=np.asarray(seen_from.position_ned_m, dtype=np.float64),
            cfg=cfg,
        )

    def add(
        self,
        points_ned_m: np.ndarray,
        t_s: float,
        duration_s: float,
        *,
        ranges_m: np.ndarray | None = None,
        viewpoint_ned_m: np.ndarray | None = None,
        cfg: MemoryConfig | None = None,
    ) -> None:
        """Remember ``points_ned_m`` (float ``(K, 3)`` metres; non-finite rows are dropped) as seen at
        ``t_s`` seconds, and forget what was last seen more than ``duration_s`` before it.

        ``ranges_m``: float ``(K,)`` the depth each was seen at, metres (None: 0, i.e. near);
        ``viewpoint_ned_m``: float ``(3,)`` where the camera was (None: unknown, trust by persistence
        only); ``cfg``: the memory section, for the trust cubes (None: trust is not kept)."""
        p = np.asarray(points_ned_m, dtype=np.float64).reshape(-1, 3)
        r = np.zeros(len(p)) if ranges_m is None else np.asarray(ranges_m, dtype=np.float64).reshape(-1)
        ok = np.all(np.isfinite(p) & (np.abs(p) < 1e6), axis=1) & np.isfinite(r)
        p, r = p[ok], r[ok]
        if not math.isfinite(t_s):
            return
        keep = (t_s - self._t) <= duration_s
        keys, pts, ts, rs = self._keys[keep], self._pts[keep], self._t[keep], self._range[keep]
        misses, past_s = self._misses[keep], self._past_s[keep]
        if len(p):
            new_keys, inverse = np.unique(self._key(p), return_inverse=True)
            first = np.zeros(new_keys.size, dtype=np.int64)
            first[inverse[::-1]] = np.arange(len(p))[::-1]
            # The nearest depth this frame saw each cube at, and the nearest it was seen at before.
            new_r = np.full(new_keys.size, np.inf)
            np.minimum.at(new_r, inverse, r)
            old = np.isin(keys, new_keys)
            if np.any(old):
                at = np.searchsorted(new_keys, keys[old])
                np.minimum.at(new_r, at, rs[old])
            keys = np.concatenate([keys[~old], new_keys])
            pts = np.concatenate([pts[~old], p[first]])
            ts = np.concatenate([ts[~old], np.full(new_keys.size, float(t_s))])
            rs = np.concatenate([rs[~old], new_r])
            misses = np.concatenate([misses[~old], np.zeros(new_keys.size, dtype=np.int64)])  # seen: no misses
            past_s = np.concatenate([past_s[~old], np.zeros(new_keys.size)])
        if keys.size > self.max_points:
            newest = np.argsort(ts, kind="stable")[-self.max_points :]
            keys, pts, ts, rs = keys[newest], pts[newest], ts[newest], rs[newest]
            misses, past_s = misses[newest], past_s[newest]
        self._keys, self._pts, self._t, self._range = keys, pts, ts, rs
        self._misses, self._past_s = misses, past_s
        if cfg is not None:
            self._update_trust(p, t_s, duration_s, viewpoint_ned_m, cfg)

    def see_through(self, far: FarView, seen_from: Pose, t_s: float, cfg: MemoryConfig) -> int:
        """Judge every remembered point against one frame seen from ``seen_from`` at ``t_s`` seconds
        (module doc, 5): a point inside the measured view, no nearer than the rig can measure, whose
        ray's every valid block (:attr:`FarView.nearest_disparity_px`) lies at least
        ``cfg.map_clear_depth_ratio`` times farther counts a miss, and the time since the last frame
        judged (at most :data:`LONGEST_COUNTED_FRAME_S`) as time seen past; one seen at or in front of
        its depth starts again from none; one not judged (out of view, too near, its block not
        measured) keeps its count and time. A point with ``cfg.map_clear_after_frames`` misses in a
        row is left out of :meth:`map_points` (0: never) until it is seen again; one seen past for
        ``cfg.guard_clear_after_s`` no longer guards either. Returns how many points are left out
        now."""
        step_s = 0.0
        if math.isfinite(t_s):
            if self._judged_t_s is not None:
                step_s = min(max(t_s - self._judged_t_s, 0.0), LONGEST_COUNTED_FRAME_S)
            self._judged_t_s = float(t_s)
        if cfg.map_clear_after_frames <= 0 or not self._keys.size:
            return 0
        cam = (self._pts - np.asarray(seen_from.position_ned_m, dtype=np.float64)) @ seen_from.ned_from_camera()
        x, y, z = cam[:, 0], cam[:, 1], cam[:, 2]
        g = far.geometry
        ahead = z > 1e-6
        zs = np.where(ahead, z, 1.0)
        u = g.focal_px * x / zs + g.cx_px
        v = g.focal_px * y / zs + g.cy_px
        rows, cols = far.nearest_disparity_px.shape
        bx = np.floor((u + 0.5) / far.block_px).astype(np.int64)
        by = np.floor((v + 0.5) / far.block_px).astype(np.int64)
        judged = ahead & far.view.covers(np.arctan2(x, zs), z) & (bx >= 0) & (bx < cols) & (by >= 0) & (by < rows)
        d = np.full(z.shape, np.nan, dtype=np.float64)
        d[judged] = far.nearest_disparity_px[by[judged], bx[judged]]
        judged &= np.isfinite(d)
        point_d = g.focal_baseline_px_m / zs
        past = judged & (d * cfg.map_clear_depth_ratio <= point_d)  # measured depth >= ratio x the point's
        self._misses = np.where(past, self._misses + 1, np.where(judged, 0, self._misses))
        self._past_s = np.where(past, self._past_s + step_s, np.where(judged, 0.0, self._past_s))
        return self.seen_past_count(cfg)

    def _seen_past(self, cfg: MemoryConfig) -> np.ndarray:
        """bool ``(points,)``: the points :meth:`see_through` leaves out of the map now."""
        if cfg.map_clear_after_frames <= 0:
            return np.zeros(self._keys.size, dtype=bool)
        return self._misses >= cfg.map_clear_after_frames

    def _update_trust(
        self, p: np.ndarray, t_s: float, duration_s: float, viewpoint_ned_m: np.ndarray | None, cfg: MemoryConfig
    ) -> None:
        vp = np.full(2, np.nan)
        if viewpoint_ned_m is not None:
            v = np.asarray(viewpoint_ned_m, dtype=np.float64).reshape(-1)
            if v.size >= 2 and np.all(np.isfinite(v[:2])):
                vp = v[:2].copy()
        self._trust.update(p, t_s, duration_s, vp, cfg)

    def trusted(self, points_ned_m: np.ndarray, cfg: MemoryConfig) -> np.ndarray:
        """bool ``(K,)``: whether each point (float ``(K, 3)`` NED metres) lies in a trusted cube (see
        the class doc); all False when trust has not been kept with this ``cfg.trust_cell_m``."""
        by_place, by_time = self._trust.seen(points_ned_m, cfg)
        return by_place | by_time

    def may_push(self, points_ned_m: np.ndarray, cfg: MemoryConfig) -> np.ndarray:
        """bool ``(K,)``: whether each point (float ``(K, 3)`` NED metres) may push the vehicle or bound
        a gap to centre in: its ``cfg.trust_cell_m`` cube seen from two camera positions at least
        ``cfg.push_baseline_m`` apart (0: :meth:`trusted`). See the class doc."""
        if cfg.push_baseline_m <= 0.0:
            return self.trusted(points_ned_m, cfg)
        by_place, _ = self._trust.seen(points_ned_m, cfg, baseline_m=cfg.push_baseline_m)
        return by_place

    def points(self, now_s: float, cfg: MemoryConfig) -> tuple[np.ndarray, np.ndarray]:
        """Every point seen within ``cfg.duration_s`` of ``now_s``: float64 ``(K, 3)`` NED metres, and
        bool ``(K,)`` trusted (the audit of false points uses both)."""
        keep = (now_s - self._t) <= cfg.duration_s
        pts = self._pts[keep]
        return pts, self.trusted(pts, cfg)

    def near_mask(self, now_s: float, cfg: MemoryConfig) -> np.ndarray:
        """bool, aligned with :meth:`points`: seen nearer than ``cfg.max_depth_m`` (the points that
        guard)."""
        keep = (now_s - self._t) <= cfg.duration_s
        return self._range[keep] <= cfg.max_depth_m

    def seen_past_mask(self, now_s: float, cfg: MemoryConfig) -> np.ndarray:
        """bool, aligned with :meth:`points`: left out of the detour layer's map now, seen past
        (:meth:`see_through`)."""
        keep = (now_s - self._t) <= cfg.duration_s
        return self._seen_past(cfg)[keep]

    def seen_past_count(self, cfg: MemoryConfig) -> int:
        """How many remembered points are left out of the detour layer's map now, seen past
        (:meth:`see_through`; the health message reports it)."""
        return int(np.count_nonzero(self._seen_past(cfg)))

    def _guard_cleared(self, cfg: MemoryConfig) -> np.ndarray:
        """bool ``(points,)``: the points that no longer guard, seen past for
        ``cfg.guard_clear_after_s`` in a row (:meth:`see_through`); none while that is 0."""
        if cfg.guard_clear_after_s <= 0.0:
            return np.zeros(self._keys.size, dtype=bool)
        return self._past_s >= cfg.guard_clear_after_s - _SUM_TOLERANCE_S

    def guard_cleared_count(self, cfg: MemoryConfig) -> int:
        """How many remembered points no longer guard (:meth:`_guard_cleared`; the health message
        reports it)."""
        return int(np.count_nonzero(self._guard_cleared(cfg)))

    def map_points(
        self,
        position_ned_m: np.ndarray,
        now_s: float,
        cfg: MemoryConfig,
        radius_m: float,
        course_down_m: float | None = None,
    ) -> np.ndarray | None:
        """The trusted points the detour layer maps with: seen within ``cfg.duration_s`` of ``now_s``
        (at any depth out to ``cfg.map_depth_m``), not seen past since (:meth:`see_through`), within
        ``cfg.height_band_m`` of the vehicle's altitude and within ``radius_m`` of it horizontally, as
        float64 ``(N, 2)`` north and east offsets from the vehicle, metres; None without a finite
        position.

        ``course_down_m`` (NED down of the altitude course hold flies back to, metres; None = off):
        only points within the band of that altitude too. A point the vehicle clears at one of the
        two heights is passed there: a door's lintel 0.2 m over a vehicle that has climbed 0.4 m
        (else held at the door as a dead end), or a low wall's top under one that
        has climbed over it. Only while the vehicle is within ``height_band_m`` of that altitude
        (the two bands share at least half their height): farther off, the bands share little or
        nothing, and their common points would be an empty map. The vehicle's own band then
        decides: what is at its height now is what it would hit (an empty map would hand every
        detour straight back into the brake)."""
        pos = np.asarray(position_ned_m, dtype=np.float64).reshape(-1)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            return None
        keep = ((now_s - self._t) <= cfg.duration_s) & ~self._seen_past(cfg)
        rel = self._pts[keep] - pos
        near = (np.abs(rel[:, 2]) <= cfg.height_band_m) & (np.hypot(rel[:, 0], rel[:, 1]) < radius_m)
        if course_down_m is not None and math.isfinite(course_down_m) and abs(pos[2] - course_down_m) <= cfg.height_band_m:
            near &= np.abs(rel[:, 2] + (pos[2] - course_down_m)) <= cfg.height_band_m
        rel = rel[near]
        trusted = self.trusted(rel + pos, cfg)
        return rel[trusted, :2]

    def clear_below(self, position_ned_m: np.ndarray, now_s: float, cfg: MemoryConfig, down_to_m: float) -> bool | None:
        """Whether the way down is free of remembered points: no point seen within
        ``cfg.duration_s`` of ``now_s`` (near or far, trusted or not) lies within ``cfg.keep_out_m``
        of the vehicle horizontally and below it, above ``down_to_m + cfg.height_band_m`` (NED down,
        metres: the altitude to descend to, less the band a point at the vehicle's height lies in).

        Course hold's descent back to the engagement altitude uses it: the camera cannot see what
        is straight below, but it saw what the vehicle climbed over on the way there. Only what lies
        under the vehicle (``keep_out_m``: its radius and a margin, as :meth:`gap_below_m`) stops
        it: a wall beside it is the guard's business, and with ``hold_clear_m`` (1 m) an office's
        walls, 0.5-1 m away, kept the vehicle at the height it had climbed to, above the door.

        Returns:
            None without a finite position or ``down_to_m``; else the answer (True for an empty
            memory).
        """
        pos = np.asarray(position_ned_m, dtype=np.float64).reshape(-1)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)) or not math.isfinite(down_to_m):
            return None
        pts = self._pts[(now_s - self._t) <= cfg.duration_s]
        below = (pts[:, 2] > pos[2]) & (pts[:, 2] < down_to_m + cfg.height_band_m)
        horizontal = np.hypot(pts[:, 0] - pos[0], pts[:, 1] - pos[1])
        return not bool(np.any(below & (horizontal < cfg.keep_out_m)))

    def gap_below_m(
        self, position_ned_m: np.ndarray, now_s: float, cfg: MemoryConfig, ground_down_m: float
    ) -> float | None:
        """The height, metres, from the vehicle's centre down to the highest point below it that was
        seen within ``cfg.duration_s`` of ``now_s`` and not seen past since, lies under it (within
        ``cfg.keep_out_m`` horizontally: a wall beside the vehicle is the guard's business), no more
        than ``cfg.clearance_below_m`` below, and above ``ground_down_m`` (NED down, metres: the
        ground's own points lie below it). None when there is no such point, or no finite position."""
        pos = np.asarray(position_ned_m, dtype=np.float64).reshape(-1)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)) or self._keys.size == 0:
            return None
        keep = ((now_s - self._t) <= cfg.duration_s) & ~self._seen_past(cfg)
        pts = self._pts[keep]
        gap = pts[:, 2] - pos[2]  # > 0: below the vehicle
        near = (gap > 0.0) & (gap <= cfg.clearance_below_m) & (pts[:, 2] < ground_down_m)
        near &= np.hypot(pts[:, 0] - pos[0], pts[:, 1] - pos[1]) < cfg.keep_out_m
        return float(gap[near].min()) if np.any(near) else None

    def _nearby(
        self,
        position_ned_m: np.ndarray,
        yaw_rad: float,
        now_s: float,
        cfg: MemoryConfig,
        radius_m: float,
        trusted_only: bool = False,
        seen_now: bool = False,
        pushing: bool = True,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """The points seen within ``cfg.duration_s`` of ``now_s`` nearer than ``cfg.max_depth_m``
        (the map's farther points do not guard), within ``cfg.height_band_m`` of the vehicle's
        altitude and within ``radius_m`` of it horizontally (``trusted_only``: trusted ones only;
        ``seen_now``: not those the camera now sees past, :meth:`see_through`), in the body frame: forward, right and horizontal distance, float64 ``(N,)`` metres each, and
        whether each may push (:meth:`may_push`; ``pushing`` False: whether it is :meth:`trusted`),
        bool ``(N,)``; ``trusted_only`` keeps those; None without a finite position and heading."""
        pos = np.asarray(position_ned_m, dtype=np.float64).reshape(-1)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)) or not math.isfinite(yaw_rad):
            return None
        sel = ((now_s - self._t) <= cfg.duration_s) & (self._range <= cfg.max_depth_m)
        sel &= ~self._guard_cleared(cfg)  # seen past that long: not there
        if seen_now:
            sel &= ~self._seen_past(cfg)
        pts = self._pts[sel]
        rel = pts - pos
        fwd, right = ned_to_body_horizontal(rel[:, 0], rel[:, 1], yaw_rad)
        dist = np.hypot(fwd, right)
        keep = (np.abs(rel[:, 2]) <= cfg.height_band_m) & (dist < radius_m)
        marked = self.may_push(pts[keep], cfg) if pushing else self.trusted(pts[keep], cfg)
        fwd, right, dist = fwd[keep], right[keep], dist[keep]
        if trusted_only:
            return fwd[marked], right[marked], dist[marked], marked[marked]
        return fwd, right, dist, marked

    def hold_inputs(
        self, position_ned_m: np.ndarray, yaw_rad: float, now_s: float, cfg: MemoryConfig, view: ViewLimits | None
    ) -> HoldInputs:
        """:meth:`guard` (None without ``view``), :meth:`sides_near`, :func:`find_gap` (from points
        that may push only) and :func:`path_ahead_m` (from trusted points), from the memory: what
        :func:`~companion.core.command.setpoint_for` takes as ``guard_m``, ``remembered_sides``, ``gap``
        and ``path_ahead_m``."""
        radius = max(cfg.guard_distance_m, cfg.hold_clear_m)
        centering = cfg.gap_centering_gain_per_s > 0.0
        reach = max(radius, math.hypot(cfg.gap_lookahead_m, cfg.gap_max_width_m)) if centering else radius
        wide = self._nearby(position_ned_m, yaw_rad, now_s, cfg, reach)  # one pass for the guard and the gap
        if wide is None:
            return HoldInputs(None, None, None)
        inside = wide[2] < radius
        near = tuple(a[inside] for a in wide)
        guard = None if view is None else _guard_rows(*near, cfg, view)  # each filters by its own distance
        gap = None
        if centering:
            pushing = wide[3]  # only points that may push bound a gap
            gap = find_gap(wide[0][pushing], wide[1][pushing], cfg)
        ahead = None
        if cfg.path_slow_time_s > 0.0:
            path = self._nearby(
                position_ned_m, yaw_rad, now_s, cfg, cfg.path_range_m, trusted_only=True, seen_now=True, pushing=False
            )
            ahead = None if path is None else path_ahead_m(path[0], path[1], cfg)
        return HoldInputs(guard, _sides(*near[:3], cfg), gap, ahead)

    def sides_near(
        self, position_ned_m: np.ndarray, yaw_rad: float, now_s: float, cfg: MemoryConfig
    ) -> tuple[bool, bool] | None:
        """Whether a point seen within ``cfg.duration_s`` lies within ``cfg.hold_clear_m`` of the
        vehicle horizontally (and ``cfg.height_band_m`` vertically), not more than ``cfg.keep_out_m``
        behind it, on its left, on its right (the body's right component < 0, > 0); None without a
        finite position and heading."""
        near = self._nearby(position_ned_m, yaw_rad, now_s, cfg, cfg.hold_clear_m)
        return None if near is None else _sides(*near[:3], cfg)

    def guard(
        self,
        position_ned_m: np.ndarray,
        yaw_rad: float,
        now_s: float,
        cfg: MemoryConfig,
        view: ViewLimits,
    ) -> np.ndarray | None:
        """The points that guard the vehicle now, nearest per sector, or None for none.

        A point guards when it was seen within ``cfg.duration_s`` of ``now_s`` nearer than
        ``cfg.max_depth_m``, lies within ``cfg.height_band_m`` of the vehicle's altitude and within
        ``cfg.guard_distance_m`` of it horizontally, and the camera cannot see it now: its bearing
        from the heading lies beyond the side of ``view`` it is on, or it is nearer than
        ``view.min_range_m``.

        Returns:
            float64 ``(S, 4)``, ``S <= 2 · GUARD_SECTORS``: horizontal distance (metres), the unit
            direction to the point in the body frame (forward, right), and 1.0 where the point may push
            (:meth:`may_push`) else 0.0: per sector, the nearest point, and the nearest one that may
            push when that is another.
        """
        near = self._nearby(position_ned_m, yaw_rad, now_s, cfg, cfg.guard_distance_m)
        return None if near is None else _guard_rows(*near, cfg, view)


def find_gap(fwd: np.ndarray, right: np.ndarray, cfg: MemoryConfig) -> Gap | None:
    """The narrow gap the vehicle is in or about to enter: where its middle lies, sideways from the
    vehicle, and how wide it is, metres; None when there is no such gap (or centering is off).

    ``fwd``, ``right``: remembered points in the body frame, horizontal metres, float ``(N,)``. The
    points from ``cfg.keep_out_m`` behind to ``cfg.gap_lookahead_m`` ahead are the vehicle's sides;
    the nearest on the left (sideways) and the nearest on the right bound the gap, which counts when
    both exist and lie less than ``cfg.gap_max_width_m`` apart. A jamb is nearer sideways than the
    wall beyond it, so a doorway is bounded by its jambs."""
    if cfg.gap_centering_gain_per_s == 0.0:
        return None
    fwd = np.asarray(fwd, dtype=np.float64)
    right = np.asarray(right, dtype=np.float64)
    beside = (fwd > -cfg.keep_out_m) & (fwd < cfg.gap_lookahead_m)
    left_m = -right[beside & (right < 0.0)]
    right_m = right[beside & (right > 0.0)]
    if left_m.size == 0 or right_m.size == 0:
        return None
    lo, hi = float(left_m.min()), float(right_m.min())
    if lo + hi >= cfg.gap_max_width_m:
        return None
    return Gap(0.5 * (hi - lo), lo + hi)


def path_ahead_m(fwd: np.ndarray, right: np.ndarray, cfg: MemoryConfig) -> float | None:
    """How far the vehicle can fly straight ahead before a point comes within
    ``cfg.path_half_width_m`` of its centre, metres: over the points (body frame, horizontal
    metres, float ``(N,)``) ahead of it and less than that sideways, the least
    ``fwd - sqrt(half_width² - right²)`` (at least 0); None when none (or it is off). The half
    width is the vehicle's radius and a little: a wall alongside, farther sideways, is not in the way
    however near it is (stopping beside one would leave a drifting vehicle there). The
    centre region is a fixed angle wide, so near the vehicle what it will hit sits in a side region
    (the paper's Fig. 11); the memory's points, in the body frame, say where it is."""
    if cfg.path_slow_time_s <= 0.0:
        return None
    fwd = np.asarray(fwd, dtype=np.float64)
    right = np.asarray(right, dtype=np.float64)
    hw = cfg.path_half_width_m
    on = (fwd > 0.0) & (np.abs(right) < hw)
    if not np.any(on):
        return None
    return float(max(0.0, (fwd[on] - np.sqrt(hw * hw - right[on] ** 2)).min()))


def _sides(fwd: np.ndarray, right: np.ndarray, dist: np.ndarray, cfg: MemoryConfig) -> tuple[bool, bool]:
    """(left, right): a point within ``cfg.hold_clear_m`` on that side and not more than
    ``cfg.keep_out_m`` behind the vehicle (body-frame arrays, metres). Turning or sliding toward a
    point farther behind does not close on it; counting it would keep a vehicle flying away from the
    goal past a pillar it had passed."""
    close = (dist < cfg.hold_clear_m) & (fwd > -cfg.keep_out_m)
    return bool(np.any(close & (right < 0.0))), bool(np.any(close & (right > 0.0)))


def _guard_rows(
    fwd: np.ndarray,
    right: np.ndarray,
    dist: np.ndarray,
    trusted: np.ndarray,
    cfg: MemoryConfig,
    view: ViewLimits,
) -> np.ndarray | None:
    """:meth:`ObstacleMemory.guard`'s rows from body-frame points (forward, right, distance, metres;
    trusted, bool)."""
    bearing = np.arctan2(right, fwd)
    unseen = ~view.covers(bearing, dist)
    keep = unseen & (dist < cfg.guard_distance_m) & (dist > 1e-6)
    if not np.any(keep):
        return None
    dist, fwd, right, bearing = dist[keep], fwd[keep], right[keep], bearing[keep]
    trusted = np.asarray(trusted, dtype=bool)[keep]
    sector = np.minimum(GUARD_SECTORS - 1, ((bearing + math.pi) / (2.0 * math.pi) * GUARD_SECTORS).astype(np.int64))
    out = []
    for k in np.unique(sector):
        i = np.flatnonzero(sector == k)
        j = i[np.argmin(dist[i])]
        out.append((dist[j], fwd[j] / dist[j], right[j] / dist[j], float(trusted[j])))
        t = i[trusted[i]]
        if not trusted[j] and t.size:
            j = t[np.argmin(dist[t])]
            out.append((dist[j], fwd[j] / dist[j], right[j] / dist[j], 1.0))
    return np.asarray(out, dtype=np.float64)


def apply_guard(
    forward_m_s: float,
    right_m_s: float,
    guard_m: np.ndarray | None,
    cfg: MemoryConfig,
    velocity_body_m_s: tuple[float, float] | None = None,
    side_room_m_s: tuple[float, float] | None = None,
) -> tuple[float, float]:
    """A horizontal body-frame velocity (m/s) with the guard applied. For each guarding point
    (:meth:`ObstacleMemory.guard` rows: distance m, unit forward, unit right, and whether it may push;
    a row of 3 columns may): a push away of ``guard_gain_per_s · (guard_distance_m - distance)`` from
    a point that may push (the summed push capped at ``max_guard_speed_m_s``), and when the point lies on the path (ahead along the velocity and within
    ``keep_out_m`` of its line) the velocity's component toward it is removed, so that the vehicle
    slides past it instead of running into it; a point beside the path does not slow the vehicle.

    ``velocity_body_m_s`` (forward, right m/s: the vehicle's velocity now, None = unknown): the
    autopilot follows a setpoint only after a lag (PX4: ~0.85 s), so a vehicle still moving toward a
    point on the path it is actually flying keeps closing on it after the command has turned away.
    For such a point the command's motion toward it is removed too, and the command leans away from
    it at ``counter_velocity_fraction`` times the closing speed (less what it already moves away):
    leaning against the motion stops it in about a third of the distance a zero command would (a
    first-order lag). The lean and the push together are capped at ``max_guard_speed_m_s``: a
    vehicle shoved sideways flies into what the camera does not see either.
    With ``guard_damping_fraction`` > 0 each point's push drops by that fraction of the speed the
    vehicle already moves away from it (never below zero): the push alone, between points on
    opposite sides, is a spring that rings against the lag.

    ``side_room_m_s`` ((left, right) m/s, :func:`~companion.core.command.side_room_m_s`: how fast the
    memory may move the vehicle toward each side the camera reads near; None = no limit): neither a
    slide past a point on the path nor the push and lean take the sideways speed toward a side past
    its room (or past what the command already had, where that is more); a slide held back slows
    the motion toward the point instead.
    The memory places its points with a position estimate that wanders, the camera does not."""
    if guard_m is None or len(guard_m) == 0:
        return forward_m_s, right_m_s
    g = np.asarray(guard_m, dtype=np.float64)
    g = g.reshape(-1, g.shape[-1])
    pushes = g[:, 3] > 0.0 if g.shape[1] > 3 else np.ones(len(g), dtype=bool)
    v = np.array([forward_m_s, right_m_s], dtype=np.float64)
    speed = float(np.hypot(v[0], v[1]))
    w = None
    if velocity_body_m_s is not None and all(math.isfinite(x) for x in velocity_body_m_s):
        w = np.array(velocity_body_m_s, dtype=np.float64)
    away = np.zeros(2)  # the push and the lean, capped together
    for (dist, uf, ur), push in zip(g[:, :3], pushes):
        u = np.array([uf, ur])
        toward = float(v @ u)
        if toward > 0.0 and _on_path(dist, u, v, speed, cfg.keep_out_m):
            v = _slide_past(v, u, toward, side_room_m_s)
        if w is not None:
            closing = float(w @ u)
            if closing > 0.0 and _on_path(dist, u, w, float(np.hypot(w[0], w[1])), cfg.keep_out_m):
                toward = float(v @ u)
                if toward > 0.0:
                    v = _slide_past(v, u, toward, side_room_m_s)
                    toward = 0.0
                away -= max(0.0, cfg.counter_velocity_fraction * closing + toward) * u
        if push:
            push_m_s = cfg.guard_gain_per_s * max(0.0, cfg.guard_distance_m - dist)
            if w is not None and cfg.guard_damping_fraction > 0.0:
                # Damped: less push while the vehicle already moves away, so that it does not ring
                # between points on opposite sides against the autopilot's lag.
                push_m_s = max(0.0, push_m_s - cfg.guard_damping_fraction * max(0.0, -float(w @ u)))
            away -= push_m_s * u
    n = float(np.hypot(away[0], away[1]))
    if n > cfg.max_guard_speed_m_s > 0.0:
        away *= cfg.max_guard_speed_m_s / n
    elif cfg.max_guard_speed_m_s == 0.0:
        away[:] = 0.0
    v += away
    return float(v[0]), within_room(float(v[1]), right_m_s, side_room_m_s)


def _slide_past(v: np.ndarray, u: np.ndarray, toward: float, side_room_m_s: tuple[float, float] | None) -> np.ndarray:
    """Velocity ``v`` (body forward, right m/s) less its part ``toward`` (m/s) along unit ``u`` toward a
    point on its path: what is left slides past the point. The slide's sideways speed stays within
    the side's room (:func:`within_room`), and the forward speed drops so that nothing is left toward
    the point: taking only the forward motion off toward a remembered box ahead on the left would
    slide the vehicle right into the wall its right region reads."""
    slid = v - toward * u
    right = within_room(float(slid[1]), float(v[1]), side_room_m_s)
    if right == slid[1]:
        return slid
    slid[1] = right
    remaining = float(slid @ u)  # what is still toward the point
    if remaining > 0.0:
        if u[0] <= 1e-6:
            return np.zeros(2)
        slid[0] -= remaining / u[0]
    return slid


def within_room(right_m_s: float, before_m_s: float, side_room_m_s: tuple[float, float] | None) -> float:
    """A sideways speed (m/s, positive = right) held within the room toward each side ((left, right)
    m/s, :func:`~companion.core.command.side_room_m_s`; None = no limit), or within ``before_m_s``
    (the speed before the memory acted) where that went further that way."""
    if side_room_m_s is None:
        return right_m_s
    lo = -max(side_room_m_s[0], -before_m_s)
    hi = max(side_room_m_s[1], before_m_s)
    return min(hi, max(lo, right_m_s))


def _on_path(dist: float, u: np.ndarray, v: np.ndarray, speed: float, keep_out_m: float) -> bool:
    """Whether a point ``dist`` metres away along unit ``u`` lies within ``keep_out_m`` of the line
    of velocity ``v`` (``speed`` = its norm, > 0; the caller has checked the point is ahead of it)."""
    if speed <= 0.0:
        return False
    return dist * abs(u[0] * v[1] - u[1] * v[0]) / speed < keep_out_m
