"""``companion calibrate import``: a Kalibr, ASL/EuRoC, ROS camera_info or OpenCV stereo calibration
converted into the project's calibration file, with the rig it describes."""

from __future__ import annotations

import argparse
import datetime
import json
import re
import sys
from pathlib import Path
from typing import Any

from companion.errors import InputError


def register(csub: argparse._SubParsersAction) -> None:
    """Add ``calibrate import`` to the ``calibrate`` sub-commands."""
    p = csub.add_parser(
        "import",
        help="convert a Kalibr camchain, ASL/EuRoC sensor.yaml pair, ROS camera_info pair or OpenCV stereo file",
        description=(
            "Read the calibration a rig already has and write the project's calibration file (calibration.file). "
            "The kind is told from the file's keys: a Kalibr camchain.yaml (cam0, cam1, T_cn_cnm1), the two "
            "eyes' ASL/EuRoC sensor.yaml (T_BS, intrinsics, distortion_coefficients; left first), the two eyes' "
            "ROS camera_info YAML (K, D, R, P), or an OpenCV stereo file (M1 D1 M2 D2 R T or K1 ...; "
            "intrinsics.yml and extrinsics.yml as two files). Prints the rig: baseline, focal length, the "
            "nearest depth the configured disparities measure, the rectified size."
        ),
    )
    p.add_argument(
        "files", type=Path, nargs="+", metavar="FILE",
        help="one file, or two (left eye's first); or a recorded flight (an ASL folder, a rosbag) for its own calibration",
    )
    p.add_argument("--out", type=Path, required=True, help="the calibration file to write: .yaml, .yml, .xml, .json or .npz")
    p.add_argument("--config", type=Path, help="TOML config: stereo.num_disparities and calibration.rectify_alpha for the rig printed")
    p.add_argument("--write-config", action="store_true", help="also set calibration.file = OUT in --config")
    p.add_argument("--image-size", metavar="WxH", help="one eye's size, for an OpenCV file that does not hold it")
    p.add_argument("--t-units", choices=["m", "cm", "mm"], help="the unit of an OpenCV file's T when it has no T_units (default m)")
    p.add_argument("--json", action="store_true", help="print the rig as JSON")
    p.set_defaults(func=run)


