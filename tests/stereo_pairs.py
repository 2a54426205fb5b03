"""Synthetic stereo pairs for the matcher tests."""

from __future__ import annotations

import cv2
import numpy as np


def shifted_pair(h: int, w: int, shift: int, seed: int, noise: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """right(x) = left(x + shift) + noise, i.e. left(x) = right(x - shift): a uint8 ``(h, w)`` pair with
    disparity ``shift`` everywhere it is matchable (blurred noise, contrast stretched)."""
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.integers(0, 256, (h, w + shift)).astype(np.float32), (0, 0), 1.0)
    base = np.clip((base - base.mean()) * 3 + 128, 0, 255).astype(np.uint8)
    left = base[:, :w].copy()
    right = np.clip(base[:, shift:].astype(int) + rng.integers(-noise, noise + 1, (h, w)), 0, 255).astype(np.uint8)
    return left, right
