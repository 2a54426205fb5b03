#!/usr/bin/env python3
"""Draw docs/planner.png: the local planner's candidates over its map (a wall with an opening seen
from the start, the camera turned 30 degrees toward it), and the speed law.

    python tools/planner-figure.py docs/planner.png
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from companion.config.planner import PlannerConfig  # noqa: E402
from companion.core.geometry import StereoGeometry  # noqa: E402
from companion.core.planner.local import N_CLIMBS, LocalPlanner, Snapshot, speed_law  # noqa: E402
from companion.core.planner.localmap import LocalMap  # noqa: E402
from companion.core.pose import Pose  # noqa: E402
from companion.core.types import Decision, DecisionKind  # noqa: E402


def wall_with_opening(geom: StereoGeometry, pose: Pose, block_px: int, wall_n: float, gap: tuple[float, float]) -> np.ndarray:
    """Block disparities of a wall across north ``wall_n`` with an opening between east ``gap``, seen
    from ``pose`` (level): ray-cast per block column (px, NaN beyond 12 m)."""
    rows, cols = -(-geom.height_px // block_px), -(-geom.width_px // block_px)
    u = np.arange(cols) * block_px + 0.5 * block_px - 0.5
    bearing = pose.yaw_rad + np.arctan((u - geom.cx_px) / geom.focal_px)
    n0, e0 = pose.position_ned_m[0], pose.position_ned_m[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (wall_n - n0) / np.cos(bearing)
    east = e0 + t * np.sin(bearing)
    depth = t * np.cos(bearing - pose.yaw_rad)
    through = (east > gap[0]) & (east < gap[1])
    depth = np.where(through | (t <= 0), 12.0, depth)
    disp = geom.focal_baseline_px_m / depth
    return np.repeat(disp[None, :], rows, axis=0).astype(np.float32)


def main() -> int:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "docs/planner.png")
    cfg = PlannerConfig()
    geom = StereoGeometry.ideal(336, 188, 90.0, 0.12)
    lmap = LocalMap(cfg.voxel_m, cfg.map_range_m, 0.25, cfg.occupied_memory_s, cfg.free_memory_s)
    planner = LocalPlanner(cfg, 0.25)
    goal = np.array([8.0, 0.0, -1.5])
    pos = np.array([0.0, 0.0, -1.5])
    plan = None
    for k, yaw_deg in enumerate((0, 0, 0, 10, 20, 30, 30)):
        yaw = math.radians(yaw_deg)
        pose = Pose(tuple(pos), yaw)
        lmap.integrate(wall_with_opening(geom, pose, 4, 3.0, (2.2, 3.8)), geom, 4, pose, 0.1 * k)
        snap = Snapshot(0.1 * k, pos, np.zeros(3), yaw, goal, Decision(DecisionKind.BRAKE, 0.0, 0.0, 0.0, "brake"))
        plan = planner.plan(snap, lmap)
    assert plan is not None
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 4.6), gridspec_kw={"width_ratios": [1.4, 1]})
    occ = lmap.occupied()
    k = int(math.floor(pos[2] / cfg.voxel_m)) - int(lmap.origin[2])
    ij = np.argwhere(occ[:, :, k])
    cells = (ij + lmap.origin[:2] + 0.5) * cfg.voxel_m
    ax.scatter(cells[:, 1], cells[:, 0], s=4, c="0.3", marker="s", label="occupied (map slice)")
    table = plan.candidates
    level = table[N_CLIMBS // 2 :: N_CLIMBS]  # the level candidates
    cost = level[:, 4]
    finite = np.isfinite(cost)
    norm = plt.Normalize(np.min(cost[finite]), np.percentile(cost[finite], 90))
    cmap = plt.get_cmap("viridis_r")
    for yaw, _, free, hoped, c in level:
        d = np.array([math.cos(yaw), math.sin(yaw)])
        col = cmap(norm(c)) if math.isfinite(c) else "0.8"
        ax.plot([0, d[1] * free], [0, d[0] * free], color=col, lw=2)
        if hoped > free:
            ax.plot([d[1] * free, d[1] * hoped], [d[0] * free, d[0] * hoped], color=col, lw=1, ls=":")
    u = plan.direction_ned
    ax.annotate("", xy=(u[1] * plan.free_m, u[0] * plan.free_m), xytext=(0, 0),
                arrowprops=dict(arrowstyle="->", color="red", lw=2.5))
    ax.plot(goal[1], goal[0], "g*", ms=14, label="goal")
    ax.set_xlim(-5, 6)
    ax.set_ylim(-3, 9)
    ax.set_aspect("equal")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title("candidates: seen-free length (solid, colour = cost, dark = cheap),\nhoped-for (dotted), chosen (red)", fontsize=9)
    ax.legend(loc="lower left", fontsize=8)
    d = np.linspace(0.0, 8.0, 200)
    for t in (0.2, 0.5, 1.0):
        c2 = cfg.model_copy(update={"latency_s": t, "cruise_speed_m_s": 20.0})
        bx.plot(d, speed_law(d, c2), label=f"latency {t:g} s")
    bx.axhline(cfg.cruise_speed_m_s, color="0.5", ls="--", label="cruise 3 m/s")
    bx.set_xlabel("seen-free length ahead (m)")
    bx.set_ylabel("speed (m/s)")
    bx.set_title(f"speed law: v·t + v²/(2a) = d - margin  (a = {cfg.braking_accel_m_s2:g} m/s²)", fontsize=9)
    bx.legend(fontsize=8)
    bx.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    print(f"wrote {out}: {plan.reason}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
