"""``companion sim``: fly the pipeline closed-loop through one course or a suite, and score it."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

from companion import exitcodes
from companion.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``sim``."""
    p = sub.add_parser(
        "sim",
        help="fly the pipeline closed-loop through simulated obstacle courses and score it",
        description=(
            "Closed-loop simulation: a simulated ZED renders what a simulated multicopter sees, the "
            "product's pipeline decides, the local planner commands the vehicle at 20 Hz, in simulated time. "
            "One course (--course KIND --seed N) reports the outcome (goal, collision, held, timeout, "
            "out_of_bounds), the minimum clearance, the path length and the time, and can draw a plot; a "
            "suite (--suite standard) flies many seeded courses and prints a table per course kind."
        ),
    )
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument(
        "--course",
        metavar="KIND",
        help=(
            "course kind: corridor, doorway, forest, pitch, side, deadend, office, detour (the suite's), "
            "head-on (one box ahead), wall (a 30 m wall across)"
        ),
    )
    what.add_argument("--suite", metavar="NAME", help="a suite of courses: standard (72 flights) or quick (16)")
    p.add_argument(
        "--kinds",
        metavar="K1,K2",
        help="--suite: fly only these course kinds of the suite (e.g. office: its 9 standard seeds)",
    )
    p.add_argument("--seed", type=int, default=0, help="course seed, 0..2147483647 (default 0)")
    p.add_argument(
        "--start",
        metavar="N,E,ALT,YAW",
        help=(
            "--course: fly from this pose instead of the course's start: north and east (m, the course's "
            "frame), altitude (m) and heading (degrees, 0 = north, 90 = east), e.g. a moment of a SITL "
            "flight to replay (its health log's vehicle.position_ned_m and attitude); write a negative north as "
            "--start=-1,0,1.5,0"
        ),
    )
    p.add_argument("--config", type=Path, help="TOML config (default: built-in defaults)")
    p.add_argument("--plot", type=Path, metavar="OUT.png", help="--course: write a top-down plot of the flight")
    p.add_argument("--side-view", action="store_true", help="--course: add the altitude profile to the plot")
    p.add_argument(
        "--trace",
        type=Path,
        metavar="OUT.csv",
        help=(
            "--course: write the flight's trace, one CSV row per setpoint: pose, velocity, what drove the "
            "setpoint and the setpoint, the true clearance, the region depths and reason of the decision "
            "applied, and the local planner's mode and reason (docs/simulator.md)"
        ),
    )
    p.add_argument(
        "--trace-dir",
        type=Path,
        metavar="DIR",
        help="--suite: write the trace (CSV) and the plot (PNG) of every flight that fails into DIR (made if missing)",
    )
    p.add_argument("--realtime", action="store_true", help="--course: pace simulated time to the wall clock")
    add_view_options(p, "--course: ")
    p.add_argument(
        "--workers", type=int, default=2,
        help="--suite: worker processes (default 2); with --ray and no address, the CPUs of the Ray started here",
    )
    p.add_argument(
        "--ray",
        nargs="?",
        const="",
        metavar="ADDRESS",
        help=(
            "--suite: fly on Ray (pip install 'companion[cluster]'): alone, a Ray started here for the run; "
            "'auto' or ray://HOST:10001, an existing cluster (docs/cluster.md). A flight that fails is tried "
            "once more, then reported with its course"
        ),
    )
    p.add_argument(
        "--realizations",
        type=int,
        default=1,
        metavar="N",
        help=(
            "--suite: fly every course under N draws of the noise and drift (sim.realization, from the "
            "config's on) and score them together, with a line per draw; the closed loop is chaotic, "
            "so judge a change over several (default 1)"
        ),
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from companion.config import load_config

    cfg = load_config(args.config)
    from companion.sim.loop import simulated_rig_check_lines

    for line in simulated_rig_check_lines(cfg):  # the simulated rig's, not the camera's
        print(f"companion sim: {line}", file=sys.stderr)
    if args.course is not None:
        if args.trace_dir is not None:
            raise InputError("--trace-dir goes with --suite; for one course, --trace OUT.csv")
        if args.ray is not None:
            raise InputError("--ray goes with --suite")
        return _run_course(args, cfg)
    if (
        args.plot is not None
        or args.side_view
        or args.realtime
        or args.view
        or args.start is not None
        or args.trace is not None
    ):
        raise InputError("--plot, --side-view, --trace, --realtime, --view and --start go with --course, not --suite")
    if args.realizations < 1:
        raise InputError(f"--realizations must be >= 1, got {args.realizations}")
    if args.kinds is not None and not args.kinds.strip():
        raise InputError("--kinds needs at least one course kind")
    return _run_suite(args, cfg)


def describe_flight(result: Any) -> list[str]:
    """The lines ``companion sim`` and ``companion demo`` print for one flight."""
    timing = result.timing
    speedup = result.time_s / timing.wall_s if timing and timing.wall_s > 0 else float("nan")
    d = result.decisions
    return [
        f"course:        {result.course.name} ({result.course.description})",
        f"outcome:       {result.outcome.value} ({'success' if result.success else 'FAIL'}): {result.reason}",
        f"min clearance: {result.min_clearance_m:.2f} m (vehicle radius {result.collision_radius_m:.2f} m)",
        f"path length:   {result.path_length_m:.1f} m",
        f"time:          {result.time_s:.1f} s simulated, {timing.wall_s:.1f} s wall ({speedup:.1f}x real time)"
        if timing else f"time:          {result.time_s:.1f} s simulated",
        f"frames:        {result.frames} (clear {d.get('clear', 0)}, avoid {d.get('avoid', 0)}, brake {d.get('brake', 0)})",
    ]


def _run_course(args: argparse.Namespace, cfg: Any) -> int:
    from companion.sim.courses import make_course
    from companion.sim.loop import fly

    course = make_course(args.course, args.seed)
    if args.start is not None:
        course = course.started_at(parse_start(args.start), cfg.sim.collision_radius_m)
    plot_path = _check_plot_path(args.plot) if args.plot is not None else None
    trace_path = _check_trace_path(args.trace) if args.trace is not None else None
    bridge = None
    if args.view:
        from companion.view.simbridge import fly_with_view

        result, bridge = fly_with_view(course, cfg, host=args.view_host, port=args.view_port,
                                       title=f"companion sim: {course.name}", on_urls=print_view_urls)
    else:
        result = fly(course, cfg, realtime=args.realtime)
    for line in describe_flight(result):
        print(line)
    if plot_path is not None:
        write_plot(result, plot_path, side_view=args.side_view)
        print(f"plot:          {plot_path}")
    if trace_path is not None:
        rows = write_trace_file(result, trace_path)
        print(f"trace:         {trace_path} ({rows} rows)")
    if bridge is not None:
        finish_view(bridge, args.view_linger_s)
    return 0


def parse_start(text: str) -> Any:
    """``N,E,ALT,YAW`` (metres, metres, metres, degrees) as a :class:`~companion.core.pose.Pose`.

    Raises:
        InputError: not four finite numbers, or an altitude not above 0.
    """
    import math

    from companion.core.pose import Pose

    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise InputError(f"--start {text!r}: expected N,E,ALT,YAW: four numbers (m, m, m, degrees)")
    north, east, altitude, yaw_deg = values
    if altitude <= 0.0:
        raise InputError(f"--start {text!r}: the altitude must be above 0 m, got {altitude:g}")
    return Pose.at(north, east, altitude, math.radians(yaw_deg))


def add_view_options(p: argparse.ArgumentParser, prefix: str = "") -> None:
    """``--view`` and its options (``companion sim`` and ``companion demo``)."""
    p.add_argument(
        "--view", action="store_true",
        help=f"{prefix}watch the flight in the browser (the page `companion view` serves); flies in real time",
    )
    p.add_argument("--view-host", default="127.0.0.1", help="--view: address to serve on (default 127.0.0.1; another needs $COMPANION_VIEW_TOKEN or gets a made-up token)")
    p.add_argument("--view-port", type=int, default=8080, help="--view: TCP port (default 8080; 0 = any free one)")
    p.add_argument(
        "--view-linger-s", type=float, default=None,
        help="--view: keep the page up this long after the flight (default: until Ctrl-C)",
    )


def print_view_urls(urls: list[str]) -> None:
    for url in urls:
        print(f"view:          open {url}", flush=True)


def finish_view(bridge: Any, linger_s: float | None) -> None:
    """Keep the page up after the flight (``linger_s`` seconds, or until Ctrl-C), then stop it."""
    from companion.view.simbridge import linger

    if linger_s is None:
        print("view:          the page stays up; Ctrl-C to quit", flush=True)
    linger(bridge, linger_s)


def _check_plot_path(path: Path) -> Path:
    path = path.expanduser().resolve()
    if path.suffix.lower() not in (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"):
        raise InputError(f"{path}: the plot must be an image file (.png, .jpg, ...)")
    if not path.parent.is_dir():
        raise InputError(f"{path.parent}: no such directory for the plot")
    return path


def _check_trace_path(path: Path) -> Path:
    if not path.parent.is_dir():
        raise InputError(f"{path.parent}: no such directory for the trace")
    if path.is_dir():
        raise InputError(f"{path}: the trace is a file (OUT.csv), not a directory")
    return path


def _trace_dir(path: Path) -> Path:
    """``--trace-dir``, made if missing."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"{path}: cannot make the trace directory ({e.strerror or e})") from e
    return path


def write_trace_file(result: Any, path: Path) -> int:
    """Write ``result``'s trace (:func:`companion.sim.trace.write_trace`); an unwritable file is an
    :class:`InputError` naming it. Returns the rows written."""
    from companion.sim.trace import write_trace

    try:
        return write_trace(result, path)
    except OSError as e:
        raise InputError(f"{path}: cannot write the trace ({e.strerror or e})") from e


def write_plot(result: Any, path: Path, side_view: bool = False) -> None:
    """Draw the flight and write it to ``path`` (raises InputError if it cannot be written)."""
    import cv2

    from companion.sim.plot import plot_flight

    if not cv2.imwrite(str(path), plot_flight(result, side_view=side_view)):
        raise InputError(f"{path}: cannot write the plot")


def courses_of(args: argparse.Namespace) -> tuple[tuple[str, int], ...]:
    """The ``(kind, seed)`` courses of ``--suite`` and ``--kinds``."""
    from companion.sim.suite import select_kinds, suite_courses

    courses = suite_courses(args.suite)
    return select_kinds(courses, args.kinds) if args.kinds is not None else courses


def _run_suite(args: argparse.Namespace, cfg: Any) -> int:
    from companion.report import machine_description
    from companion.sim.suite import realization_line, run_suites, suite_table

    if args.workers < 1:
        raise InputError(f"--workers must be >= 1, got {args.workers}")
    courses = courses_of(args)
    n = args.realizations
    on_ray = None
    if args.ray is not None:
        from companion.sim.cluster import SuiteOnRay  # Ray's module only when asked for

        on_ray = SuiteOnRay(len(courses) * n, args.ray or None, args.workers)
    trace_dir = _trace_dir(args.trace_dir) if args.trace_dir is not None else None
    first = cfg.sim.realization
    draws = f", realizations {first}-{first + n - 1}" if n > 1 else ""
    where = (f"{args.workers} worker(s)" if on_ray is None
             else f"Ray at {args.ray}" if args.ray else f"a local Ray of {args.workers} CPU(s)")
    print(f"suite {args.suite}: {len(courses) * n} flights{draws} on {where}; {machine_description()}")
    t0 = time.perf_counter()

    def tag(j: int) -> str:
        return f"r{first + j} " if n > 1 else ""

    def progress(j: int, done: int, total: int, result: Any) -> None:
        note = ""
        if trace_dir is not None and not result.success:
            stem = trace_dir / f"{tag(j).strip() + '-' if n > 1 else ''}{result.course.name}"
            write_trace_file(result, stem.with_suffix(".csv"))
            write_plot(result, stem.with_suffix(".png"), side_view=True)
            note = f" (trace: {stem}.csv)"
        print(f"{tag(j)}[{done:3d}/{total}] {result.summary()}{note}", flush=True)

    def failed(j: int, done: int, total: int, failure: Any) -> None:
        print(f"{tag(j)}[{done:3d}/{total}] {failure.line()} (FAILED, tried twice)", flush=True)

    drawn = [cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"realization": r})}) for r in range(first, first + n)]
    keep = trace_dir is not None
    with on_ray if on_ray is not None else contextlib.nullcontext():
        # One set of workers for every draw, locally or on Ray.
        if on_ray is None:
            got_all = run_suites(drawn, courses, workers=args.workers, keep_logs=keep, progress=progress)
        else:
            got_all = on_ray.fly(drawn, courses, keep_logs=keep, progress=progress, failed=failed)
    results: list[Any] = []
    per_draw: list[tuple[int, list[Any]]] = []
    for j, got in enumerate(got_all):
        if trace_dir is not None:  # written: the table needs no logs
            got = [dataclasses.replace(x, log=None, frame_log=None) for x in got]
        per_draw.append((first + j, got))
        results.extend(got)
    wall = time.perf_counter() - t0
    print()
    if results:
        print(suite_table(results))
    if n > 1:
        print()
        for r, got in per_draw:
            print(realization_line(r, got))
    print(f"\nsuite wall time {wall:.0f} s ({sum(r.time_s for r in results):.0f} s simulated)")
    if on_ray is not None and on_ray.failures:
        print(f"{len(on_ray.failures)} flight(s) failed twice and are not in the table:")
        for failure in on_ray.failures:
            print(f"  {failure.line()}")
        sys.stdout.flush()
        return exitcodes.INTERNAL_ERROR
    sys.stdout.flush()
    return 0
