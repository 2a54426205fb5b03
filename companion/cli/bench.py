"""``companion bench``: the arguments, and which benchmark of :mod:`companion.bench` runs."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from companion.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench",
        help="time the pipeline per stage (median, p99) on rendered frames",
        description=(
            "Time the pipeline per stage on rendered ZED-like frames at 672x376 (64 disparities) and "
            "1280x720 (128 disparities), plus the fuzzy controller and the renderer. With --backend cupy, "
            "the GPU path (--matcher sgm or sad) and OpenCV StereoBM and StereoSGBM on all host cores run "
            "on the same frames, with the ratios. "
            "With --e2e, frame-to-setpoint latency of the service over a replayed 60 fps stream."
        ),
    )
    p.add_argument(
        "--backend",
        default="opencv-bm",
        choices=["opencv-bm", "opencv-sgbm", "reference", "cupy", "cpu-sgm"],
        help="disparity backend to time (default opencv-bm)",
    )
    p.add_argument(
        "--matcher",
        default="sgm",
        choices=["sgm", "sad"],
        help="with --backend cupy or reference: the matcher to time (default sgm)",
    )
    p.add_argument("--sgm-paths", type=int, default=4, choices=[4, 8], help="with --matcher sgm: paths (default 4)")
    p.add_argument("--frames", type=int, default=200, help="timed frames per size (default 200)")
    p.add_argument("--warmup", type=int, default=10, help="untimed frames first (default 10)")
    p.add_argument("--sizes", default=None, help="e.g. 672x376:64,1280x720:128 (the default)")
    p.add_argument("--e2e", action="store_true", help="frame-to-setpoint latency of the service instead")
    p.add_argument(
        "--soak",
        action="store_true",
        help=(
            "run the service engaged for --duration-s with operator traffic; a row of memory, setpoint rate, "
            "latency and dropped frames every --sample-s"
        ),
    )
    p.add_argument(
        "--flood",
        action="store_true",
        help="with --soak: another process floods the control socket the whole time (what a flood costs the flight path)",
    )
    p.add_argument("--duration-s", type=float, default=3600.0, help="--soak: how long, seconds (default 3600)")
    p.add_argument("--sample-s", type=float, default=60.0, help="--soak: seconds between rows (default 60)")
    p.add_argument(
        "--viewer", nargs="?", const="on", default="off", choices=["on", "alternate"],
        help=(
            "with --e2e: a preview subscriber watches the run (what `companion view` costs the flight loop); "
            "--viewer alternate: it subscribes in every other 2 s window, and the latencies of both kinds of "
            "window are compared (the same machine state for both)"
        ),
    )
    p.add_argument(
        "--stream-fps", type=float, default=60.0, metavar="HZ",
        help="with --e2e: the replayed stream's frame rate (default 60; the ZED offers 15, 30, 60 and 100 at 672x376)",
    )
    p.add_argument(
        "--no-rectify",
        action="store_true",
        help="skip the rectification remap (default: time it with a ZED-like calibration, as a real camera needs)",
    )
    p.add_argument("--json", type=Path, metavar="OUT", help="also write the figures as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from companion.bench.common import DEFAULT_SIZES, parse_sizes

    if args.frames < 1 or args.warmup < 0:
        raise InputError("--frames must be >= 1 and --warmup >= 0")
    if not 1.0 <= args.stream_fps <= 240.0:
        raise InputError(f"--stream-fps must be within 1..240 Hz, got {args.stream_fps:g}")
    try:
        sizes = parse_sizes(args.sizes) if args.sizes else list(DEFAULT_SIZES)
    except ValueError as err:
        raise InputError(str(err)) from None
    if args.flood and not args.soak:
        raise InputError("--flood goes with --soak")
    if args.soak:
        if args.duration_s <= 0 or args.sample_s <= 0:
            raise InputError("--duration-s and --sample-s must be > 0")
        from companion.bench.soak import run_soak

        report = run_soak(args, sizes[:1] if args.sizes else [s for s in sizes if s.width_px == 672] or sizes)
    elif args.e2e:
        from companion.bench.e2e import run_e2e_bench

        report = run_e2e_bench(args, sizes)
    elif args.backend == "cpu-sgm":
        from companion.bench.cpu_sgm import run_cpu_sgm_bench

        report = run_cpu_sgm_bench(args, sizes if args.sizes else None)
    elif args.backend == "cupy":
        from companion.bench.gpu import run_gpu_bench

        report = run_gpu_bench(args, sizes)
    else:
        from companion.bench.cpu import run_cpu_bench

        report = run_cpu_bench(args, sizes)
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    return 0
