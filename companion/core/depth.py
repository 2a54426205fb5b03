"""Disparity -> depth along the optical axis: ``z = f·B / d`` (paper eq. 2)."""

from __future__ import annotations

import math

import numpy as np


def disparity_to_depth(
    disparity: np.ndarray, focal_baseline_px_m: float, out: np.ndarray | None = None
) -> np.ndarray:
    """Depth image from a disparity image.

    Per pixel: ``z = f·B / d`` computed in float32; NaN stays NaN (invalid); ``d == 0`` (either sign
    of zero) gives ``+inf`` (a valid match farther than the rig resolves); ``d < 0`` gives NaN (not
    a physical match).

    Args:
        disparity: float32 ``(H, W)`` (any float array works), pixels, NaN = invalid.
        focal_baseline_px_m: ``f·B``, pixel·metres (> 0), e.g. ``StereoGeometry.focal_baseline_px_m``.
        out: optional float32 array of ``disparity``'s shape to write into (may be ``disparity``
            itself when that is float32).

    Returns:
        float32 depth, metres, same shape (``out`` when given).

    Raises:
        ValueError: ``focal_baseline_px_m`` not finite and positive, or a bad ``out``.
    """
    fb = float(focal_baseline_px_m)
    if not (math.isfinite(fb) and fb > 0):
        raise ValueError(f"focal_baseline_px_m must be finite and > 0, got {focal_baseline_px_m}")
    disparity = np.asarray(disparity)
    if out is None:
        out = np.empty(disparity.shape, dtype=np.float32)
    elif out.shape != disparity.shape or out.dtype != np.float32:
        raise ValueError(f"out must be float32 {disparity.shape}, got {out.dtype} {out.shape}")
    # Masks first: out may alias disparity.
    negative = disparity < 0
    zero = disparity == 0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        np.divide(np.float32(fb), disparity, out=out, casting="same_kind")
    np.copyto(out, np.float32(np.inf), where=zero)  # -0.0 would give -inf
    np.copyto(out, np.float32(np.nan), where=negative)
    return out
