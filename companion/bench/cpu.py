"""``companion bench`` (CPU backends): per-stage median and p99 timings of the pipeline on rendered
frames, the fuzzy controller and the renderer."""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path
from typing import Any

from companion.backends import make_pipeline
from companion.bench.common import progress, rendered_frames, stats_ms, write_bench_calibration
from companion.bench.fuzzy import bench_fuzzy
from companion.bench.render import bench_render
from companion.config import CompanionConfig
from companion.report import format_table, machine_description


def run_cpu_bench(args: argparse.Namespace, sizes: list[Any]) -> dict[str, Any]:
    """Time the CPU pipeline per stage at each size; print a table; return the figures."""
    with tempfile.TemporaryDirectory(prefix="companion-bench-") as tmp:
        return _run_cpu_bench(args, sizes, Path(tmp))


def _run_cpu_bench(args: argparse.Namespace, sizes: list[Any], tmp: Path) -> dict[str, Any]:
    report: dict[str, Any] = {
        "machine": machine_description(),
        "backend": args.backend,
        "rectify": not args.no_rectify,
        "sizes": {},
    }
    print(f"machine: {report['machine']}")
    rows = []
    for size in sizes:
        calibration: dict[str, Any] = {"ideal_hfov_deg": 87.0}
        if not args.no_rectify:
            calibration["file"] = str(write_bench_calibration(size, tmp))
        stereo = {
            "backend": args.backend,
            "num_disparities": size.num_disparities,
            "matcher": args.matcher,
            "sgm_paths": args.sgm_paths,
        }
        # Validated, so that the backend-dependent settings are resolved for this backend.
        cfg = CompanionConfig.model_validate({"stereo": stereo, "calibration": calibration})
        progress(f"{size.label}: rendering the frames")
        _, frames = rendered_frames(size, n=min(32, args.frames + args.warmup))
        progress(f"{size.label}: timing {args.warmup} + {args.frames} frames")
        pipeline = make_pipeline(cfg, size.width_px, size.height_px)
        per_stage: dict[str, list[float]] = {}
        for i in range(args.warmup + args.frames):
            result = pipeline.process(frames[i % len(frames)], timestamp_s=i / 30.0)
            if i >= args.warmup:
                for stage, ms in result.timings_ms.items():
                    per_stage.setdefault(stage, []).append(ms)
        stats = {stage: stats_ms(v) for stage, v in per_stage.items()}
        report["sizes"][size.label] = stats
        for stage, s in stats.items():
            rows.append([size.label, stage.removesuffix("_ms"), f"{s['median_ms']:.3f}", f"{s['p99_ms']:.3f}"])
    progress("the fuzzy controller: 5000 decisions")
    fuzzy = bench_fuzzy(5000)
    report["fuzzy_us"] = fuzzy
    progress("the renderer: 200 stereo pairs")
    render = bench_render(200)
    report["render_672x376_ms"] = render
    print(format_table(rows, ["size/disp", "stage", "median ms", "p99 ms"]))
    print(
        f"fuzzy: one inference {fuzzy['infer_median_us']:.1f} us median ({fuzzy['infer_p99_us']:.1f} p99); "
        f"whole decision {fuzzy['decide_median_us']:.1f} us ({fuzzy['decide_p99_us']:.1f} p99)"
    )
    print(
        f"render 672x376 stereo pair + depth: {render['median_ms']:.2f} ms median ({render['p99_ms']:.2f} p99)"
    )
    sys.stdout.flush()
    return report
