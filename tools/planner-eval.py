#!/usr/bin/env python3
"""Fly a set of simulator courses with one config and print the planner's figures: the suite table, goals
among courses that are not dead ends, dead ends held, collisions, the median time to goal over the
straight line at cruise, and the mean speed of goal flights on the open kinds (pitch, side).

    python tools/planner-eval.py --config my.toml --seeds 1000-1008 --workers 15 --json out.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from companion.config import load_config
from companion.sim.courses import COURSE_KINDS, make_course
from companion.sim.scoring import Outcome
from companion.sim.suite import realization_line, run_suite, suite_table


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, default=None)
    ap.add_argument("--seeds", default="0-8", help="first-last seed of every kind")
    ap.add_argument("--kinds", default=",".join(COURSE_KINDS))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--label", default="")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    cfg = load_config(args.config)
    lo, hi = (int(x) for x in args.seeds.split("-"))
    kinds = [k for k in args.kinds.split(",") if k]
    courses = [(k, s) for s in range(lo, hi + 1) for k in kinds]
    results = run_suite(cfg, courses, workers=args.workers)
    cruise = cfg.planner.cruise_speed_m_s
    ratios, speeds, rows = [], [], []
    for r in results:
        course = make_course(r.course.kind, r.course.seed)
        straight_s = (course.goal_north_m - course.start.position_ned_m[0]) / cruise
        if r.outcome is Outcome.GOAL:
            ratios.append(r.time_s / straight_s)
            if r.course.kind in ("pitch", "side"):
                speeds.append(r.path_length_m / r.time_s)
        rows.append(
            {"kind": r.course.kind, "seed": r.course.seed, "outcome": r.outcome.value, "time_s": round(r.time_s, 2),
             "min_clearance_m": round(r.min_clearance_m, 3), "path_m": round(r.path_length_m, 2), "reason": r.reason,
             "hold_reason": r.hold_reason}
        )
    print(f"== {args.label} (cruise {cruise:g} m/s, seeds {args.seeds})")
    print(suite_table(results))
    print(realization_line(cfg.sim.realization, results))
    if ratios:
        print(f"median time to goal / straight line at cruise: {np.median(ratios):.2f}x (max {np.max(ratios):.2f}x)")
    if speeds:
        print(f"mean speed of goal flights on pitch and side: {np.mean(speeds):.2f} m/s")
    for row in rows:
        if row["outcome"] not in ("goal",) and not (row["kind"] == "deadend" and row["outcome"] == "held"):
            print(f"  fail {row['kind']}-{row['seed']}: {row['outcome']}: {row['reason']} {row['hold_reason']}")
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
