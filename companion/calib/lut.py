"""The paper's depth look-up table, measured (``companion calibrate lut``).

Section VI of the paper refines the computed depth with a table measured on the rig: a flat target is
placed at known distances, the depth the pipeline computes for it is noted, and the table maps one to
the other. Here: each capture is run through the configured estimator (the same rectification,
matcher and robust minimum the service uses, before the LUT), the centre region's depth is taken as
the computed depth, and :func:`~companion.core.lut.fit_lut` fits the table.

Captures come from a folder (:mod:`companion.calib.views` layouts) with their true distances typed
in or read from a CSV (``file,true_distance_m``), or are taken live from the configured camera.
"""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.backends import make_estimator
from companion.calib.views import StereoImage
from companion.config import CompanionConfig
from companion.core.lut import DepthLUT
from companion.core.types import REGION_INDEX
from companion.errors import CalibrationError, InputError

log = logging.getLogger(__name__)

#: The centre must see the target only: a spread of depths (10th to 90th percentile) over this share
#: of their median means it sees more (the floor, what is behind the target).
MAX_SPREAD = 0.15


@dataclass(frozen=True)
class CentreMeasurement:
    """What the pipeline computed for one capture of the target.

    Attributes:
        name: the capture.
        true_m: the measured distance to the target, metres.
        computed_m: the centre region's depth as the pipeline computes it before the LUT (its robust
            minimum), metres; NaN when the region is unknown.
        median_m: the median depth over the centre region, metres (NaN: none valid).
        valid_fraction: share of the centre region with a depth, [0, 1].
        spread: (90th - 10th percentile) / median of the centre's depths (0: one flat surface).
    """

    name: str
    true_m: float
    computed_m: float
    median_m: float
    valid_fraction: float
    spread: float

    def problem(self) -> str | None:
        """Why this capture cannot be used (or None)."""
        if math.isnan(self.computed_m):
            return (
                f"{self.name}: the centre region has too few depths ({self.valid_fraction:.0%} valid): is the target "
                "textured, lit, and filling the middle of the image?"
            )
        if self.spread > MAX_SPREAD:
            return (
                f"{self.name}: the centre region sees depths from a wide range ({self.spread:.0%} of their median, "
                f"at most {MAX_SPREAD:.0%}): the target must fill the centre of the image, square to the camera"
            )
        return None


def measure_centre(captures: Sequence[tuple[str, np.ndarray, float]], cfg: CompanionConfig) -> list[CentreMeasurement]:
    """Run each capture through the configured estimator and measure its centre region.

    Args:
        captures: ``(name, side-by-side frame uint8 (H, 2W, 3), true distance m)``; one size.
        cfg: the config whose calibration, stereo and regions sections the service uses.

    Raises:
        CalibrationError: captures of different sizes (or the config's calibration does not fit them).
    """
    if not captures:
        return []
    h, w2 = captures[0][1].shape[:2]
    width = w2 // 2
    for name, frame, _ in captures:
        if frame.shape[:2] != (h, w2):
            raise CalibrationError(f"mixed sizes: {name} is {frame.shape[1]}x{frame.shape[0]}, the first capture {w2}x{h}")
    estimator = make_estimator(cfg, width, h)
    centre = REGION_INDEX["center"]
    rows, cols = estimator.layout.region_slices(centre)
    fb = estimator.geometry.focal_baseline_px_m
    out = []
    for name, frame, true_m in captures:
        est = estimator.estimate(frame, want_disparity=True)
        computed = float(est.regions.depth_m[centre])
        valid = float(est.regions.valid_fraction[centre])
        median = spread = float("nan")
        disp = est.disparity
        if disp is not None and disp.shape == (h, width):
            d = disp[rows, cols]
            d = d[np.isfinite(d) & (d > 0)]
            if d.size:
                depth = fb / d
                median = float(np.median(depth))
                p10, p90 = np.percentile(depth, [10, 90])
                spread = float((p90 - p10) / median)
        out.append(CentreMeasurement(name, float(true_m), computed, median, valid, 0.0 if math.isnan(spread) else spread))
    return out


