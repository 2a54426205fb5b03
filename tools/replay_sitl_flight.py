#!/usr/bin/env python3
"""Replay a `companion sitl` flight through the pure core, from the service's health log.

A PX4 SITL flight is not repeatable (PX4's estimator and the service's timing differ each run), but
its health log (``WORKDIR/service/health.jsonl``, ~10 records a second) keeps the vehicle's pose,
velocity and the setpoint the service sent. The service's camera renders the course from that pose
(``camera.sim_world = "course"``), so the frames can be rendered again. For every record this tool

* renders the course at the logged pose with the service's own sim camera (its rig, noise and
  seed: :func:`~companion.service.camera.sim_camera_from_config`), runs the pipeline and puts
  the frame's near points in an obstacle memory from that pose, as the supervisor does;
* once the log says ``engaged``, steps a course hold (:class:`~companion.core.course.CourseHold`,
  engaged at that record's pose with the logged goal) with the replayed decision and the logged
  position, heading and velocity, as the supervisor does;
* prints the logged and the replayed setpoints side by side, the track counter both ways, the
  replayed middle-row depths and, with ``--guard``, the guard's rows (distance, bearing from the
  nose, whether the point may push).

Where the two setpoints agree, the replay's internals (``--guard``, or a breakpoint in
``CourseHold``) show why the service commanded what it did. It is an approximation: the service
steps at 20 Hz and captures at 15 fps, the replay once per record; the course's placement is taken
from the first ``engaging`` record's pose (a few centimetres off the harness's own); the detour
layer's histograms are computed at once.

Usage: ``PYTHONPATH=. python tools/replay_sitl_flight.py WORKDIR [--from S] [--to S] [--guard]``,
``WORKDIR`` one flight's folder under ``companion sitl --workdir`` (e.g. ``work/30-office-3``); times
in seconds from the log's first record. docs/sitl.md, "Replaying a flight".
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from companion.backends import make_pipeline
from companion.config import load_config
from companion.core.course import CourseHold
from companion.core.goal import GoalSpec
from companion.core.memory import ObstacleMemory
from companion.core.pose import Pose
from companion.core.types import REGION_INDEX, VelocitySetpoint
from companion.service.camera import placement_fields, sim_camera_from_config
from companion.sim.courses import make_course
from companion.core.placement import CoursePlacement


def _goal(record: dict[str, Any]) -> GoalSpec:
    g = record.get("goal") or {}
    if g.get("kind") == "point":
        return GoalSpec(kind="point", north_m=float(g["north_m"]), east_m=float(g["east_m"]))
    return GoalSpec()  # the heading and line at engagement (a bearing goal is logged as its point)


def _f(x: float | None) -> str:
    return "  nan" if x is None or not math.isfinite(x) else f"{x:5.2f}"


def replay(workdir: Path, t_from: float, t_to: float, show_guard: bool) -> int:
    records = [json.loads(line) for line in (workdir / "service" / "health.jsonl").read_text().splitlines() if line.strip()]
    records = [r for r in records if r.get("type") == "health" and (r.get("vehicle") or {}).get("position_ned_m")]
    if not records:
        print(f"{workdir}: no health records with a position", file=sys.stderr)
        return 2
    cfg = load_config(workdir / "service" / "companion.toml")
    if cfg.camera.sim_world != "course":
        print(f"{workdir}: camera.sim_world is {cfg.camera.sim_world!r}, not a course", file=sys.stderr)
        return 2
    engaging = next((r for r in records if r["state"] == "engaging"), None)
    if engaging is None:
        print(f"{workdir}: the log has no engaging record (the course is placed then)", file=sys.stderr)
        return 2
    course = make_course(cfg.camera.sim_course, cfg.camera.sim_course_seed)
    n, e, d = engaging["vehicle"]["position_ned_m"]
    placement = CoursePlacement((n, e, d - float(course.start.position_ned_m[2])), float(engaging["vehicle"]["attitude_rad"][2]))
    data = cfg.model_dump()
    data["camera"].update(placement_fields(placement))
    cfg = type(cfg).model_validate(data)

    # The service's own sim camera (its rig, scene, noise and seed), fed the logged pose and time.
    now: list[Any] = [None, 0.0]  # the pose in the course and the time of the record being replayed
    camera = sim_camera_from_config(cfg, pose_provider=lambda: (now[0], now[1]), clock=lambda: now[1])
    camera.open()
    pipeline = make_pipeline(cfg, cfg.camera.width_px, cfg.camera.height_px)
    memory = ObstacleMemory()
    hold = CourseHold(defer_histogram=False)
    engaged = False
    t0 = records[0]["time_s"]
    prefer_right = cfg.controller.preferred_yaw_side == "right"
    print("t s    north  east   yaw deg  decision      logged sp fwd,right,yaw  replayed sp fwd,right,yaw  counter log/rep  L     C     R")
    for r in records:
        t = r["time_s"] - t0
        if t > t_to:
            break
        v = r["vehicle"]
        pos = np.asarray(v["position_ned_m"], dtype=np.float64)
        att = np.asarray(v["attitude_rad"], dtype=np.float64)
        vel = np.asarray(v["velocity_ned_m_s"], dtype=np.float64) if v.get("velocity_ned_m_s") else None
        now[:] = [placement.pose_in_course(pos, att), r["time_s"]]
        res = pipeline.process(camera.read().image, r["time_s"])
        if res.near_points_cam_m is not None:
            seen_from = Pose.from_telemetry(pos, att)
            if seen_from is not None:
                memory.add_frame(res.near_points_cam_m, seen_from, r["time_s"], cfg.memory, res.far_view)
        if r["state"] == "engaged" and not engaged:
            engaged = True
            hold.engage(pos, float(att[2]), _goal(r))
        if not engaged or r["state"] != "engaged":
            continue
        hold.observe(res.decision, r["time_s"], pos)
        guard, sides, gap, ahead = memory.hold_inputs(pos, float(att[2]), r["time_s"], cfg.memory, res.view_limits)
        sp = hold.setpoint(
            res.decision, r["time_s"], 0.0, cfg.command,
            position_ned_m=pos, yaw_rad=float(att[2]), velocity_ned_m_s=vel, position_time_s=r["time_s"],
            region_depths_m=res.refined.depth_m, guard_m=guard, remembered_sides=sides, gap=gap, path_ahead_m=ahead,
            memory_cfg=cfg.memory, obstacles=memory, detour_cfg=cfg.detour, prefer_right=prefer_right,
        )
        if t < t_from:
            continue
        logged = VelocitySetpoint(**r["setpoint"]) if r.get("setpoint") else VelocitySetpoint()
        depth = res.refined.depth_m
        kind = f"{res.decision.kind.value}/{(r.get('decision') or {}).get('kind', '-')}"
        print(
            f"{t:5.1f} {pos[0]:6.2f} {pos[1]:6.2f} {math.degrees(att[2]):7.1f}  {kind:12s}  "
            f"{logged.forward_m_s:5.2f},{logged.right_m_s:5.2f},{logged.yaw_rate_deg_s:6.1f}       "
            f"{sp.forward_m_s:5.2f},{sp.right_m_s:5.2f},{sp.yaw_rate_deg_s:6.1f}       "
            f"{(r.get('memory') or {}).get('track_counter_m_s', 0.0):.2f}/{hold.track_counter_m_s:.2f}     "
            f"{_f(depth[REGION_INDEX['left']])} {_f(depth[REGION_INDEX['center']])} {_f(depth[REGION_INDEX['right']])}"
        )
        if show_guard and guard is not None:
            for dist, uf, ur, push in np.asarray(guard).reshape(-1, 4):
                print(f"        guard {dist:.2f} m at {math.degrees(math.atan2(ur, uf)):6.1f} deg, may push: {bool(push)}")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("workdir", type=Path, help="one flight's folder under `companion sitl --workdir`")
    ap.add_argument("--from", dest="t_from", type=float, default=0.0, help="print from this time, s")
    ap.add_argument("--to", dest="t_to", type=float, default=math.inf, help="stop at this time, s")
    ap.add_argument("--guard", action="store_true", help="print the guard's rows too")
    a = ap.parse_args(argv)
    return replay(a.workdir.resolve(), a.t_from, a.t_to, a.guard)


if __name__ == "__main__":
    sys.exit(main())
