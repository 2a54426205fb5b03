"""Disparity image -> MAVLink OBSTACLE_DISTANCE: 72 bins of 5° in the body frame (the exact reference).

What an autopilot's collision prevention reads (PX4 ``CollisionPrevention``, ArduPilot
``AP_Proximity_MAV``): ``distances[j]`` (uint16 cm) is the nearest obstacle in the direction
``angle_offset + j·increment`` degrees, clockwise from the vehicle's nose (MAV_FRAME_BODY_FRD), PX4's
bin ``j`` covering ±``increment``/2 around it. Here ``angle_offset`` is 0 and ``increment`` 5, so bin 0
looks straight ahead, bin 1 is 5° right, bin 71 is 5° left. Values:

* ``UINT16_MAX`` (65535): unknown: outside the matched field of view, or a bin whose columns have fewer
  valid disparities than ``min_valid_fraction`` (a blank wall the camera cannot match);
* ``max_distance + 1``: nothing within ``max_distance`` (or fewer than ``min_points`` in-band points);
* else the robust minimum (the k-th nearest, k = max(1, ceil(pct/100 · n))) of the horizontal
  distances of the bin's in-band points, floored to the centimetre and at least ``min_distance``.

A pixel (u, v) with disparity d > 0 is the point X = (u - cx)·B/d, Y = (v - cy)·B/d, Z = f·B/d
(camera frame: x right, y down, z forward; the rig faces forward, level). It is *in band* when
|Y| <= h (``band_half_height_m``), i.e. ``d >= |v - cy|·B/h`` (a per-row threshold, float32); its
horizontal distance is sqrt(X² + Z²) = Z·sqrt(1 + ((u - cx)/f)²), computed as one float32 division
``(f·B·k_u) / d`` with the per-column constant ``f·B·k_u`` rounded to float32 once, so a GPU kernel doing
the same division reproduces it bit for bit. Column u belongs to the bin of its bearing
atan((u - cx)/f); the left ``num_disparities - 1`` columns (no match can be searched there) belong to
none.

Pure: NumPy only, no clock (the caller stamps the message with the frame's capture time).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.config.obstacle import ObstacleDistanceConfig
from companion.core.geometry import StereoGeometry

#: Bins of one OBSTACLE_DISTANCE message, and their width, degrees.
N_BINS = 72
INCREMENT_DEG = 5
#: MAVLink's "unknown / not used" distance.
UNKNOWN_CM = 65535
#: MAV_FRAME_BODY_FRD: the bins turn with the vehicle, 0 = its nose, clockwise.
MAV_FRAME_BODY_FRD = 12
#: MAV_DISTANCE_SENSOR_UNKNOWN (there is no stereo camera type).
SENSOR_TYPE_UNKNOWN = 4


@dataclass(frozen=True)
class ObstacleDistance:
    """One OBSTACLE_DISTANCE's content (the wire message adds ``time_usec``, the capture time).

    Attributes:
        distances_cm: uint16 ``(72,)``, bin j at ``j·5°`` clockwise from the nose, centimetres;
            65535 unknown, ``max_distance_cm + 1`` nothing near.
        min_distance_cm, max_distance_cm: what the rig measures, centimetres.
    """

    distances_cm: np.ndarray
    min_distance_cm: int
    max_distance_cm: int
    increment_deg: int = INCREMENT_DEG
    angle_offset_deg: float = 0.0
    frame: int = MAV_FRAME_BODY_FRD
    sensor_type: int = SENSOR_TYPE_UNKNOWN

    @property
    def nearest_m(self) -> float | None:
        """The nearest known obstacle, metres (None: nothing within max_distance)."""
        d = self.distances_cm[self.distances_cm <= self.max_distance_cm]
        return None if d.size == 0 else float(d.min()) / 100.0


def bin_of_bearing(bearing_deg: np.ndarray | float) -> np.ndarray:
    """The bin (0..71) whose ±2.5° covers each bearing (degrees, clockwise from the nose)."""
    b = np.floor((np.asarray(bearing_deg, dtype=np.float64) + INCREMENT_DEG / 2.0) / INCREMENT_DEG)
    return np.mod(b, N_BINS).astype(np.int64)


@dataclass(frozen=True)
class ObstacleLayout:
    """Everything per column and per row that does not change between frames (one camera model).

    Attributes:
        column_bin: int16 ``(W,)`` the bin of each column, -1 for the unmatched left columns.
        bin_columns: int ``(72, 2)`` the [start, stop) column range of each bin (columns of one bin
            are contiguous: the bearing grows with u); (0, 0) for a bin outside the view.
        row_threshold_px: float32 ``(H,)``: a disparity at least this is in band, pixels.
        column_fbk: float32 ``(W,)``: f·B·sqrt(1 + ((u-cx)/f)²), pixel·metres (horizontal distance =
            column_fbk / disparity).
        min_distance_cm, max_distance_cm: the message's limits, centimetres.
        max_distance_m: float32 limit the distances are compared with, metres.
        percentile_pct, min_points, min_valid_fraction: the config's.
    """

    column_bin: np.ndarray
    bin_columns: np.ndarray
    row_threshold_px: np.ndarray
    column_fbk: np.ndarray
    min_distance_cm: int
    max_distance_cm: int
    max_distance_m: np.float32
    percentile_pct: float
    min_points: int
    min_valid_fraction: float

    @property
    def in_view(self) -> np.ndarray:
        """bool ``(72,)``: bins with at least one matched column."""
        return self.bin_columns[:, 1] > self.bin_columns[:, 0]


def obstacle_layout(geometry: StereoGeometry, num_disparities: int, cfg: ObstacleDistanceConfig) -> ObstacleLayout:
    """The layout for a rectified rig searching ``num_disparities`` disparities."""
    w, h = geometry.width_px, geometry.height_px
    f, cx, cy, base = float(geometry.focal_px), float(geometry.cx_px), float(geometry.cy_px), float(geometry.baseline_m)
    u = np.arange(w, dtype=np.float64)
    bearing = np.degrees(np.arctan((u - cx) / f))
    column_bin = bin_of_bearing(bearing).astype(np.int16)
    first = max(0, int(num_disparities) - 1)
    column_bin[:first] = -1
    bin_columns = np.zeros((N_BINS, 2), dtype=np.int64)
    for j in range(N_BINS):
        cols = np.flatnonzero(column_bin == j)
        if cols.size:
            bin_columns[j] = (cols[0], cols[-1] + 1)
            if cols[-1] - cols[0] + 1 != cols.size:  # pragma: no cover - the bearing is monotonic in u
                raise ValueError(f"bin {j}: its columns are not contiguous")
    v = np.arange(h, dtype=np.float64)
    row_threshold = (np.abs(v - cy) * base / float(cfg.band_half_height_m)).astype(np.float32)
    fbk = (f * base * np.sqrt(1.0 + ((u - cx) / f) ** 2)).astype(np.float32)
    min_range_m = f * base / max(1, int(num_disparities) - 1)
    max_cm = int(round(cfg.max_distance_m * 100.0))
    min_cm = min(max_cm, int(math.ceil(min_range_m * 100.0)))
    return ObstacleLayout(
        column_bin=column_bin,
        bin_columns=bin_columns,
        row_threshold_px=row_threshold,
        column_fbk=fbk,
        min_distance_cm=min_cm,
        max_distance_cm=max_cm,
        max_distance_m=np.float32(cfg.max_distance_m),
        percentile_pct=float(cfg.robust_percentile_pct),
        min_points=int(cfg.min_points),
        min_valid_fraction=float(cfg.min_valid_fraction),
    )


def rank(pct: float, n: int) -> int:
    """The robust minimum's rank: k = max(1, ceil(pct·n/100)) (1 = the minimum)."""
    return max(1, math.ceil(pct * n / 100.0))


