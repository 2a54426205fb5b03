#!/usr/bin/env python3
"""What the hard surfaces (plain walls, bars, glare) do to the disparity and the map's blocks, per backend.

Single frames of each kind's courses seen from fixed poses on the course line (the simulated camera's
noise and eye gain mismatch, no flight), scored like ``companion eval`` against the renderer's depth:
density and bad-2 over the pixels, and per region the classes (near / far / unknown) from the output
and from the ground truth: a **phantom** is a region the output calls near that the ground truth
calls far; **unknown** one the output leaves unknown (which the controller treats as near) that the
ground truth knows. Then the local planner's map input, its blocks of nearest disparity
(:func:`~companion.core.evaluation.map_block_report`): the share too near, where they lie (a depth
edge smeared onto what is behind it, a plain or a textured surface), and the share of near surfaces
seen; with ``--block-erode-px 0,1,2``, also of the disparity eroded along rows first
(``planner.block_erode_px``).

Usage::

    python tools/hard_surface_study.py [--config C.toml] [--backends opencv-bm,reference] [--kinds office,doorway]
        [--block-erode-px 0,1]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from companion.config import load_config  # noqa: E402
from companion.sim.suite import single_thread_config  # noqa: E402

#: A block whose ground truth is nearer than this counts as a near surface (for "near seen"), metres.
_NEAR_M = 2.5


def _frame_poses(kind: str, seed: int) -> list[tuple[float, float]]:
    """(north, east) metres of the study's viewpoints on a course: on the line, 1.5 m up, facing north.
    The office: the start, 2.5 and 1.2 m before the fence, in the fence's gap 1 m past it, and 3 m
    and 1.5 m before the far wall; other kinds: every 1.5 m from the start to 4.5 m."""
    from companion.sim.courses import make_course

    course = make_course(kind, seed)
    if kind != "office":
        return [(n, 0.0) for n in (0.0, 1.5, 3.0, 4.5)]
    obs = course.scene.obstacles
    fence = next(ob for ob in obs if getattr(ob, "surface", None) is not None and ob.surface.kind == "bars"
                 and ob.surface.see_through)
    fence_n, fence_e, span = fence.centre_ned_m[0], fence.centre_ned_m[1], fence.size_m[1]
    wall_n = obs[2].centre_ned_m[0] - 0.5 * obs[2].size_m[0]
    # The fence's free end is the edge nearer the line; its gap is on the other side of the line.
    free_e = fence_e - np.sign(fence_e) * 0.5 * span
    gap_e = free_e - np.sign(fence_e) * 0.7
    return [(0.0, 0.0), (fence_n - 2.5, 0.0), (fence_n - 1.2, 0.0), (fence_n + 1.0, gap_e),
            (wall_n - 3.0, gap_e), (wall_n - 1.5, gap_e)]


def _frames(args: tuple[str, int, dict, list[str], list[int]]) -> list[dict[str, object]]:
    kind, seed, cfg_data, backends, erosions = args
    from companion.backends import make_estimator
    from companion.config import apply_patch, parse_config
    from companion.core.evaluation import GroundTruthPair, disparity_metrics, map_block_report, region_report
    from companion.core.blocks import erode_rows
    from companion.sim.camera import make_texture_bank
    from companion.sim.courses import make_course
    from companion.sim.loop import simulator_config
    from companion.sim.render import Photometry, Pose, StereoRenderer

    cfg = simulator_config(parse_config(cfg_data, source="study"))
    sim = cfg.sim
    w, h = sim.eye_width_px, sim.eye_height_px
    course = make_course(kind, seed)
    estimators = {b: make_estimator(apply_patch(cfg, {"stereo": {"backend": b}}), w, h) for b in backends}
    geo = next(iter(estimators.values())).geometry
    renderer = StereoRenderer(geo, course.scene, seed=seed, textures=make_texture_bank())
    rng = np.random.default_rng([seed, 0x57D])
    rows = []
    for i, (north, east) in enumerate(_frame_poses(kind, seed)):
        m = sim.eye_gain_mismatch * float(rng.uniform(-1.0, 1.0))
        res = renderer.render(Pose.at(north, east, 1.5), left=Photometry(1.0 + 0.5 * m, sim.noise_std_grey),
                              right=Photometry(1.0 - 0.5 * m, sim.noise_std_grey), rng=rng)
        gt = (geo.focal_baseline_px_m / res.depth_m).astype(np.float32)
        pair = GroundTruthPair(res.left_bgr[:, :, 0], res.right_bgr[:, :, 0], gt, geo.focal_px, geo.baseline_m,
                               0.0, geo.cx_px, geo.cy_px, f"{kind}-{seed} view {i}")
        frame = np.ascontiguousarray(np.hstack([res.left_bgr, res.right_bgr]))
        for b, est in estimators.items():
            disp = est.estimate(frame, want_disparity=True).disparity
            met = disparity_metrics(disp, gt, cfg.stereo.num_disparities)
            reg = region_report(disp, pair, cfg)
            blocks = {
                k: map_block_report(erode_rows(disp, k), gt, cfg.planner.block_px,
                                    geo.focal_baseline_px_m / _NEAR_M, left=pair.left)
                for k in erosions
            }
            rows.append({
                "kind": kind, "backend": b, "density": met["density_matchable"], "bad2": met["bad2_matchable"],
                "phantom": sum(r["class"] == "near" and r["gt_class"] == "far" for r in reg["regions"]),
                "unknown": sum(r["class"] == "unknown" and r["gt_class"] != "unknown" for r in reg["regions"]),
                "missed": sum(r["class"] == "far" and r["gt_class"] == "near" for r in reg["regions"]),
                "decision_differs": reg["decision"]["kind"] != reg["gt_decision"]["kind"],
                "blocks": blocks,
            })
    return rows


def frames_main(args: argparse.Namespace) -> int:
    """The study (module doc)."""
    cfg = single_thread_config(load_config(args.config))
    kinds = [k.strip() for k in (args.kinds or "office").split(",") if k.strip()]
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    seeds = range(args.seeds)
    data = cfg.model_dump(mode="json")
    erosions = [int(x) for x in args.block_erode_px.split(",")]
    with mp.get_context("spawn").Pool(args.workers) as pool:
        out = pool.map(_frames, [(k, s, data, backends, erosions) for k in kinds for s in seeds], chunksize=1)
    rows = [r for part in out for r in part]
    print(f"seeds 0..{args.seeds - 1}; density and bad-2 over matchable pixels (mean of frames); regions of 9 per frame")
    print("kind      backend       frames  density  bad-2   phantom near  unknown  missed near  decision differs")
    for kind in kinds:
        for b in backends:
            sel = [r for r in rows if r["kind"] == kind and r["backend"] == b]
            n = len(sel)
            print(f"{kind:9s} {b:12s} {n:7d}  {100 * np.mean([r['density'] for r in sel]):5.1f} %"
                  f"  {100 * np.nanmean([r['bad2'] for r in sel]):4.1f} %"
                  f"  {sum(r['phantom'] for r in sel):12d}  {sum(r['unknown'] for r in sel):7d}"
                  f"  {sum(r['missed'] for r in sel):11d}  {sum(r['decision_differs'] for r in sel):6d}")
    print(f"\nthe map's blocks ({cfg.planner.block_px} px, each its nearest disparity): too near = nearer than every "
          f"surface in it by > 1 px; at a jump: within 6 px of a depth edge; plain: texture < 4 grey levels; "
          f"seen: of the blocks with a surface nearer than {_NEAR_M} m, within 1 px")
    print("kind      backend       erode  blocks/frame  too near  at a jump  plain  textured  near seen")
    for kind in kinds:
        for b in backends:
            sel = [r for r in rows if r["kind"] == kind and r["backend"] == b]
            for k in erosions:
                t = {key: sum(r["blocks"][k][key] for r in sel) for key in sel[0]["blocks"][k]}
                tn = max(t["too_near"], 1.0)
                print(f"{kind:9s} {b:12s} ±{k} px  {t['blocks'] / len(sel):12.0f}  {100 * t['too_near'] / t['blocks']:6.1f} %"
                      f"  {100 * t['too_near_at_jump'] / tn:7.0f} %  {100 * t['too_near_plain'] / tn:3.0f} %"
                      f"  {100 * t['too_near_textured'] / tn:6.0f} %  {100 * t['near_seen'] / max(t['near'], 1.0):7.1f} %")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path)
    ap.add_argument("--kinds")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--backends", default="opencv-bm,reference", help="backends to score")
    ap.add_argument("--seeds", type=int, default=9, help="seeds 0..N-1 of each kind")
    ap.add_argument("--block-erode-px", default="0", help="also score the map's blocks of the disparity eroded "
                    "along rows by these ±px (comma-separated; 0 = as the backend gives it)")
    return frames_main(ap.parse_args())


if __name__ == "__main__":
    raise SystemExit(main())