def _parse_size(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if m is None or int(m.group(1)) <= 0 or int(m.group(2)) <= 0:
        raise InputError(f"--image-size {text!r}: expected WIDTHxHEIGHT in pixels, e.g. 752x480")
    return int(m.group(1)), int(m.group(2))


def rig_summary(calib: Any, cfg: Any) -> dict[str, Any]:
    """The rig a calibration describes under ``cfg``: what ``calibrate import`` prints.

    Returns:
        ``baseline_m``, ``focal_px`` (rectified), ``rectified_size_px`` ``[w, h]``, ``valid_region_px``
        ``[x, y, w, h]``, ``num_disparities``, ``min_measurable_depth_m`` (``f·B / (D - 1)``),
        ``lens`` (pinhole or fisheye), ``rotation_between_eyes_deg``.

    Raises:
        CalibrationError: the rig cannot be rectified (swapped eyes, a vertical rig).
    """
    import cv2
    import numpy as np

    from companion.core.rectifier import Rectifier

    rect = Rectifier(calib, alpha=cfg.calibration.rectify_alpha)
    g = rect.geometry
    D = cfg.stereo.num_disparities
    rvec, _ = cv2.Rodrigues(np.asarray(calib.R))
    return {
        "lens": calib.model,
        "eye_size_px": list(calib.image_size),
        "baseline_m": round(g.baseline_m, 5),
        "focal_px": round(g.focal_px, 2),
        "rectified_size_px": [g.width_px, g.height_px],
        "valid_region_px": list(rect.valid_roi_left),
        "num_disparities": D,
        "min_measurable_depth_m": round(g.focal_baseline_px_m / (D - 1), 3),
        "rotation_between_eyes_deg": round(float(np.degrees(np.linalg.norm(rvec))), 3),
    }


def _import(args: argparse.Namespace) -> Any:
    """The files' calibration; a recorded flight's own (an ASL folder's sensor.yaml files, a bag's
    camera_info topics) when the one path given is a recording."""
    from companion.calib.importers import ImportedCalibration, import_calibration
    from companion.errors import CalibrationError
    from companion.recorded.sequence import is_sequence, open_sequence

    if len(args.files) == 1 and is_sequence(args.files[0]):
        seq = open_sequence(args.files[0])
        calib = seq.calibration()
        if calib is None:
            where = "mav0/cam0/sensor.yaml and mav0/cam1/sensor.yaml" if seq.kind == "asl" else (
                f"camera_info topics beside {seq.topics[0]} and {seq.topics[1]}"
            )
            raise CalibrationError(f"{args.files[0]}: the recording holds no calibration (no {where})")
        return ImportedCalibration(calib, "asl" if seq.kind == "asl" else "rosbag", (args.files[0],))
    return import_calibration(args.files, image_size=_parse_size(args.image_size), t_units=args.t_units)


def run(args: argparse.Namespace) -> int:
    from companion.calib.importers import FORMATS
    from companion.config import load_config
    from companion.core.calibration_files import OPENCV_CALIBRATION_SUFFIXES, save_calibration

    out = args.out.expanduser()
    if out.suffix.lower() not in OPENCV_CALIBRATION_SUFFIXES:
        raise InputError(f"{out}: --out must end in {', '.join(OPENCV_CALIBRATION_SUFFIXES)}")
    if args.write_config and args.config is None:
        raise InputError("--write-config needs --config")
    if len(args.files) > 2:
        raise InputError(f"give one or two calibration files, not {len(args.files)}")
    cfg = load_config(args.config)
    imported = _import(args)
    calib = imported.calibration
    rig = rig_summary(calib, cfg)  # before writing: a rig that cannot be rectified is not written
    if rig["baseline_m"] > 2.0:
        raise InputError(
            f"{' + '.join(str(f) for f in imported.files)}: a baseline of {rig['baseline_m']:g} m is no drone's stereo "
            "rig; is T in millimetres (--t-units mm)?"
        )
    save_calibration(
        calib,
        out,
        metadata={
            "tool": "companion calibrate import",
            "created": datetime.date.today().isoformat(),
            "imported_from": f"{FORMATS[imported.format]}: " + ", ".join(str(f.resolve()) for f in imported.files),
        },
    )
    if args.write_config:
        from companion.config.edit import set_config_value_in_file

        set_config_value_in_file(args.config, "calibration", "file", str(out.resolve()))
    if args.json:
        doc = {"format": imported.format, "files": [str(f) for f in imported.files], "out": str(out), **rig, "notes": list(imported.notes)}
        json.dump(doc, sys.stdout, indent=2)
        sys.stdout.write("\n")
        return 0
    x, y, w, h = rig["valid_region_px"]
    lines = [
        f"imported {FORMATS[imported.format]}: {', '.join(str(f) for f in imported.files)}",
        *(f"  note: {n}" for n in imported.notes),
        f"  eyes: {rig['eye_size_px'][0]}x{rig['eye_size_px'][1]} px, {rig['lens']} lens, "
        f"{rig['rotation_between_eyes_deg']:g} deg between the eyes",
        f"  baseline {rig['baseline_m'] * 1000:.1f} mm, rectified focal length {rig['focal_px']:.1f} px",
        f"  nearest measurable depth {rig['min_measurable_depth_m']:.2f} m at {rig['num_disparities']} disparities "
        "(stereo.num_disparities)",
        f"  rectified size {rig['rectified_size_px'][0]}x{rig['rectified_size_px'][1]} px, all-valid region {w}x{h} at ({x}, {y})",
        f"wrote {out}" + (f"; set calibration.file in {args.config}" if args.write_config else ""),
    ]
    print("\n".join(lines))
    return 0
