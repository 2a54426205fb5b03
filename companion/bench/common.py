"""What every benchmark shares: the sizes, rendered frames, the benchmark calibration, statistics.

Speed goals live here and in ``docs/benchmarks.md``, never in timed tests.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from companion.core.geometry import StereoGeometry
from companion.errors import CompanionError
from companion.sim.render import Photometry, Pose, StereoRenderer, corridor_scene


def rss_bytes(pid: int | None = None) -> int:
    """The resident set size of process ``pid`` (None: this process), bytes, from Linux's /proc.

    Raises:
        CompanionError: no VmRSS line (not Linux, or no such process).
    """
    where = Path("/proc") / ("self" if pid is None else str(pid)) / "status"
    try:
        lines = where.read_text(encoding="utf-8").splitlines()
    except OSError as err:
        raise CompanionError(f"no resident size of process {pid or 'self'}: {err}") from None
    for line in lines:
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise CompanionError(f"no VmRSS in {where} (Linux only)")


@dataclass(frozen=True)
class BenchSize:
    """One benchmark setting: one eye's size and the disparity range."""

    width_px: int
    height_px: int
    num_disparities: int

    @property
    def label(self) -> str:
        return f"{self.width_px}x{self.height_px}/{self.num_disparities}"


#: The sizes the issues ask for: ZED VGA with 64 disparities, ZED HD720 with 128.
DEFAULT_SIZES = (BenchSize(672, 376, 64), BenchSize(1280, 720, 128))


def parse_sizes(text: str) -> list[BenchSize]:
    """Parse ``"672x376:64,1280x720:128"``; raises ValueError naming the bad item."""
    sizes = []
    for item in text.split(","):
        try:
            dims, disp = item.strip().split(":")
            w, h = dims.lower().split("x")
            sizes.append(BenchSize(int(w), int(h), int(disp)))
        except ValueError:
            raise ValueError(f"bad size {item!r}: expected WIDTHxHEIGHT:DISPARITIES, e.g. 672x376:64") from None
    return sizes


def stats_ms(samples: Sequence[float]) -> dict[str, float]:
    """Median, p99, mean and max of ``samples`` (milliseconds)."""
    a = np.asarray(samples, dtype=np.float64)
    return {
        "median_ms": float(np.median(a)),
        "p99_ms": float(np.percentile(a, 99)),
        "mean_ms": float(a.mean()),
        "max_ms": float(a.max()),
    }


def rendered_frames(size: BenchSize, n: int, seed: int = 0) -> tuple[StereoGeometry, list[np.ndarray]]:
    """``n`` distinct side-by-side frames (uint8 (H, 2W, 3)) flying down the benchmark corridor.

    Distinct frames so that caches do not flatter the figures. The rig is ZED-like (87° HFOV, 12 cm).
    """
    geometry = StereoGeometry.ideal(size.width_px, size.height_px, hfov_deg=87.0, baseline_m=0.12)
    scene = corridor_scene(length_m=80.0, width_m=6.0, n_obstacles=18, seed=seed)
    renderer = StereoRenderer(geometry, scene, seed=seed)
    rng = np.random.default_rng(seed)
    noise = Photometry(noise_std=2.0)
    frames = []
    for i in range(n):
        t = i / max(1, n)
        pose = Pose.at(
            2.0 + 60.0 * t,
            1.2 * math.sin(7.0 * t),
            1.5 + 0.3 * math.sin(3.0 * t),
            yaw_rad=0.25 * math.sin(11.0 * t),
        )
        frames.append(renderer.render_side_by_side(pose, left=noise, right=noise, rng=rng))
    return geometry, frames


def write_bench_calibration(size: BenchSize, directory: Path) -> Path:
    """Write a ZED-like stereo calibration for ``size`` as ``.npz`` and return its path.

    The rendered frames are already rectified; timing them with this calibration makes the benchmark
    pay for the rectification remap as a real camera does (the depths it then computes are slightly
    off, which does not matter for timing). Mild radial distortion, a 0.1° rotation between the eyes,
    a 12 cm baseline, the benchmark's 87° field of view.
    """
    geometry = StereoGeometry.ideal(size.width_px, size.height_px, hfov_deg=87.0, baseline_m=0.12)
    k = np.array(
        [[geometry.focal_px, 0.0, geometry.cx_px], [0.0, geometry.focal_px, geometry.cy_px], [0.0, 0.0, 1.0]]
    )
    rotation, _ = cv2.Rodrigues(np.radians([0.05, 0.1, -0.05]))
    path = directory / f"bench-calibration-{size.width_px}x{size.height_px}.npz"
    np.savez(
        path,
        K1=k,
        D1=np.array([-0.04, 0.01, 0.0, 0.0, 0.0]),
        K2=k,
        D2=np.array([-0.035, 0.008, 0.0, 0.0, 0.0]),
        R=rotation,
        T=np.array([-0.12, 0.0, 0.0]),
        image_size=np.array([size.width_px, size.height_px]),
    )
    return path


def progress(what: str) -> None:
    """One line on stderr before each step (a bench runs for minutes; stdout keeps the figures)."""
    print(f"companion bench: {what}...", file=sys.stderr, flush=True)
