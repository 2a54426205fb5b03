"""A flight's trace: one CSV row per setpoint, joined to the frame whose decision was applied, with
what the local planner was doing; ``companion sim --trace`` and ``--trace-dir`` write it."""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from companion.cli import main
from companion.config import CompanionConfig, parse_config
from companion.sim.courses import head_on_course, make_course
from companion.sim.loop import FlightResult, fly
from companion.sim.trace import COLUMNS, trace_rows, write_trace

BM = parse_config({"stereo": {"backend": "opencv-bm"}})


@pytest.fixture(scope="module")
def detour_flight() -> FlightResult:
    # detour-2 with StereoBM: the wall across the course, the way round it through its opening.
    return fly(make_course("detour", 2), BM)


def _read(path: Path) -> list[dict[str, str]]:
    with path.open(newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def test_every_setpoint_is_a_row_joined_to_the_frame_its_decision_came_from(detour_flight: FlightResult, tmp_path: Path) -> None:
    log, frames = detour_flight.log, detour_flight.frame_log
    assert log is not None and frames is not None
    path = tmp_path / "t.csv"
    assert write_trace(detour_flight, path) == log.t_s.shape[0]
    rows = _read(path)
    assert tuple(rows[0]) == COLUMNS and len(rows) == log.t_s.shape[0]
    # Before the first decision: no frame; afterwards every row names a frame the frame log holds,
    # no later than the row, and carries that frame's depths and reason.
    assert rows[0]["frame_t_s"] == "" and rows[0]["decision"] == ""
    joined = [r for r in rows if r["frame_t_s"] != ""]
    assert len(joined) > 0.9 * len(rows)
    for r in joined[:: max(1, len(joined) // 50)]:
        j = int(np.argmin(np.abs(frames.t_s - float(r["frame_t_s"]))))
        assert abs(frames.t_s[j] - float(r["frame_t_s"])) < 1e-3 <= float(r["t_s"]) - frames.t_s[j] + 1e-3
        assert r["decision"] == frames.reason[j]
        for name, depth in zip(COLUMNS[16:25], frames.region_depths_m[j]):
            assert (r[name] == "") if not math.isfinite(depth) else float(r[name]) == pytest.approx(depth, abs=1e-3)
    # Units: the position and heading are the log's, in metres and degrees.
    k = len(rows) // 2
    assert float(rows[k]["north_m"]) == pytest.approx(log.position_ned_m[k, 0], abs=1e-3)
    assert float(rows[k]["altitude_m"]) == pytest.approx(-log.position_ned_m[k, 2], abs=1e-3)
    assert float(rows[k]["heading_deg"]) == pytest.approx(math.degrees(log.attitude_rad[k, 2]), abs=0.1)


def test_the_planner_column_tells_the_local_planner_s_modes(detour_flight: FlightResult) -> None:
    assert detour_flight.outcome.value == "goal" and detour_flight.detours >= 1, detour_flight.reason
    rows = trace_rows(detour_flight)
    planner = [r[-1] for r in rows]
    kinds = [r[7] for r in rows]
    modes = [p.split(":", 1)[0] for p in planner]
    # Before the first frame nothing ahead is seen free: the first ticks may look round (detour).
    assert {"cruise", "detour"} <= set(modes) <= {"cruise", "avoid", "detour", "hold"}, set(modes)
    assert all(": " in p for p in planner)  # each names the way it chose, or why it holds
    # While the planner is in its detour mode the row says so (kind "detour"; "none" before the first frame).
    assert {k for m, k in zip(modes, kinds) if m == "detour"} <= {"detour", "stale", "none"}


def test_a_flight_without_logs_cannot_be_traced(detour_flight: FlightResult) -> None:
    bare = dataclasses.replace(detour_flight, log=None, frame_log=None)
    with pytest.raises(ValueError, match="detour-2: the flight carries no log"):
        trace_rows(bare)


def test_without_a_frame_log_the_frame_columns_are_empty(detour_flight: FlightResult) -> None:
    # A SITL flight's log has no frame log (and NaN frame times).
    rows = trace_rows(dataclasses.replace(detour_flight, frame_log=None))
    assert all(r[15] == "" and r[-2] == "" for r in rows)


def test_a_hold_is_in_the_planner_column() -> None:
    result = fly(make_course("deadend", 1), CompanionConfig())
    assert result.outcome.value == "held", result.reason
    planner = [r[-1] for r in trace_rows(result)]
    # The rule stack writes "held: reason", the local planner (the default) its mode, "hold: reason".
    held = [p for p in planner if p.startswith(("held: ", "hold: "))]
    assert held and result.hold_reason in held[-1]


def test_sim_trace_writes_the_csv_and_says_where(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "head-on.csv"
    assert main(["sim", "--course", "head-on", "--start", "6,0,1.5,0", "--trace", str(out)]) == 0
    text = capsys.readouterr().out
    rows = _read(out)
    assert f"trace:         {out} ({len(rows)} rows)" in text
    assert rows and float(rows[-1]["north_m"]) >= 8.0  # the goal line of head-on lies at 8 m


def test_a_suite_writes_a_trace_and_a_plot_for_each_failed_flight_only(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from companion.sim import courses as course_module

    # Two flights; the second is made to fail by a time limit it cannot meet.
    def courses(name: str) -> list[tuple[str, int]]:  # noqa: ARG001
        return [("pitch", 0), ("doorway", 1)]

    real = course_module.make_course

    def short(kind: str, seed: int):
        c = real(kind, seed)
        return dataclasses.replace(c, time_limit_s=2.0) if kind == "doorway" else c

    monkeypatch.setattr(course_module, "make_course", short)
    monkeypatch.setattr("companion.sim.suite.suite_courses", courses)
    out = tmp_path / "misses"
    assert main(["sim", "--suite", "quick", "--workers", "1", "--trace-dir", str(out)]) == 0
    text = capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["doorway-1.csv", "doorway-1.png"]
    assert f"(trace: {out / 'doorway-1'}.csv)" in text
    assert float(_read(out / "doorway-1.csv")[-1]["t_s"]) == pytest.approx(2.0, abs=0.06)


def test_a_trace_dir_that_is_a_file_is_an_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["sim", "--suite", "quick", "--kinds", "pitch", "--trace-dir", str(f)]) == 2
    assert "cannot make the trace directory" in capsys.readouterr().err


def test_the_sitl_log_names_the_planner_s_mode_and_the_hold() -> None:
    from companion.sitl.flight import _planner_text

    assert _planner_text("engaged", {"planner": {"mode": "detour", "reason": "round the left"}}) == "detour: round the left"
    assert _planner_text("engaged", {"planner": None}) == ""
    assert _planner_text("engaged", {}) == ""
    assert _planner_text("paused", {"reason": "dead end: no direction"}) == "held: dead end: no direction"


def test_head_on_log_has_the_new_columns_aligned() -> None:
    r = fly(head_on_course(seed=1, box_north_m=4.0, box_width_m=0.6), CompanionConfig())
    assert r.log is not None
    n = r.log.t_s.shape[0]
    assert r.log.frame_t_s.shape == (n,) and len(r.log.planner) == n
    assert math.isnan(r.log.frame_t_s[0]) and np.all(np.diff(r.log.frame_t_s[~np.isnan(r.log.frame_t_s)]) >= 0)
