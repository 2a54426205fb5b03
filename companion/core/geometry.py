"""Rectified stereo geometry: what every stage after rectification needs to know about the rig."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class StereoGeometry:
    """A rectified, row-aligned stereo pair (both eyes share focal length and principal point).

    Pixel convention: pixel (u, v) = (column, row) has its centre at integer coordinates, so a point
    (X, Y, Z) in the left camera frame (x right, y down, z forward, metres) projects to
    ``u = focal_px * X / Z + cx_px`` and ``v = focal_px * Y / Z + cy_px``; the right eye sits
    ``baseline_m`` to the right, and disparity ``d = u_left - u_right = focal_px * baseline_m / Z``.

    Attributes:
        width_px, height_px: size of one rectified eye image, pixels.
        focal_px: rectified focal length, pixels.
        cx_px, cy_px: rectified principal point, pixels.
        baseline_m: distance between the optical centres, metres (> 0).
    """

    width_px: int
    height_px: int
    focal_px: float
    cx_px: float
    cy_px: float
    baseline_m: float

    def __post_init__(self) -> None:
        if self.width_px <= 0 or self.height_px <= 0:
            raise ValueError(f"image size must be positive, got {self.width_px}x{self.height_px}")
        if not (self.focal_px > 0 and self.baseline_m > 0):
            raise ValueError(f"focal ({self.focal_px} px) and baseline ({self.baseline_m} m) must be > 0")

    @classmethod
    def ideal(cls, width_px: int, height_px: int, hfov_deg: float, baseline_m: float) -> StereoGeometry:
        """An ideal rig: principal point at the image centre, focal length from the horizontal FOV."""
        focal = (width_px / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(
            width_px=width_px,
            height_px=height_px,
            focal_px=focal,
            cx_px=(width_px - 1) / 2.0,
            cy_px=(height_px - 1) / 2.0,
            baseline_m=baseline_m,
        )

    @property
    def focal_baseline_px_m(self) -> float:
        """f·B in pixel·metres: depth (m) = f·B / disparity (px)."""
        return self.focal_px * self.baseline_m
