#!/usr/bin/env python3
"""The CPU-default study: quality and speed of CPU matcher settings.

For each setting (``stereo`` config overrides, built with ``make_cpu_matcher``):

* Aloe at half size (the shared Middlebury pair, ``shared/data/aloe`` beside the checkout or a folder
  above it): bad-2 and density over the pixels with ground truth (``companion eval``'s metrics);
* the benchmark corridor: 16 rendered 672x376 frames with depth ground truth, 64 disparities: bad-2,
  density, and per region (the pipeline's robust minimum) the phantom near regions (near from the output,
  far from the truth) and the unknown ones (unknown from the output, known from the truth);
* a plain wall 3 m ahead: 672x376 pairs of a smooth texture of 2, 4 or 8 grey levels RMS plus sensor
  noise, shifted by a sub-pixel disparity: unknown and near regions of 27 per texture level;
* speed: the whole CPU pipeline (``Pipeline.process``) at 672x376/64 with ``cpu_threads`` threads.

Usage: ``python tools/cpu_stereo_study.py [--threads 2] [--frames 200] [NAME ...]`` (names select rows).
Today's figure of the CPU default is in docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from companion.bench.common import BenchSize, rendered_frames  # noqa: E402
from companion.config import CompanionConfig, apply_patch  # noqa: E402
from companion.config.core import StereoConfig  # noqa: E402
from companion.core.depth import disparity_to_depth  # noqa: E402
from companion.core.disparity import make_cpu_matcher  # noqa: E402
from companion.core.evaluation import disparity_metrics, load_middlebury, rescale  # noqa: E402
from companion.core.fuzzy.avoidance import AvoidanceController  # noqa: E402
from companion.core.geometry import StereoGeometry  # noqa: E402
from companion.backends import make_pipeline  # noqa: E402
from companion.core.regions import reduce_regions, region_layout  # noqa: E402
from companion.sim.render import Photometry, Pose, StereoRenderer, corridor_scene  # noqa: E402
from companion.core.types import REGION_NAMES  # noqa: E402

OLD = {"uniqueness_ratio_pct": 10, "disp12_max_diff_px": -1, "bm_scale_check": "off"}
NO_HALF = {"bm_scale_check": "off"}  # the rows of 2026-11-23, before StereoBM's half-size check
SETTINGS: dict[str, dict] = {
    "bm, old default": {"backend": "opencv-bm", **OLD},
    "bm disp12 1": {"backend": "opencv-bm", "uniqueness_ratio_pct": 10, "disp12_max_diff_px": 1, **NO_HALF},
    "bm disp12 1 u5 (2026-11-23 default)": {"backend": "opencv-bm", "uniqueness_ratio_pct": 5, "disp12_max_diff_px": 1,
                                            **NO_HALF},
    "bm disp12 1 u5 scale check agree (default)": {"backend": "opencv-bm", "uniqueness_ratio_pct": 5,
                                                   "disp12_max_diff_px": 1, "bm_scale_check": "agree"},
    "bm disp12 1 u5 scale check no_conflict": {"backend": "opencv-bm", "uniqueness_ratio_pct": 5,
                                               "disp12_max_diff_px": 1, "bm_scale_check": "no_conflict"},
    "bm disp12 1 u15": {"backend": "opencv-bm", "uniqueness_ratio_pct": 15, "disp12_max_diff_px": 1, **NO_HALF},
    "bm disp12 1 texture 0": {"backend": "opencv-bm", "uniqueness_ratio_pct": 10, "disp12_max_diff_px": 1,
                              "bm_texture_threshold": 0, **NO_HALF},
    "bm disp12 1 speckle off": {"backend": "opencv-bm", "uniqueness_ratio_pct": 10, "disp12_max_diff_px": 1,
                                "speckle_window_px": 0, **NO_HALF},
    "bm disp12 1 speckle 400": {"backend": "opencv-bm", "uniqueness_ratio_pct": 10, "disp12_max_diff_px": 1,
                                "speckle_window_px": 400, **NO_HALF},
    "sgbm b9": {"backend": "opencv-sgbm", **OLD},
    "sgbm b5": {"backend": "opencv-sgbm", "block_size_px": 5, **OLD},
    "sgbm b5 mirrored lr": {"backend": "opencv-sgbm", "block_size_px": 5, "sgbm_lr_check": True, **OLD},
}


def _shared(name: str) -> Path:
    for parent in ROOT.parents:
        if (parent / "shared" / "data" / name).is_dir():
            return parent / "shared" / "data" / name
    raise SystemExit(f"no shared/data/{name} beside the checkout or above it")


def _classes(ctrl: AvoidanceController, depth: np.ndarray) -> list[str]:
    res = ctrl.main_system.infer(ctrl.prepare(depth))
    out = []
    for i, name in enumerate(REGION_NAMES):
        near = float(res.memberships[ctrl.main_system.atom(name, "near")])
        out.append("unknown" if math.isnan(depth[i]) else ("near" if near >= 0.5 else "far"))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("names", nargs="*")
    args = ap.parse_args()
    cv2.setNumThreads(args.threads)
    aloe = rescale(load_middlebury(_shared("aloe")), 0.5)
    geometry = StereoGeometry.ideal(672, 376, hfov_deg=87.0, baseline_m=0.12)
    fb = geometry.focal_baseline_px_m
    renderer = StereoRenderer(geometry, corridor_scene(length_m=80.0, width_m=6.0, n_obstacles=18, seed=0), seed=0)
    rng = np.random.default_rng(0)
    noise = Photometry(noise_std=2.0)
    corridor = []
    for i in range(16):
        t = i / 16
        pose = Pose.at(2.0 + 60.0 * t, 1.2 * math.sin(7.0 * t), 1.5 + 0.3 * math.sin(3.0 * t),
                       yaw_rad=0.25 * math.sin(11.0 * t))
        r = renderer.render(pose, left=noise, right=noise, rng=rng)
        corridor.append((cv2.cvtColor(r.left_bgr, cv2.COLOR_BGR2GRAY), cv2.cvtColor(r.right_bgr, cv2.COLOR_BGR2GRAY),
                         r.depth_m))
    walls = []
    for amp in (2.0, 4.0, 8.0):
        for seed in range(3):
            wrng = np.random.default_rng([int(amp), seed])
            h, w, s = 376, 672, 4
            base = cv2.GaussianBlur(wrng.normal(0, 1, (h, (w + 40) * s)).astype(np.float32), (0, 0), 6.0)
            base = base / base.std() * amp + 128
            sh = int(round(fb / 3.0 * s))
            lw = cv2.resize(base[:, : w * s], (w, h), interpolation=cv2.INTER_AREA)
            rw = cv2.resize(base[:, sh : sh + w * s], (w, h), interpolation=cv2.INTER_AREA)
            lw = np.clip(lw + wrng.normal(0, 2, lw.shape), 0, 255).astype(np.uint8)
            rw = np.clip(rw + wrng.normal(0, 2, rw.shape), 0, 255).astype(np.uint8)
            walls.append((amp, lw, rw))
    cfg = CompanionConfig()
    layout = region_layout(geometry, cfg.regions)
    ctrl = AvoidanceController(cfg.controller)
    _, frames = rendered_frames(BenchSize(672, 376, 64), 32)
    for name, st in SETTINGS.items():
        if args.names and not any(n in name for n in args.names):
            continue
        half = make_cpu_matcher(StereoConfig(num_disparities=112, cpu_threads=args.threads, **st))
        m = disparity_metrics(half.compute(aloe.left, aloe.right), aloe.disparity, 112)
        matcher = make_cpu_matcher(StereoConfig(num_disparities=64, cpu_threads=args.threads, **st))
        bad2, dens, phantom, unknown = [], [], 0, 0
        for left, right, depth in corridor:
            gt = (np.float32(fb) / depth).astype(np.float32)
            d = matcher.compute(left, right)
            cm = disparity_metrics(d, gt, 64)
            bad2.append(cm["bad2_known"])
            dens.append(cm["density_known"])
            got = _classes(ctrl, reduce_regions(disparity_to_depth(d, fb), layout, cfg.regions).depth_m)
            truth = _classes(ctrl, reduce_regions(depth, layout, cfg.regions).depth_m)
            phantom += sum(a == "near" and b == "far" for a, b in zip(got, truth))
            unknown += sum(a == "unknown" and b != "unknown" for a, b in zip(got, truth))
        wall: dict[float, list[int]] = {}
        for amp, lw, rw in walls:
            c = _classes(ctrl, reduce_regions(disparity_to_depth(matcher.compute(lw, rw), fb), layout,
                                              cfg.regions).depth_m)
            acc = wall.setdefault(amp, [0, 0])
            acc[0] += c.count("unknown")
            acc[1] += c.count("near")
        pipe = make_pipeline(apply_patch(cfg, {"stereo": {**st, "cpu_threads": args.threads}}), 672, 376)
        times = []
        for i in range(30 + args.frames):
            t0 = time.perf_counter()
            pipe.process(frames[i % len(frames)], timestamp_s=i / 30.0)
            if i >= 30:
                times.append((time.perf_counter() - t0) * 1e3)
        print(
            f"{name:30s} Aloe/2 bad-2 {100 * m['bad2_known']:5.2f} % density {100 * m['density_known']:5.1f} % | "
            f"corridor bad-2 {100 * np.mean(bad2):5.2f} % density {100 * np.mean(dens):5.1f} %, phantom {phantom} "
            f"unknown {unknown} of {9 * len(corridor)} | wall unknown/near of 27: "
            + " ".join(f"{a:g}: {u}/{n}" for a, (u, n) in wall.items())
            + f" | pipeline {np.median(times):6.2f} ms (p99 {np.percentile(times, 99):6.2f})",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
