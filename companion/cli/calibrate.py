"""``companion calibrate stereo`` and ``companion calibrate lut``: a new rig's calibration, and the paper's
depth look-up table, measured."""

from __future__ import annotations

import argparse
import datetime
import json
import math
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from companion import exitcodes
from companion.errors import CalibrationError, InputError

_BOARD_HELP = (
    "the board: chessboard:COLSxROWS:SQUARE_M (inner corners, e.g. chessboard:9x6:0.025 for a board of 10x7 "
    "squares of 25 mm) or charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT] (squares, e.g. charuco:8x6:0.03:0.022)"
)


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``calibrate`` and its two sub-commands."""
    p = sub.add_parser(
        "calibrate",
        help="calibrate a stereo rig (stereo), import a rig's calibration (import), or measure the depth table (lut)",
        description=(
            "stereo: calibrate a stereo camera from views of a chessboard or ChArUco board and write the "
            "calibration file the service reads (calibration.file). lut: measure the depth the pipeline "
            "computes for a flat target at known distances and fit the paper's look-up table (lut.points_m)."
        ),
    )
    csub = p.add_subparsers(dest="calibrate_command", metavar="WHAT", required=True)

    s = csub.add_parser(
        "stereo",
        help="calibrate a stereo rig from views of a board; write the calibration file",
        description=(
            "Calibrate a stereo rig from 10 or more views of a board, each seen whole by both eyes, from a "
            "folder (side-by-side frames, or left/ and right/ files) or live from the configured camera. "
            "Prints the RMS reprojection error, the vertical error between the eyes after rectification, and "
            "how much of the image the board covered; refuses (exit 2, nothing written) a set with too few "
            "views, poor coverage, high error or mixed sizes, saying why."
        ),
    )
    src = s.add_mutually_exclusive_group(required=True)
    src.add_argument("--views", type=Path, metavar="DIR", help="a folder of views (side-by-side images, or left/ and right/)")
    src.add_argument("--live", action="store_true", help="capture the views from the camera of --config")
    s.add_argument("--board", required=True, help=_BOARD_HELP)
    s.add_argument("--out", type=Path, required=True, help="the calibration file to write: .yaml, .yml, .xml, .json or .npz")
    s.add_argument("--layout", choices=["auto", "sbs", "pair"], default="auto", help="how --views holds the eyes (default: auto)")
    s.add_argument("--swap-eyes", action="store_true", help="the camera (or the files) put the right eye first")
    s.add_argument("--config", type=Path, help="TOML config: the camera for --live, calibration.rectify_alpha")
    s.add_argument("--write-config", action="store_true", help="also set calibration.file = OUT in --config")
    s.add_argument("--count", type=int, default=20, help="--live: views to capture (default 20)")
    s.add_argument("--save-views", type=Path, metavar="DIR", help="--live: keep the views here (default: OUT's name + _views)")
    s.add_argument("--timeout-s", type=float, default=600.0, help="--live: give up after this long (default 600)")
    s.add_argument("--rectified", type=Path, metavar="PNG", help="also write one view rectified, with rows to check by eye")
    s.add_argument("--min-views", type=int, default=10, help="refuse fewer views (default 10)")
    s.add_argument("--min-coverage", type=float, default=0.3, help="refuse a board whose corners covered less of each image (default 0.3)")
    s.add_argument("--max-rms-px", type=float, default=1.0, help="refuse a larger RMS reprojection error (default 1.0 px)")
    s.add_argument("--max-epipolar-px", type=float, default=0.5, help="refuse a larger RMS vertical error after rectification (default 0.5 px)")
    s.add_argument("--fix-k3", action="store_true", help="keep the third radial distortion coefficient at 0")
    s.add_argument("--force", action="store_true", help="write the file even when the set is refused (not for flying)")
    s.add_argument("--json", action="store_true", help="print the report as JSON")
    s.set_defaults(func=_stereo)

    lut = csub.add_parser(
        "lut",
        help="measure the depth of a flat target at known distances; fit the paper's LUT into the config",
        description=(
            "The paper's depth refinement (section VI): captures of a flat, textured target filling the middle "
            "of the image, each at a measured distance, are run through the configured pipeline; the centre "
            "region's computed depth against the true distance gives a piecewise-linear table (monotone, "
            "clamped at its ends), written into the config's lut.points_m. Distances come from a CSV "
            "(file,true_distance_m) or are typed in."
        ),
    )
    src = lut.add_mutually_exclusive_group(required=True)
    src.add_argument("--captures", type=Path, metavar="DIR", help="a folder of captures (side-by-side, or left/ and right/)")
    src.add_argument("--live", action="store_true", help="capture from the camera of --config, asking for each distance")
    lut.add_argument("--distances", type=Path, metavar="CSV", help="file,true_distance_m for each capture (else typed in)")
    lut.add_argument("--config", type=Path, help="TOML config: the pipeline that computes the depths; the LUT is written into it")
    lut.add_argument("--dry-run", action="store_true", help="print the table, do not write it into --config")
    lut.add_argument("--plot", type=Path, metavar="PNG", help="draw computed vs true depth, and the table")
    lut.add_argument("--layout", choices=["auto", "sbs", "pair"], default="auto", help="how --captures holds the eyes")
    lut.add_argument("--swap-eyes", action="store_true", help="the camera (or the files) put the right eye first")
    lut.add_argument("--frames", type=int, default=5, help="--live: frames per distance (default 5)")
    lut.add_argument("--save-captures", type=Path, metavar="DIR", help="--live: keep the captures and distances.csv here")
    lut.add_argument("--no-extend", action="store_true", help="do not extend the table to 0.2 and 40 m by the end points' ratio")
    lut.add_argument("--json", action="store_true", help="print the result as JSON")
    lut.set_defaults(func=_lut)

    from companion.cli import calibrate_import

    calibrate_import.register(csub)


# ------------------------------------------------------------------------------------------------ helpers


def _camera_from_config(config: Path | None) -> Any:
    from companion.config import load_config
    from companion.service.camera import make_camera

    if config is None:
        raise InputError("--live needs --config (its [camera] section is the camera)")
    cfg = load_config(config)
    if cfg.camera.replay_path is not None and not cfg.camera.replay_path.is_absolute():
        cfg = cfg.model_copy(
            update={"camera": cfg.camera.model_copy(update={"replay_path": config.parent / cfg.camera.replay_path})}
        )
    # Capturing the views that make the calibration must work before there is one.
    return make_camera(cfg, require_calibration=False)


def _interruptible() -> tuple[threading.Event, Callable[[], None]]:
    """An event set by Ctrl-C (the first one), and a function that restores the old handler."""
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        return stop, lambda: None
    old = signal.getsignal(signal.SIGINT)

    def handler(signum: int, frame: Any) -> None:
        stop.set()
        signal.signal(signal.SIGINT, old)  # a second Ctrl-C interrupts for real

    signal.signal(signal.SIGINT, handler)
    return stop, lambda: signal.signal(signal.SIGINT, old)


def _check_out(path: Path, suffixes: tuple[str, ...], what: str) -> Path:
    path = path.expanduser()
    if path.suffix.lower() not in suffixes:
        raise InputError(f"{path}: {what} must end in {', '.join(suffixes)}")
    if path.parent != Path("") and not path.parent.expanduser().resolve().is_dir():
        raise InputError(f"{path.parent}: no such directory")
    return path


def _today() -> str:
    return datetime.date.today().isoformat()


# ------------------------------------------------------------------------------------------------ stereo


def _stereo(args: argparse.Namespace) -> int:
    import cv2
    import numpy as np

    from companion.calib.views import capture_views, load_stereo_images, open_camera, save_view
    from companion.config import load_config
    from companion.core.calibrate import BoardSpec, Thresholds, calibrate_stereo, detect_board, pair_views
    from companion.core.calibration_files import (
        OPENCV_CALIBRATION_SUFFIXES,
        load_calibration,
        save_calibration,
    )

    board = BoardSpec.parse(args.board)
    out = _check_out(args.out, OPENCV_CALIBRATION_SUFFIXES, "--out")
    if args.write_config and args.config is None:
        raise InputError("--write-config needs --config")
    if args.min_views < 3:
        raise InputError(f"--min-views must be at least 3, got {args.min_views}")
    if not 0.0 <= args.min_coverage <= 1.0:
        raise InputError(f"--min-coverage is a share of the image, 0 to 1, got {args.min_coverage}")
    thresholds = Thresholds(args.min_views, args.min_coverage, args.max_rms_px, args.max_epipolar_px)
    cfg = load_config(args.config)
    say = (lambda *a: print(*a, file=sys.stderr)) if args.json else print

    if args.live:
        if args.count < args.min_views:
            raise InputError(f"--count ({args.count}) must be at least --min-views ({args.min_views})")
        camera = _camera_from_config(args.config)
        save_dir = args.save_views or out.with_name(out.stem + "_views")
        open_camera(camera)
        stop, restore = _interruptible()
        timer = threading.Timer(args.timeout_s, stop.set)
        timer.daemon = True
        timer.start()
        say(f"capturing {args.count} views of {board.describe()} from {camera.name} into {save_dir}; show the whole "
            "board to both eyes, at the edges and corners too, near and far, tilted; Ctrl-C to stop early")

        def kept(i: int, view: Any) -> None:
            if args.swap_eyes:
                view = type(view)(view.name, view.right, view.left)
            path = save_view(save_dir, view)
            say(f"  view {i + 1}/{args.count}: {path.name}")

        try:
            views = capture_views(camera, board, args.count, on_kept=kept, stop=stop)
        finally:
            timer.cancel()
            restore()
            camera.close()
        if args.swap_eyes:
            views = [type(v)(v.name, v.right, v.left) for v in views]
        source = f"{camera.name} (views in {save_dir})"
    else:
        views = load_stereo_images(args.views, args.layout, swap_eyes=args.swap_eyes)
        source = str(args.views)

    size = views[0].eye_size_px
    paired = []
    skipped = []
    for v in views:
        pv = pair_views(v.name, detect_board(v.left, board), detect_board(v.right, board))
        (skipped if isinstance(pv, str) else paired).append(pv)
    say(f"{len(views)} views of {size[0]}x{size[1]} eyes from {source}: the board is whole in both eyes in {len(paired)}")
    for why in skipped:
        say(f"  skipped {why}")
    report = calibrate_stereo(
        paired, size, thresholds, fix_k3=args.fix_k3, rectify_alpha=cfg.calibration.rectify_alpha, source=str(out)
    )
    c, g = report.calibration, report.geometry
    doc = {
        "views": len(report.views),
        "skipped": skipped,
        "image_size_px": list(size),
        "rms_px": round(report.rms_px, 4),
        "rms_left_px": round(report.rms_left_px, 4),
        "rms_right_px": round(report.rms_right_px, 4),
        "epipolar_rms_px": round(report.epipolar_rms_px, 4),
        "epipolar_max_px": round(report.epipolar_max_px, 4),
        "coverage_left": round(report.coverage_left, 3),
        "coverage_right": round(report.coverage_right, 3),
        "uncovered_left": list(report.uncovered_left),
        "uncovered_right": list(report.uncovered_right),
        "baseline_m": round(c.baseline_m, 5),
        "T_m": [round(float(v), 5) for v in c.T],
        "rotation_deg": round(float(np.degrees(np.linalg.norm(cv2.Rodrigues(c.R)[0]))), 4),
        "K1": np.round(c.K1, 3).tolist(),
        "D1": np.round(c.D1, 5).tolist(),
        "K2": np.round(c.K2, 3).tolist(),
        "D2": np.round(c.D2, 5).tolist(),
        "rectified_focal_px": round(g.focal_px, 3),
        "rectified_baseline_m": round(g.baseline_m, 5),
        "worst_views": [[n, round(e, 3)] for n, e in report.worst_views()],
        "problems": list(report.problems),
        "accepted": report.accepted,
    }
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        print(f"RMS reprojection error   {report.rms_px:.3f} px (left eye alone {report.rms_left_px:.3f}, right {report.rms_right_px:.3f})")
        print(f"rectified epipolar error {report.epipolar_rms_px:.3f} px RMS, {report.epipolar_max_px:.3f} px at worst (rows of the two eyes)")
        print(f"coverage                 left {report.coverage_left:.0%}, right {report.coverage_right:.0%} of the image")
        print(f"baseline                 {c.baseline_m * 1000:.2f} mm (T = {', '.join(f'{v:+.4f}' for v in c.T)} m)")
        print(f"focal length             left {c.K1[0, 0]:.2f}/{c.K1[1, 1]:.2f} px, right {c.K2[0, 0]:.2f}/{c.K2[1, 1]:.2f} px; "
              f"rectified {g.focal_px:.2f} px")
        print("worst views              " + ", ".join(f"{n} {e:.2f} px" for n, e in report.worst_views()))
    for problem in report.problems:
        print(f"refused: {problem}", file=sys.stderr)
    if report.problems and not args.force:
        raise CalibrationError(
            f"{out} not written: {len(report.problems)} problem(s) above; retake the views (or --force, not for flying)"
        )
    meta = {
        "created": _today(),
        "tool": "companion calibrate stereo",
        "board": board.describe(),
        "views": len(report.views),
        "rms_px": float(round(report.rms_px, 4)),
        "epipolar_rms_px": float(round(report.epipolar_rms_px, 4)),
        "coverage_left": float(round(report.coverage_left, 3)),
        "coverage_right": float(round(report.coverage_right, 3)),
        "accepted": "yes" if report.accepted else "no (written with --force)",
    }
    save_calibration(c, out, meta)
    load_calibration(out, size)  # what the service will do: it must read back
    say(f"wrote {out}" + ("" if report.accepted else " (REFUSED set, written with --force: do not fly with it)"))
    if args.rectified is not None:
        _write_rectified(args.rectified, report, views, paired, cfg.calibration.rectify_alpha)
        say(f"wrote {args.rectified} (a rectified view: the same feature must lie on the same row in both eyes)")
    if args.write_config:
        from companion.config.edit import set_config_value_in_file

        set_config_value_in_file(args.config, "calibration", "file", str(out.resolve()))
        say(f"set calibration.file = {out.resolve()} in {args.config}")
    return exitcodes.OK


def _write_rectified(path: Path, report: Any, views: list[Any], paired: list[Any], alpha: float) -> None:
    """The best view, rectified side by side, with a row every 24 px and the board's corners marked."""
    import cv2
    import numpy as np

    from companion.core.rectifier import Rectifier

    _check_out(path, (".png", ".jpg", ".jpeg", ".bmp"), "--rectified")
    rect = Rectifier(report.calibration, alpha=alpha)
    best = int(np.argmin(report.view_rms_px.max(axis=1)))
    name = report.views[best]
    view = next(v for v in views if v.name == name)
    left, right = rect.rectify(view.left, view.right)
    image = np.concatenate([left, right], axis=1)
    h, w2 = image.shape[:2]
    for y in range(12, h, 24):
        cv2.line(image, (0, y), (w2 - 1, y), (0, 200, 255), 1)
    cv2.putText(image, f"{name} rectified: a feature lies on the same row in both eyes", (8, h - 10),
                cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 255, 0), 1, cv2.LINE_AA)
    if not cv2.imwrite(str(path), image):
        raise InputError(f"{path}: cannot write the image")


