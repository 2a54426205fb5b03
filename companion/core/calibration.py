"""Raw stereo calibration: :class:`StereoCalibration`, one rig's two cameras in OpenCV's conventions.

The files it comes from are read and written by :mod:`companion.core.calibration_files` (OpenCV's
formats, and any calibration by extension) and :mod:`companion.core.zed_conf` (the ZED factory file);
:mod:`companion.core.rectifier` rectifies frames with it.

OpenCV convention used throughout: a point ``X_l`` in the left camera frame (x right, y down,
z forward) is ``X_r = R @ X_l + T`` in the right camera frame. For a left/right rig the right
camera sits at ``+baseline`` along x, so ``T ≈ (-baseline, 0, 0)`` and, after rectification,
``P2[0, 3] = -f·baseline < 0`` and disparity ``d = x_left - x_right = f·baseline / Z > 0``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from companion.errors import CalibrationError

__all__ = [
    "LENS_MODELS",
    "StereoCalibration",
]

#: Lens models the rectifier handles: OpenCV's pinhole (radial-tangential) and its fisheye (equidistant).
LENS_MODELS: Final[tuple[str, ...]] = ("pinhole", "fisheye")

# Distortion vector lengths OpenCV's pinhole model accepts.
_DIST_LENGTHS: Final[frozenset[int]] = frozenset({4, 5, 8, 12, 14})


def fmt_size(size: tuple[int, int]) -> str:
    """``(width, height)`` as ``WxH`` for messages."""
    return f"{size[0]}x{size[1]}"


def readonly(a: np.ndarray) -> np.ndarray:
    """``a`` itself, made read-only."""
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class StereoCalibration:
    """Raw (unrectified) stereo calibration in OpenCV's conventions.

    Attributes:
        K1, K2: camera matrices of the left and right eye, float64 ``(3, 3)``, pixels.
        D1, D2: distortion coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]]),
            float64 ``(n,)`` with n in {4, 5, 8, 12, 14}.
        R: rotation from the left to the right camera frame, float64 ``(3, 3)``.
        T: translation from the left to the right camera frame (``X_r = R X_l + T``), float64
            ``(3,)``, METRES; ``T[0] ≈ -baseline`` for a left/right rig.
        image_size: one eye's raw image size ``(width, height)``, pixels.
        source: where the calibration came from (file and section), for messages.
        model: the lens model: ``"pinhole"`` (OpenCV's radial-tangential family, D of 4 to 14
            coefficients) or ``"fisheye"`` (the equidistant model of ``cv2.fisheye``, Kalibr's
            ``equidistant``: D is ``k1 k2 k3 k4``).

    The arrays are stored as read-only float64 copies.

    Raises:
        CalibrationError: a wrong shape, a non-finite value, a non-rotation R, a zero T, a
            non-positive focal length or image size.
    """

    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    R: np.ndarray
    T: np.ndarray
    image_size: tuple[int, int]
    source: str = "<memory>"
    model: str = "pinhole"

    def __post_init__(self) -> None:
        src = self.source
        if self.model not in LENS_MODELS:
            raise CalibrationError(
                f"calibration {src}: distortion_model {self.model!r} is not one the pipeline rectifies "
                f"({', '.join(LENS_MODELS)})",
                source=src,
                key="distortion_model",
            )

        def arr(name: str, value: Any, shape: tuple[int, ...] | None) -> np.ndarray:
            try:
                a = np.array(value, dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise CalibrationError(f"calibration {src}: {name} is not numeric ({exc})", source=src, key=name) from None
            if shape is None:
                a = a.reshape(-1)
                if self.model == "fisheye" and a.size != 4:
                    raise CalibrationError(
                        f"calibration {src}: {name} has {a.size} coefficients; the fisheye model takes 4 (k1..k4)",
                        source=src,
                        key=name,
                    )
                if a.size not in _DIST_LENGTHS:
                    raise CalibrationError(
                        f"calibration {src}: {name} has {a.size} coefficients; OpenCV takes 4, 5, 8, 12 or 14",
                        source=src,
                        key=name,
                    )
            else:
                if a.size == math.prod(shape) and a.ndim <= 2:
                    a = a.reshape(shape)
                if a.shape != shape:
                    raise CalibrationError(
                        f"calibration {src}: {name} must be {shape}, got shape {a.shape}", source=src, key=name
                    )
            if not np.all(np.isfinite(a)):
                raise CalibrationError(f"calibration {src}: {name} has non-finite values", source=src, key=name)
            return readonly(a)

        for name in ("K1", "K2"):
            k = arr(name, getattr(self, name), (3, 3))
            if not (k[0, 0] > 0 and k[1, 1] > 0) or not np.allclose(k[2], (0.0, 0.0, 1.0)):
                raise CalibrationError(
                    f"calibration {src}: {name} is not a camera matrix (fx, fy > 0, last row 0 0 1): {k.tolist()}",
                    source=src,
                    key=name,
                )
            object.__setattr__(self, name, k)
        for name in ("D1", "D2"):
            object.__setattr__(self, name, arr(name, getattr(self, name), None))
        rot = arr("R", self.R, (3, 3))
        if not np.allclose(rot.T @ rot, np.eye(3), atol=1e-4) or np.linalg.det(rot) <= 0:
            raise CalibrationError(
                f"calibration {src}: R is not a rotation matrix (R^T R = I, det R = +1): {np.round(rot, 6).tolist()}",
                source=src,
                key="R",
            )
        object.__setattr__(self, "R", rot)
        t = arr("T", self.T, (3,))
        if not np.linalg.norm(t) > 0:
            raise CalibrationError(f"calibration {src}: T is zero; the two cameras cannot coincide", source=src, key="T")
        object.__setattr__(self, "T", t)
        try:
            w, h = (int(v) for v in self.image_size)
        except (TypeError, ValueError):
            raise CalibrationError(
                f"calibration {src}: image_size must be (width, height), got {self.image_size!r}", source=src, key="image_size"
            ) from None
        if w <= 0 or h <= 0:
            raise CalibrationError(f"calibration {src}: image_size must be positive, got {w}x{h}", source=src, key="image_size")
        object.__setattr__(self, "image_size", (w, h))

    @property
    def baseline_m(self) -> float:
        """Distance between the two optical centres, metres (``|T|``)."""
        return float(np.linalg.norm(self.T))