def read_distances_csv(path: Path) -> dict[str, float]:
    """``file,true_distance_m`` rows (a header row is allowed; ``#`` starts a comment) → file name ->
    metres.

    Raises:
        InputError: unreadable file, a row without two columns, a distance that is not a positive
            number of metres (the message names the row).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as err:
        raise InputError(f"{path}: cannot read the distances: {err.strerror or err}") from None
    out: dict[str, float] = {}
    for lineno, row in enumerate(csv.reader(text.splitlines()), start=1):
        if not row or not "".join(row).strip() or row[0].strip().startswith("#"):
            continue
        if len(row) < 2:
            raise InputError(f"{path}:{lineno}: expected 'file,true_distance_m', got {','.join(row)!r}")
        name, value = row[0].strip(), row[1].strip()
        try:
            metres = float(value)
        except ValueError:
            if not out and lineno == 1:
                continue  # a header
            raise InputError(f"{path}:{lineno}: distance {value!r} is not a number (metres)") from None
        if not (math.isfinite(metres) and metres > 0):
            raise InputError(f"{path}:{lineno}: distance {value!r} must be a positive number of metres")
        out[name] = metres
    if not out:
        raise InputError(f"{path}: no distances (rows of 'file,true_distance_m')")
    return out


def distances_for(views: Sequence[StereoImage], distances: Mapping[str, float], source: str) -> list[float]:
    """Each view's true distance from ``distances`` (by file name, or its stem).

    Raises:
        InputError: a view without a distance (named), or a distance for no view.
    """
    out = []
    used = set()
    for v in views:
        key = v.name if v.name in distances else Path(v.name).stem if Path(v.name).stem in distances else None
        if key is None:
            raise InputError(f"{source}: no true distance for {v.name}")
        used.add(key)
        out.append(distances[key])
    extra = sorted(set(distances) - used)
    if extra:
        raise InputError(f"{source}: distances for files that are not captures: {', '.join(extra[:5])}")
    return out


# --------------------------------------------------------------------------------------------------
# The plot (OpenCV only: the base install has no matplotlib)


def plot_lut(
    measurements: Sequence[CentreMeasurement], table: Sequence[tuple[float, float]], size_px: tuple[int, int] = (760, 560)
) -> np.ndarray:
    """Computed vs true depth: the captures (red), the fitted table (blue line), the captures
    corrected by it (green), and the identity (grey). BGR uint8 ``(H, W, 3)``."""
    import cv2

    w, h = size_px
    img = np.full((h, w, 3), 255, np.uint8)
    ok = [m for m in measurements if not math.isnan(m.computed_m)]
    lut = DepthLUT(table)
    hi = max([m.true_m for m in ok] + [m.computed_m for m in ok] + [1.0]) * 1.15
    left, right, top, bottom = 70, 20, 40, 60
    sx = (w - left - right) / hi
    sy = (h - top - bottom) / hi

    def px(x: float, y: float) -> tuple[int, int]:
        return int(round(left + x * sx)), int(round(h - bottom - y * sy))

    font = cv2.FONT_HERSHEY_SIMPLEX
    step = 0.5 if hi <= 4 else 1.0 if hi <= 10 else 2.0 if hi <= 20 else 5.0
    v = 0.0
    while v <= hi + 1e-9:
        cv2.line(img, px(v, 0), px(v, hi), (230, 230, 230), 1)
        cv2.line(img, px(0, v), px(hi, v), (230, 230, 230), 1)
        cv2.putText(img, f"{v:g}", (px(v, 0)[0] - 8, h - bottom + 18), font, 0.45, (60, 60, 60), 1, cv2.LINE_AA)
        cv2.putText(img, f"{v:g}", (left - 40, px(0, v)[1] + 5), font, 0.45, (60, 60, 60), 1, cv2.LINE_AA)
        v += step
    cv2.rectangle(img, px(0, hi), px(hi, 0), (120, 120, 120), 1)
    cv2.putText(img, "true distance (m)", (left + (w - left - right) // 2 - 70, h - 18), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "depth (m)", (8, top - 12), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.line(img, px(0, 0), px(hi, hi), (170, 170, 170), 1, cv2.LINE_AA)
    # The table as true -> computed (its inverse), drawn over the captures' range.
    xs = np.linspace(0.0, hi, 200)
    comp = np.interp(xs, lut.true_m, lut.computed_m)
    pts = np.array([px(x, y) for x, y in zip(xs, comp)], np.int32)
    cv2.polylines(img, [pts], False, (200, 120, 40), 2, cv2.LINE_AA)
    for m in ok:
        cv2.circle(img, px(m.true_m, m.computed_m), 5, (40, 40, 220), -1, cv2.LINE_AA)
        cv2.circle(img, px(m.true_m, float(lut.apply(np.array([m.computed_m]))[0])), 5, (60, 170, 60), 2, cv2.LINE_AA)
    legend = [((170, 170, 170), "true = computed"), ((40, 40, 220), "computed (centre region)"),
              ((200, 120, 40), "the LUT (computed for a true depth)"), ((60, 170, 60), "computed, corrected by the LUT")]
    for i, (colour, text) in enumerate(legend):
        y = top + 8 + 20 * i
        cv2.rectangle(img, (left + 12, y - 10), (left + 24, y), colour, -1)
        cv2.putText(img, text, (left + 30, y), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "companion calibrate lut", (w - 230, top - 12), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def captures_to_frames(views: Sequence[StereoImage], distances: Sequence[float]) -> list[tuple[str, np.ndarray, float]]:
    """``(name, side-by-side frame, true distance)`` for :func:`measure_centre`."""
    return [(v.name, v.side_by_side(), float(d)) for v, d in zip(views, distances)]
