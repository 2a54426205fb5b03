"""``companion process``: run the pipeline on one stereo frame and print the result as JSON."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from companion.errors import FrameError, InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "process",
        help="run the pipeline on one stereo frame; print region depths, yaw, pitch and the decision as JSON",
        description=(
            "Run the whole pipeline on one stereo frame (a ZED side-by-side image, or a left/right pair) "
            "and print JSON: the 9 region depths in metres (null = unknown), yaw, pitch, the decision and "
            "what it means in words, the setpoint it gives flown directly (no map: at the planner's "
            "limits), per-stage timings, and the nearest depth the rig can measure "
            "(min_measurable_depth_m). Try it on the repository's sample: "
            "--sbs samples/frame.jpg --calib samples/frame-calib.yaml."
        ),
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--sbs", type=Path, metavar="FRAME", help="side-by-side frame (left | right), e.g. a ZED capture")
    src.add_argument("--left", type=Path, metavar="L", help="left image (with --right)")
    src.add_argument(
        "--sequence", type=Path, metavar="PATH", help="a recorded flight: an ASL/EuRoC folder or a rosbag (see --out)"
    )
    p.add_argument("--right", type=Path, metavar="R", help="right image (with --left)")
    p.add_argument("--calib", type=Path, help="calibration file (ZED SN*.conf or OpenCV yaml/npz); overrides the config's")
    p.add_argument("--config", type=Path, help="TOML config (default: built-in defaults)")
    p.add_argument("--backend", help="override stereo.backend (auto, opencv-bm, opencv-sgbm, reference, cupy, cpu-sgm)")
    p.add_argument("--overlay", type=Path, metavar="OUT.png", help="also draw the regions, depths and command arrow")
    p.add_argument("--verbose", action="store_true", help="also the controller's reason and its rules' strengths")
    from companion.cli.sequence import add_sequence_arguments

    add_sequence_arguments(p)
    p.set_defaults(func=run)


def _read_image(path: Path) -> Any:
    import cv2

    if path.is_dir():
        raise InputError(f"{path}: a folder, not an image file (give one image: a PNG or JPEG)")
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{path}: not a readable image (OpenCV could not decode it)")
    if image.dtype != "uint8":
        raise InputError(f"{path}: 8-bit images only, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 4:
        image = image[:, :, :3]
    return image


def load_frame(args: argparse.Namespace) -> Any:
    """Read the side-by-side frame, or join a left/right pair into one."""
    import numpy as np

    if args.sbs is not None:
        if args.right is not None:
            raise InputError("--right goes with --left, not with --sbs")
        return _read_image(args.sbs)
    if args.right is None:
        raise InputError("--left needs --right")
    left, right = _read_image(args.left), _read_image(args.right)
    if left.shape != right.shape:
        raise FrameError(
            f"left and right differ: {args.left} is {left.shape[1]}x{left.shape[0]}"
            f"{'' if left.ndim == 2 else 'x' + str(left.shape[2])}, {args.right} is "
            f"{right.shape[1]}x{right.shape[0]}{'' if right.ndim == 2 else 'x' + str(right.shape[2])}"
        )
    return np.ascontiguousarray(np.concatenate([left, right], axis=1))


def run(args: argparse.Namespace) -> int:
    from companion.config import apply_patch, load_config
    from companion.core.direct import decision_setpoint
    from companion.core.overlay import draw_overlay
    from companion.backends import make_pipeline
    from companion.core.rig_check import check_rig, near_unmeasurable, rig_check_lines
    from companion.core.words import decision_words
    from companion.core.stereo import split_side_by_side

    cfg = load_config(args.config)
    patch: dict[str, Any] = {}
    if args.calib is not None:
        patch["calibration"] = {"file": str(args.calib)}
    if args.backend is not None:
        patch["stereo"] = {"backend": args.backend}
    if patch:
        # checked below against the rig this frame is really seen with (the file's, at the frame's size)
        cfg = apply_patch(cfg, patch)
    if args.sequence is not None:
        from companion.cli.sequence import run_sequence

        return run_sequence(args, cfg)
    frame = load_frame(args)
    left, right = split_side_by_side(frame)
    height, width = left.shape[:2]
    pipeline = make_pipeline(cfg, width, height)
    rig = check_rig(pipeline.geometry, cfg.stereo, cfg.regions, cfg.controller)
    result = pipeline.process(frame, timestamp_s=0.0, want_disparity=args.overlay is not None)
    setpoint = decision_setpoint(result.decision, cfg)
    g = pipeline.geometry
    out = {
        "backend": pipeline.estimator.name,
        "image_size_px": [width, height],
        "focal_px": round(g.focal_px, 3),
        "baseline_m": round(g.baseline_m, 5),
        "regions_m": result.refined.as_dict(),
        "raw_regions_m": result.raw.as_dict(),
        "valid_fraction": {
            k: round(float(v), 4) for k, v in zip(result.raw.as_dict(), result.raw.valid_fraction)
        },
        "decision": result.decision.kind.value,
        "words": decision_words(
            result.decision.kind, result.decision.yaw, result.decision.pitch, result.refined.depth_m,
            result.decision.speed_fraction,
        ),
        "yaw": round(result.decision.yaw, 4),
        "pitch": round(result.decision.pitch, 4),
        "setpoint": {
            "forward_m_s": round(setpoint.forward_m_s, 4),
            "right_m_s": round(setpoint.right_m_s, 4),
            "down_m_s": round(setpoint.down_m_s, 4),
            "yaw_rate_deg_s": round(setpoint.yaw_rate_deg_s, 4),
        },
        "timings_ms": {k: round(v, 3) for k, v in result.timings_ms.items()},
        "min_measurable_depth_m": round(rig.nearest_depth_m, 3),
        **(
            {"reason": result.decision.reason,
             "rules": {k: round(v, 4) for k, v in result.decision.rule_strengths.items()}}
            if args.verbose else {}
        ),
        "rig_check": {"errors": list(rig.errors), "warnings": list(rig.warnings)},
    }
    blind = near_unmeasurable(rig, cfg.controller)
    if blind:
        # What the pipeline cannot know: a surface nearer than the nearest measurable depth is out of
        # the disparity search, so it reads unknown or (a false match) far. A "far" region or a "clear"
        # decision says nothing about what is nearer than that.
        out["near_unmeasurable"] = True
        out["far_regions_unverified"] = [
            name for name, d in out["regions_m"].items() if d is not None and d >= rig.nearest_depth_m
        ]
    if args.overlay is not None:
        import cv2

        from companion.core.rectifier import make_rectifier

        # The regions are laid out on the rectified image: draw on that (the raw eye when there is
        # no calibration: the frame is then taken as rectified already).
        left_view, _ = make_rectifier(cfg.calibration, width, height).rectify(left, right)
        near, far = _near_far_m(cfg)
        image = draw_overlay(
            left_view,
            pipeline.estimator.layout,
            result.refined.depth_m,
            result.decision,
            near_m=near,
            far_m=far,
            disparity=result.disparity,
            max_disparity_px=float(cfg.stereo.num_disparities),
            legend=True,
        )
        if not cv2.imwrite(str(args.overlay), image):
            raise InputError(f"{args.overlay}: cannot write the overlay image (bad extension or directory)")
        out["overlay"] = str(args.overlay.resolve())
    if cfg.calibration.file is None:
        # Said after the work, so that bad input still gets its one line. Not an error (rendered and
        # simulated frames come from that ideal rig), but a real camera's depths are wrong by as much as
        # its rig differs from it, with nothing else to say so.
        print(
            f"companion process: warning: no calibration (--calib, or calibration.file in --config): the frame is "
            f"taken as already rectified by an ideal rig ({cfg.calibration.ideal_baseline_m:g} m baseline, "
            f"{cfg.calibration.ideal_hfov_deg:g} deg horizontal field of view); a real camera's depths are off by "
            "as much as it differs. A ZED: pass its SN<serial>.conf; another camera: `companion calibrate stereo`.",
            file=sys.stderr,
        )
    for line in rig_check_lines(rig):
        print(f"companion process: {line}", file=sys.stderr)
    if blind and result.decision.kind.value == "clear":
        print(
            f"companion process: warning: the decision is clear, but this rig measures nothing nearer than "
            f"{rig.nearest_depth_m:.2f} m: an obstacle nearer than that would not be seen (more "
            "stereo.num_disparities, or a shorter baseline)",
            file=sys.stderr,
        )
    json.dump(out, sys.stdout, indent=2)
    sys.stdout.write("\n")
    return 0


def _near_far_m(cfg: Any) -> tuple[float, float]:
    """The depths where 'near' stops being total and where 'far' becomes total, for colouring."""
    near = cfg.controller.input_terms.get("near")
    far = cfg.controller.input_terms.get("far")
    near_m = near.params_m[0] if near is not None else 0.75
    far_m = far.params_m[-1] if far is not None else 2.25
    return float(near_m), float(far_m)