# ------------------------------------------------------------------------------------------------ lut


def ask_distance(prompt: str, read: Callable[[str], str] | None = None) -> float | None:
    """Ask for a distance in metres until one is given; an empty answer (or the end of the input) is None."""
    read = read or input
    while True:
        try:
            text = read(prompt).strip()
        except EOFError:
            return None
        if not text:
            return None
        try:
            metres = float(text.lower().removesuffix("m").strip())
        except ValueError:
            print(f"  {text!r} is not a number of metres; again (empty to stop)")
            continue
        if math.isfinite(metres) and metres > 0:
            return metres
        print("  a distance is a positive number of metres; again (empty to stop)")


def _live_captures(args: argparse.Namespace) -> tuple[list[Any], list[float]]:
    import csv

    from companion.calib.views import StereoImage, open_camera, save_view
    from companion.core.stereo import to_bgr

    if args.frames < 1:
        raise InputError(f"--frames must be >= 1, got {args.frames}")
    camera = _camera_from_config(args.config)
    save_dir = args.save_captures or (args.config.parent / "lut_captures")
    open_camera(camera)
    views: list[StereoImage] = []
    distances: list[float] = []
    print(f"measuring the LUT with {camera.name}: put the flat target square to the camera, filling the middle of "
          f"the image; type its distance (camera to target, metres); {args.frames} frames are taken at each; an empty "
          f"answer ends. Captures go to {save_dir}.")
    try:
        k = 0
        while True:
            metres = ask_distance(f"distance #{k + 1} in metres (empty to finish): ")
            if metres is None:
                break
            for j in range(args.frames):
                frame = to_bgr(camera.read().image)  # saved views are for people too: BGR
                half = frame.shape[1] // 2
                left, right = frame[:, :half].copy(), frame[:, half:].copy()
                if args.swap_eyes:
                    left, right = right, left
                view = StereoImage(f"d{k:02d}_{metres:g}m_{j:02d}.png", left, right)
                save_view(save_dir, view)
                views.append(view)
                distances.append(metres)
            print(f"  {args.frames} frames at {metres:g} m")
            k += 1
    finally:
        camera.close()
    if views:
        with (save_dir / "distances.csv").open("w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(["file", "true_distance_m"])
            for v, d in zip(views, distances):
                w.writerow([v.name, f"{d:g}"])
    return views, distances


def _lut(args: argparse.Namespace) -> int:
    import cv2
    import numpy as np

    from companion.calib.lut import captures_to_frames, distances_for, measure_centre, plot_lut, read_distances_csv
    from companion.calib.views import load_stereo_images
    from companion.config import load_config
    from companion.core.lut import DepthLUT, fit_lut

    if args.plot is not None:
        _check_out(args.plot, (".png", ".jpg", ".jpeg", ".bmp"), "--plot")
    cfg = load_config(args.config)
    if args.live:
        views, distances = _live_captures(args)
        source = "live"
    else:
        views = load_stereo_images(args.captures, args.layout, swap_eyes=args.swap_eyes)
        source = str(args.captures)
        if args.distances is not None:
            distances = distances_for(views, read_distances_csv(args.distances), str(args.distances))
        else:
            distances = []
            print(f"{len(views)} captures in {source}: type each one's true distance (camera to target, metres)")
            for v in views:
                metres = ask_distance(f"  {v.name}: ")
                if metres is None:
                    raise InputError(f"no distance for {v.name}: every capture needs one (or give --distances)")
                distances.append(metres)
    if not views:
        raise InputError("no captures")
    measurements = measure_centre(captures_to_frames(views, distances), cfg)
    problems = [p for p in (m.problem() for m in measurements) if p]
    for p in problems:
        print(f"refused: {p}", file=sys.stderr)
    if problems:
        raise CalibrationError(f"{len(problems)} capture(s) cannot be used (above); retake them")
    try:
        table = fit_lut([m.computed_m for m in measurements], [m.true_m for m in measurements],
                        extend_to_m=None if args.no_extend else (0.2, 40.0))
    except ValueError as err:
        raise CalibrationError(f"cannot fit a LUT: {err}") from None
    lut = DepthLUT(table)
    rows = []
    for d in sorted({m.true_m for m in measurements}):
        comp = float(np.median([m.computed_m for m in measurements if m.true_m == d]))
        corr = float(lut.apply(np.array([comp]))[0])
        rows.append({"true_m": d, "computed_m": round(comp, 4), "corrected_m": round(corr, 4),
                     "error_before_pct": round(100 * (comp - d) / d, 2), "error_after_pct": round(100 * (corr - d) / d, 2)})
    before = max(abs(r["error_before_pct"]) for r in rows)
    after = max(abs(r["error_after_pct"]) for r in rows)
    written = None
    if args.config is not None and not args.dry_run:
        from companion.config.edit import set_config_value_in_file

        set_config_value_in_file(args.config, "lut", "points_m", [list(p) for p in table])
        written = str(args.config)
    if args.plot is not None:
        if not cv2.imwrite(str(args.plot), plot_lut(measurements, table)):
            raise InputError(f"{args.plot}: cannot write the plot")
    if args.json:
        print(json.dumps({"captures": len(measurements), "distances": rows, "points_m": [list(p) for p in table],
                          "max_error_before_pct": before, "max_error_after_pct": after, "written_to": written,
                          "plot": str(args.plot) if args.plot else None}, indent=2))
        return exitcodes.OK
    print(f"{len(measurements)} captures at {len(rows)} distances ({source}); the centre region's depth:")
    print("   true m   computed m   error   corrected m   error")
    for r in rows:
        print(f"  {r['true_m']:7.3f}   {r['computed_m']:10.3f}  {r['error_before_pct']:+6.1f} %  "
              f"{r['corrected_m']:11.3f}  {r['error_after_pct']:+6.1f} %")
    print(f"largest error: {before:.1f} % before the LUT, {after:.1f} % after")
    print("points_m = " + json.dumps([list(p) for p in table]))
    if written:
        print(f"wrote lut.points_m into {written}")
    elif args.config is None:
        print("not written anywhere (no --config)")
    else:
        print(f"not written (--dry-run); {args.config} unchanged")
    if args.plot is not None:
        print(f"wrote {args.plot}")
    return exitcodes.OK