def distance_cm(distance_m: float, layout: ObstacleLayout) -> int:
    """A bin's robust minimum (metres, float32 value) -> its wire value, centimetres: beyond
    ``max_distance`` -> max + 1; else floored (never reported farther than measured) and at least
    ``min_distance``."""
    if not distance_m <= float(layout.max_distance_m):
        return layout.max_distance_cm + 1
    return min(layout.max_distance_cm, max(layout.min_distance_cm, int(math.floor(distance_m * 100.0))))


def reduce_obstacle_distance(disparity: np.ndarray, layout: ObstacleLayout) -> ObstacleDistance:
    """The OBSTACLE_DISTANCE of one disparity image (see the module doc).

    Args:
        disparity: float32 ``(H, W)`` rectified left-eye disparity, pixels; NaN (or < 0) invalid.
        layout: :func:`obstacle_layout` for this image size.

    Returns:
        :class:`ObstacleDistance` (uint16 ``(72,)`` centimetres).
    """
    disp = np.asarray(disparity, dtype=np.float32)
    h, w = layout.row_threshold_px.shape[0], layout.column_fbk.shape[0]
    if disp.shape != (h, w):
        raise ValueError(f"disparity {disp.shape} does not match the obstacle layout ({h}, {w})")
    out = np.full(N_BINS, UNKNOWN_CM, dtype=np.uint16)
    with np.errstate(invalid="ignore", divide="ignore"):
        valid_per_column = np.count_nonzero(disp >= 0, axis=0)  # NaN compares False: invalid
        in_band = disp >= layout.row_threshold_px[:, None]
        in_band &= disp > 0
        for j in range(N_BINS):
            c0, c1 = (int(x) for x in layout.bin_columns[j])
            if c1 <= c0:
                continue
            n_valid = int(valid_per_column[c0:c1].sum())
            if n_valid == 0 or n_valid < layout.min_valid_fraction * (h * (c1 - c0)):
                continue  # unknown
            mask = in_band[:, c0:c1]
            n_band = int(np.count_nonzero(mask))
            if n_band < layout.min_points:
                out[j] = layout.max_distance_cm + 1
                continue
            rows, cols = np.nonzero(mask)
            cols += c0
            # float32 / float32: one rounding, as the GPU kernel divides.
            vals = layout.column_fbk[cols] / disp[rows, cols]
            k = rank(layout.percentile_pct, n_band)
            vals.partition(k - 1)
            out[j] = distance_cm(float(vals[k - 1]), layout)
    return ObstacleDistance(out, layout.min_distance_cm, layout.max_distance_cm)
