"""``companion bench --backend cpu-sgm``: the CPU census + SGM pipeline against the StereoBM pipeline on
the same frames, in the same run (their frames interleaved, so that a busy machine slows both alike).

Speed goals (whole pipeline, rendered ZED-like frames, 4 paths + left-right check): 672x376 with 64
disparities within 40 ms median and within 2.5x the StereoBM pipeline; 336x188 with 32 within 12 ms.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path
from typing import Any

from companion.backends import make_pipeline
from companion.bench.common import parse_sizes, rendered_frames, stats_ms, write_bench_calibration
from companion.config import CompanionConfig
from companion.report import format_table, machine_description

#: (size, disparities) -> median milliseconds of the whole pipeline the engine should meet.
GOALS_MS = {(672, 376, 64): 40.0, (336, 188, 32): 12.0}
#: The largest ratio of the CPU SGM pipeline's median to StereoBM's.
GOAL_RATIO = 2.5
#: The sizes timed when ``--sizes`` is not given.
DEFAULT_SIZES = "672x376:64,336x188:32"


def run_cpu_sgm_bench(args: argparse.Namespace, sizes: list[Any] | None = None) -> dict[str, Any]:
    """Time both pipelines per size (``args.frames`` each after ``args.warmup``); print a table and
    return the figures (median and p99 ms of each, the ratio, the goals)."""

    if sizes is None:
        sizes = parse_sizes(DEFAULT_SIZES)
    report: dict[str, Any] = {"machine": machine_description(), "sgm_paths": args.sgm_paths, "sizes": {}}
    print(f"machine: {report['machine']}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="companion-bench-") as tmp:
        for size in sizes:
            base = CompanionConfig()
            calibration = base.calibration.model_copy(
                update={
                    "ideal_hfov_deg": 87.0,
                    "file": None if args.no_rectify else write_bench_calibration(size, Path(tmp)),
                }
            )
            pipelines = {}
            for backend in ("cpu-sgm", "opencv-bm"):
                stereo = base.stereo.model_copy(
                    update={"backend": backend, "num_disparities": size.num_disparities, "sgm_paths": args.sgm_paths}
                )
                cfg = base.model_copy(update={"stereo": stereo, "calibration": calibration})
                pipelines[backend] = make_pipeline(cfg, size.width_px, size.height_px)
            _, frames = rendered_frames(size, n=min(32, args.frames + args.warmup))
            totals: dict[str, list[float]] = {name: [] for name in pipelines}
            disparity: dict[str, list[float]] = {name: [] for name in pipelines}
            for i in range(args.warmup + args.frames):
                for name, pipeline in pipelines.items():
                    timings = pipeline.process(frames[i % len(frames)], timestamp_s=i / 30.0).timings_ms
                    if i >= args.warmup:
                        totals[name].append(timings["total_ms"])
                        disparity[name].append(timings["disparity_ms"])
            figures = {name: {"total": stats_ms(totals[name]), "disparity": stats_ms(disparity[name])} for name in pipelines}
            ratio = figures["cpu-sgm"]["total"]["median_ms"] / figures["opencv-bm"]["total"]["median_ms"]
            goal = GOALS_MS.get((size.width_px, size.height_px, size.num_disparities))
            report["sizes"][size.label] = {**figures, "ratio": ratio, "goal_ms": goal, "goal_ratio": GOAL_RATIO}
            for name, f in figures.items():
                rows.append([
                    size.label, name, f"{f['disparity']['median_ms']:.2f}", f"{f['total']['median_ms']:.2f}",
                    f"{f['total']['p99_ms']:.2f}",
                    "" if name != "cpu-sgm" else f"{ratio:.2f}x (goal <= {GOAL_RATIO}x)"
                    + ("" if goal is None else f", goal <= {goal:g} ms"),
                ])
    print(format_table(rows, ["size/disp", "backend", "disparity ms", "total ms", "total p99", "cpu-sgm / opencv-bm"]))
    sys.stdout.flush()
    return report
