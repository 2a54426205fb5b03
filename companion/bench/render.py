"""The renderer's own benchmark: both eyes and the depth along a flight down the benchmark corridor."""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from companion.core.geometry import StereoGeometry
from companion.sim.render import Pose, Scene, StereoRenderer, corridor_scene


def bench_scene() -> tuple[StereoGeometry, Scene]:
    """The benchmark setting: a ZED-like VGA rig (672x376, 87 deg HFOV, 12 cm) and a corridor with
    20 obstacles (2 walls, 18 boxes/pillars), ground and backdrop."""
    geometry = StereoGeometry.ideal(672, 376, hfov_deg=87.0, baseline_m=0.12)
    return geometry, corridor_scene(length_m=80.0, width_m=6.0, n_obstacles=18, seed=0)


def bench_render(
    n: int = 200,
    *,
    seed: int = 0,
    warmup: int = 10,
    clock: Callable[[], float] = time.perf_counter,
) -> dict[str, float | int]:
    """Time :meth:`StereoRenderer.render` (both eyes + depth) along a flight down the bench corridor.

    Returns:
        ``{"frames", "median_ms", "p99_ms", "mean_ms", "max_ms", "sbs_median_ms", "width_px",
        "height_px", "faces"}``; ``sbs_median_ms`` times :meth:`render_side_by_side` into a
        preallocated frame (no depth). Textures are generated before timing.
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    geometry, scene = bench_scene()
    renderer = StereoRenderer(geometry, scene, seed=seed)
    renderer.prepare_textures()

    def pose(i: int) -> Pose:
        t = i / max(n, 1)
        return Pose.at(1.0 + 70.0 * t, 1.5 * math.sin(7.0 * t), 1.5 + 0.5 * math.sin(3.0 * t),
                       yaw_rad=0.3 * math.sin(11.0 * t), pitch_rad=0.05 * math.sin(5.0 * t))

    for i in range(warmup):
        renderer.render(pose(i * n // max(warmup, 1)))
    times = []
    for i in range(n):
        t0 = clock()
        renderer.render(pose(i))
        times.append((clock() - t0) * 1e3)
    frame = np.empty((geometry.height_px, 2 * geometry.width_px, 3), np.uint8)
    sbs = []
    for i in range(n):
        t0 = clock()
        renderer.render_side_by_side(pose(i), out=frame)
        sbs.append((clock() - t0) * 1e3)
    arr = np.asarray(times)
    return {
        "frames": n,
        "median_ms": float(np.median(arr)),
        "p99_ms": float(np.percentile(arr, 99)),
        "mean_ms": float(arr.mean()),
        "max_ms": float(arr.max()),
        "sbs_median_ms": float(np.median(sbs)),
        "width_px": geometry.width_px,
        "height_px": geometry.height_px,
        "faces": renderer._faces.n_faces,
    }
