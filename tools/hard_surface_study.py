#!/usr/bin/env python3
"""Issue 15 item 5: what the hard surfaces do to the obstacle memory, per backend.

Flies courses of a suite closed-loop (as ``companion sim --suite`` does: same configs, same verdicts)
and checks every near point the memory is given (``FrameResult.near_points_cam_m``, placed in NED
from the pose the frame was seen from) against the ground truth: a point is **false** when no
surface (obstacle or ground) lies within ``0.1 m + 10 %`` of its range (about one pixel of disparity
error at 2.5 m, the memory's farthest point). Prints the suite table and, per course kind: points
per frame, false points per frame, the false share, and the share of frames with a false point.

Usage::

    python tools/hard_surface_study.py --config C.toml [--suite standard] [--kinds office] [--workers 2]

Figures of 2026-11-23 are in docs/history.md ("Hard surfaces").
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from companion.config import load_config  # noqa: E402
from companion.sim.suite import select_kinds, single_thread_config, suite_courses, suite_table  # noqa: E402

#: A point farther than this plus ``_TOL_FRACTION`` of its range from every surface is false, metres.
_TOL_M = 0.1
_TOL_FRACTION = 0.1


def _fly(args: tuple[str, int, dict]) -> tuple[object, dict[str, float]]:
    kind, seed, cfg_data = args
    import dataclasses

    from companion.config import parse_config
    from companion.core.memory import camera_points_to_ned
    from companion.sim.courses import make_course
    from companion.sim.loop import fly
    from companion.sim.render import Pose

    cfg = parse_config(cfg_data, source="study")
    course = make_course(kind, seed)
    points: list[np.ndarray] = []

    def on_frame(frame: object, res: object) -> None:
        pts = getattr(res, "near_points_cam_m", None)
        points.append(np.zeros((0, 3)) if pts is None else np.asarray(pts, dtype=np.float64).reshape(-1, 3))

    result = fly(course, cfg, on_frame=on_frame)
    log = result.frame_log
    assert log is not None and len(points) == log.t_s.size
    n_pts = n_false = frames_false = 0
    for i, pts in enumerate(points):
        if pts.shape[0] == 0:
            continue
        roll, pitch, yaw = log.attitude_rad[i]
        pose = Pose(tuple(log.position_ned_m[i]), float(yaw), float(pitch), float(roll))
        ned = camera_points_to_ned(pts, pose)
        rng_m = np.linalg.norm(pts, axis=1)
        dist = np.asarray(course.scene.distance_to_obstacles_m(ned, include_ground=True)).reshape(-1)
        false = dist > _TOL_M + _TOL_FRACTION * rng_m
        n_pts += pts.shape[0]
        n_false += int(false.sum())
        frames_false += bool(false.any())
    stats = {"frames": float(log.t_s.size), "points": float(n_pts), "false": float(n_false),
             "frames_false": float(frames_false)}
    return dataclasses.replace(result, log=None, frame_log=None), stats


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path)
    ap.add_argument("--suite", default="standard")
    ap.add_argument("--kinds")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    cfg = single_thread_config(load_config(args.config))
    courses = suite_courses(args.suite)
    if args.kinds:
        courses = select_kinds(courses, args.kinds)
    data = cfg.model_dump(mode="json")
    t0 = time.perf_counter()
    with mp.get_context("spawn").Pool(args.workers) as pool:
        out = pool.map(_fly, [(k, s, data) for k, s in courses], chunksize=1)
    results = [r for r, _ in out]
    for r, st in out:
        print(f"{r.summary()}  points {st['points']:.0f}, false {st['false']:.0f} in {st['frames']:.0f} frames")
    print()
    print(suite_table(results))
    print(f"\nwall time {time.perf_counter() - t0:.0f} s; false point: > {_TOL_M} m + {_TOL_FRACTION:.0%} of its range "
          "from every surface")
    print("kind      frames  points/frame  false/frame  false share  frames with a false point")
    kinds = sorted({r.course.kind for r in results}, key=[k for k, _ in courses].index)
    for kind in kinds + ["all"]:
        sts = [st for r, st in out if kind in ("all", r.course.kind)]
        fr = sum(s["frames"] for s in sts)
        pts = sum(s["points"] for s in sts)
        fa = sum(s["false"] for s in sts)
        ff = sum(s["frames_false"] for s in sts)
        print(f"{kind:9s} {fr:6.0f}  {pts / fr:12.2f}  {fa / fr:11.3f}  {100 * fa / max(pts, 1):10.1f} %  "
              f"{100 * ff / fr:6.1f} %")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
