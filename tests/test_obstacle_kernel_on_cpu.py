"""The OBSTACLE_DISTANCE kernel's exact source (kernels/obstacle.cu), run on the CPU by the host
emulation (companion.gpu.hostemu), equals companion.core.obstacle.reduce_obstacle_distance bit for bit.
The same comparison on a GPU is in tests/test_gpu.py (marker ``gpu``)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from companion.config import ObstacleDistanceConfig
from companion.core.geometry import StereoGeometry
from companion.core.obstacle import obstacle_layout, reduce_obstacle_distance

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(shutil.which("g++") is None, reason="needs g++ to compile the kernel for the CPU"),
]


def _host_view(q: np.ndarray, scale: int) -> np.ndarray:
    """The disparity as the host estimator hands it to the reference: px, NaN invalid."""
    out = q.astype(np.float32) * np.float32(1.0 / scale)
    out[q < 0] = np.nan
    return out


@pytest.mark.parametrize(
    ("w", "h", "ndisp", "scale", "cfg", "threads"),
    [
        (160, 96, 32, 16, {}, 256),  # SGM's 1/16 px
        (150, 80, 16, 1, {"min_points": 3, "robust_percentile_pct": 0.0}, 64),  # SAD's whole pixels, the raw minimum
        (128, 72, 64, 16, {"min_points": 1, "robust_percentile_pct": 10.0, "band_half_height_m": 2.0}, 96),
        (96, 60, 16, 16, {"min_valid_fraction": 0.6, "max_distance_m": 3.0}, 128),  # unknown and far bins
        (120, 64, 32, 16, {"max_distance_m": 300.0, "robust_percentile_pct": 5.0}, 64),  # coarse bins + a second pass
    ],
)
def test_kernel_source_equals_the_reference(w: int, h: int, ndisp: int, scale: int, cfg: dict, threads: int) -> None:
    from companion.gpu.hostemu import HostObstacleKernel

    g = StereoGeometry.ideal(w, h, 90.0, 0.12)
    lay = obstacle_layout(g, ndisp, ObstacleDistanceConfig(**cfg))
    kernel = HostObstacleKernel(threads)
    rng = np.random.default_rng([w, h, scale])
    for trial in range(2):
        z = rng.uniform(0.25, 25.0, (h, w))
        q = np.round(g.focal_baseline_px_m / z * scale).clip(0, 32767).astype(np.int16)
        q[rng.random(q.shape) < (0.3 if trial == 0 else 0.7)] = -1
        q[rng.random(q.shape) < 0.02] = 0
        ref = reduce_obstacle_distance(_host_view(q, scale), lay).distances_cm
        # the estimator's row slices, one slice (a block per bin), and more slices than rows (empty ones)
        for slices in (None, 1, h + 3) if trial == 0 else (None,):
            np.testing.assert_array_equal(kernel.run(q, scale, lay, slices), ref)
    blank = np.full((h, w), -1, np.int16)
    np.testing.assert_array_equal(kernel.run(blank, scale, lay), reduce_obstacle_distance(_host_view(blank, scale), lay).distances_cm)
