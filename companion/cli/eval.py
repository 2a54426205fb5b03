"""``companion eval``: disparity and region quality of a backend on a stereo pair with ground truth."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

from companion.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "eval",
        help="score a disparity backend on a stereo pair with ground truth (bad-1/bad-2, density, regions)",
        description=(
            "Run one backend on a rectified pair with ground truth and print: bad-1, bad-2 and density "
            "over the GT-known and the matchable pixels, the share of errors that point too near, and per "
            "region the robust minimum depth from the output against the same from the ground truth, "
            "each region's near/far class and the controller's decision from both. Reads Middlebury "
            "folders (2014/2021: im0.png, im1.png, disp0.pfm, calib.txt; 2005/2006: view1.png, view5.png, "
            "disp1.png at full, half or third size; OpenCV's Aloe sample) or explicit files. Without a "
            "calibration the rig is assumed (90 degree field of view, 12 cm baseline) for the depths. Each "
            "region is judged: a phantom reads nearer than 0.75 x the truth, a missed surface is one nearer "
            "than 1 m read farther than its depth / 0.75 and than the rig's nearest measurable depth, and "
            "unknown has too few valid pixels."
        ),
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--middlebury", type=Path, nargs="+", metavar="DIR",
        help="Middlebury folders (see above); with several, each report and then the totals",
    )
    src.add_argument("--left", type=Path, metavar="L", help="left image (with --right and a ground truth)")
    p.add_argument("--right", type=Path, metavar="R", help="right image")
    gt = p.add_mutually_exclusive_group()
    gt.add_argument("--gt-disparity", type=Path, metavar="F", help="left-view disparity: .pfm, .png, .npy or .npz, px")
    gt.add_argument("--gt-depth", type=Path, metavar="F", help="left-view depth: .pfm, .npy or .npz in m, 16-bit .png in mm")
    p.add_argument("--gt-png-scale", type=float, default=1.0, help="PNG disparity units per pixel (default 1)")
    p.add_argument("--calib", type=Path, help="Middlebury calib.txt for explicit files (focal, baseline, doffs)")
    p.add_argument("--focal-px", type=float, help="focal length, px (overrides the calibration or the assumption)")
    p.add_argument("--baseline-m", type=float, help="baseline, m (overrides the calibration or the assumption)")
    p.add_argument("--doffs-px", type=float, default=None, help="principal point offset between the eyes, px")
    p.add_argument("--scale", type=float, default=1.0, help="evaluate at this scale, e.g. 0.5 (default 1)")
    p.add_argument("--config", type=Path, help="TOML config (default: built-in defaults)")
    p.add_argument("--backend", help="override stereo.backend (auto, opencv-bm, opencv-sgbm, reference, cupy, cpu-sgm)")
    p.add_argument("--matcher", choices=["sgm", "sad"], help="override stereo.matcher (reference, cupy)")
    p.add_argument("--sgm-paths", type=int, choices=[4, 8], help="override stereo.sgm_paths")
    p.add_argument(
        "--num-disparities", type=int, help="override the search range (default: the ground truth's, rounded up to 16)"
    )
    p.add_argument("--save-disparity", type=Path, metavar="OUT", help="also write the output disparity (.npy or .pfm)")
    p.add_argument("--json", type=Path, metavar="OUT", help="also write every figure as JSON")
    p.set_defaults(func=run)


def _load(args: argparse.Namespace, folder: Path | None) -> Any:
    from dataclasses import replace

    from companion.core.evaluation import load_middlebury, load_pair, rescale

    if folder is not None:
        if args.right is not None or args.gt_disparity is not None or args.gt_depth is not None:
            raise InputError("--middlebury reads the folder's own files: leave out --right/--gt-*")
        pair = load_middlebury(folder)
    else:
        if args.right is None:
            raise InputError("--left needs --right")
        pair = load_pair(
            args.left, args.right, disparity=args.gt_disparity, depth=args.gt_depth, calib=args.calib,
            focal_px=args.focal_px, baseline_m=args.baseline_m,
            doffs_px=args.doffs_px if args.doffs_px is not None else 0.0,
            disparity_png_scale=args.gt_png_scale,
        )
    over: dict[str, Any] = {}
    if args.focal_px is not None:
        over["focal_px"] = float(args.focal_px)
    if args.baseline_m is not None:
        over["baseline_m"] = float(args.baseline_m)
    if args.doffs_px is not None:
        over["doffs_px"] = float(args.doffs_px)
    if over:
        pair = replace(pair, assumed=False, **over)
    return rescale(pair, float(args.scale))


def evaluate(args: argparse.Namespace, folder: Path | None = None) -> dict[str, Any]:
    """Load the pair (``folder``: a Middlebury folder, else the explicit files), run the backend, score
    it; returns the report (also what ``--json`` writes for one pair)."""
    import numpy as np

    from companion.config import apply_patch, load_config
    from companion.core.evaluation import disparity_metrics, region_report, suggested_num_disparities, write_pfm
    from companion.backends import make_estimator

    pair = _load(args, folder)
    w, h = pair.width_px, pair.height_px
    D = int(args.num_disparities or suggested_num_disparities(pair))
    stereo: dict[str, Any] = {"num_disparities": D}
    if args.backend:
        stereo["backend"] = args.backend
    if args.matcher:
        stereo["matcher"] = args.matcher
    if args.sgm_paths:
        stereo["sgm_paths"] = args.sgm_paths
    hfov = math.degrees(2.0 * math.atan((w / 2.0) / pair.focal_px))
    cfg = apply_patch(
        load_config(args.config),
        {
            "stereo": stereo,
            "calibration": {"file": None, "ideal_hfov_deg": hfov, "ideal_baseline_m": pair.baseline_m},
            "camera": {"width_px": w, "height_px": h},
            "gpu": {"disparity_preview_downsample": 0},
        },
    )
    from companion.core.rig_check import check_rig

    rig_check = check_rig(pair.geometry(), cfg.stereo, cfg.regions, cfg.controller)
    est = make_estimator(cfg, w, h)
    frame = np.ascontiguousarray(np.hstack([pair.left, pair.right]))
    t0 = time.perf_counter()
    res = est.estimate(frame, want_disparity=True)
    run_s = time.perf_counter() - t0
    disp = res.disparity
    assert disp is not None
    if args.save_disparity is not None:
        if args.save_disparity.suffix.lower() == ".pfm":
            write_pfm(args.save_disparity, np.where(np.isnan(disp), np.inf, disp).astype(np.float32))
        else:
            np.save(args.save_disparity, disp)
    st = cfg.stereo
    backend = est.name
    if backend in ("reference", "cupy"):
        backend += f" ({st.matcher}" + (f", {st.sgm_paths} paths)" if st.matcher == "sgm" else ")")
    elif backend == "cpu-sgm":
        backend += f" (sgm, {st.sgm_paths} paths)"
    return {
        "pair": pair.name,
        "size": [w, h],
        "num_disparities": D,
        "rig": {"focal_px": pair.focal_px, "baseline_m": pair.baseline_m, "doffs_px": pair.doffs_px,
                "assumed": pair.assumed},
        "backend": backend,
        "rig_check": {"errors": list(rig_check.errors), "warnings": list(rig_check.warnings),
                      "nearest_depth_m": rig_check.nearest_depth_m},
        "run_s": run_s,
        "disparity": disparity_metrics(disp, pair.disparity, D),
        **region_report(disp, pair, cfg),
    }


def _pct(v: float) -> str:
    return "-" if v != v else f"{100 * v:.1f} %"


def _m(v: float) -> str:
    return "unknown" if v != v else f"{v:.2f}"


def print_report(r: dict[str, Any]) -> None:
    d = r["disparity"]
    rig = r["rig"]
    print(f"pair: {r['pair']}, {r['size'][0]}x{r['size'][1]}, {r['num_disparities']} disparities")
    print(
        f"rig: f = {rig['focal_px']:.1f} px, B = {rig['baseline_m']:.3f} m, doffs = {rig['doffs_px']:.1f} px"
        + (" (assumed: no calibration)" if rig["assumed"] else "")
    )
    for kind in ("errors", "warnings"):
        for msg in r["rig_check"][kind]:
            print(f"rig check: {kind[:-1]}: {msg} (reported, not applied: eval scores any rig)")
    print(f"backend: {r['backend']}, {r['run_s'] * 1e3:.1f} ms for the frame")
    for label in ("known", "matchable"):
        print(
            f"{'GT-known' if label == 'known' else 'matchable'} pixels ({int(d[label + '_px'])}): "
            f"bad-1 {_pct(d['bad1_' + label])}, bad-2 {_pct(d['bad2_' + label])} of the output pixels, "
            f"density {_pct(d['density_' + label])}; bad-2 errors that point too near: "
            f"{_pct(d['too_near_' + label])}"
        )
    print("region        GT m   out m   err m  GT valid  valid  GT class  class    verdict")
    for row in r["regions"]:
        err = "-" if row["error_m"] != row["error_m"] else f"{row['error_m']:+.2f}"
        print(
            f"{row['name']:<11} {_m(row['gt_depth_m']):>7} {_m(row['depth_m']):>7} {err:>7}  "
            f"{100 * row['gt_valid']:6.1f}%  {100 * row['valid']:5.1f}%  {row['gt_class']:<8}  "
            f"{row['class']:<7}  {row['verdict']}".rstrip()
        )
    g, o = r["gt_decision"], r["decision"]
    print(f"classes agree in {r['class_agreement']} of 9 regions")
    print(f"decision from GT:     {g['kind']} (yaw {g['yaw']:+.2f}, pitch {g['pitch']:+.2f}): {g['reason']}")
    print(f"decision from output: {o['kind']} (yaw {o['yaw']:+.2f}, pitch {o['pitch']:+.2f}): {o['reason']}")
    sys.stdout.flush()


def summarise(reports: list[dict[str, Any]]) -> dict[str, Any]:
    """Totals over several pairs: regions judged, phantoms, missed near surfaces, unknown regions, and
    the mean bad-2 and density over the GT-known pixels."""
    verdicts = [row["verdict"] for r in reports for row in r["regions"]]
    return {
        "pairs": len(reports),
        "regions": len(verdicts),
        "phantoms": verdicts.count("phantom"),
        "missed": verdicts.count("missed"),
        "unknown": verdicts.count("unknown"),
        "mean_bad2_known": sum(r["disparity"]["bad2_known"] for r in reports) / len(reports),
        "mean_density_known": sum(r["disparity"]["density_known"] for r in reports) / len(reports),
    }


def run(args: argparse.Namespace) -> int:
    if not 0.05 <= args.scale <= 1.0:
        raise InputError(f"--scale must be in [0.05, 1], got {args.scale}")
    folders = args.middlebury or [None]
    if len(folders) > 1 and args.save_disparity is not None:
        raise InputError("--save-disparity writes one pair's disparity: give one --middlebury folder")
    reports = []
    for folder in folders:
        reports.append(evaluate(args, folder))
        print_report(reports[-1])
    out: dict[str, Any] = reports[0]
    if len(reports) > 1:
        out = {"pairs": reports, "summary": summarise(reports)}
        t = out["summary"]
        print(
            f"{t['pairs']} pairs, {t['regions']} regions: {t['phantoms']} phantoms, {t['missed']} missed near "
            f"surfaces, {t['unknown']} unknown; mean bad-2 {_pct(t['mean_bad2_known'])} at density "
            f"{_pct(t['mean_density_known'])} (GT-known pixels)"
        )
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=2, default=float) + "\n", encoding="utf-8")
    return 0
