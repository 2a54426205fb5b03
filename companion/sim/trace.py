"""A flight's trace as CSV: one row per setpoint, what the vehicle did and why.

The plot (:mod:`companion.sim.plot`) shows where a flight went; the trace says why, step by step: the
pose and velocity, what drove the setpoint and the setpoint itself, the true clearance, the nine
region depths and the controller's reason of the frame whose decision was applied, and what the
local planner was doing (its mode and reason: cruise, avoid, detour, hold).
``companion sim --course K --trace OUT.csv`` writes one for a flight, ``companion sim --suite S
--trace-dir DIR`` one (and a plot) for every flight that failed; a spreadsheet, pandas or ``grep``
reads it.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from companion.core.types import REGION_NAMES
from companion.sim.loop import FlightResult, LogKind

#: The columns, in order, with their units in their names.
COLUMNS: tuple[str, ...] = (
    "t_s",
    "north_m",
    "east_m",
    "altitude_m",
    "heading_deg",
    "speed_m_s",
    "velocity_bearing_deg",
    "kind",
    "decision_yaw",
    "decision_pitch",
    "sp_forward_m_s",
    "sp_right_m_s",
    "sp_down_m_s",
    "sp_yaw_rate_deg_s",
    "clearance_m",
    "frame_t_s",
    *(f"depth_{name}_m" for name in REGION_NAMES),
    "decision",
    "planner",
)


def trace_rows(result: FlightResult) -> list[list[object]]:
    """The trace of ``result`` (which must carry its logs), one list per setpoint in :data:`COLUMNS`
    order: numbers rounded to the millimetre (mm/s, 0.001 of the decision's outputs, 0.1° and
    0.1 deg/s for angles and the yaw rate), angles in degrees from north (clockwise), the speed and
    its bearing those of the velocity the vehicle reports (its autopilot tracks it; a simulated drift
    moves the position besides), the region depths in metres with "" for unknown, the frame columns ""
    before the first frame or without a frame log (a SITL flight).

    Raises:
        ValueError: the result was flown without logs (``run_suite(keep_logs=False)``).
    """
    log, frames = result.log, result.frame_log
    if log is None:
        raise ValueError(f"{result.course.name}: the flight carries no log to trace")
    rows: list[list[object]] = []
    for i in range(log.t_s.shape[0]):
        n, e, d = (float(x) for x in log.position_ned_m[i])
        vn, ve = float(log.velocity_ned_m_s[i, 0]), float(log.velocity_ned_m_s[i, 1])
        speed = math.hypot(vn, ve)
        sp = log.setpoint[i]
        row: list[object] = [
            round(float(log.t_s[i]), 3),
            round(n, 3),
            round(e, 3),
            round(-d, 3),
            round(math.degrees(float(log.attitude_rad[i, 2])), 1),
            round(speed, 3),
            round(math.degrees(math.atan2(ve, vn)), 1) if speed > 1e-3 else "",
            LogKind(int(log.kind[i])).name.lower(),
            round(float(log.decision_yaw[i]), 3),
            round(float(log.decision_pitch[i]), 3),
            *(round(float(x), 3) for x in sp[:3]),
            round(float(sp[3]), 1),
            round(float(log.clearance_m[i]), 3),
        ]
        j = _frame_row(frames.t_s if frames is not None else None, float(log.frame_t_s[i]))
        if j is None or frames is None:
            row += ["", *([""] * len(REGION_NAMES)), ""]
        else:
            row.append(round(float(frames.t_s[j]), 3))
            row += [round(float(x), 3) if math.isfinite(x) else "" for x in frames.region_depths_m[j]]
            row.append(frames.reason[j])
        row.append(log.planner[i])
        rows.append(row)
    return rows


def _frame_row(frame_t_s: np.ndarray | None, t_s: float) -> int | None:
    """The index of the frame captured at ``t_s`` (seconds) in the frame log's times, None when
    there is none (NaN, no frame log, or a time not in it)."""
    if frame_t_s is None or not math.isfinite(t_s) or frame_t_s.size == 0:
        return None
    j = int(np.searchsorted(frame_t_s, t_s))
    return j if j < frame_t_s.size and frame_t_s[j] == t_s else None


def write_trace(result: FlightResult, path: Path) -> int:
    """Write the trace of ``result`` to ``path`` as CSV with a header row; returns the rows written
    (without the header).

    Raises:
        ValueError: the result carries no log.
        OSError: the file cannot be written.
    """
    rows = trace_rows(result)
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        w.writerows(rows)
    return len(rows)
