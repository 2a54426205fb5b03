"""``companion sim`` and ``companion demo`` from the command line."""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path

import cv2
import pytest

from companion.cli import main
from companion.config import CompanionConfig
from companion.sim.courses import make_course
from companion.sim.scoring import Outcome
from companion.sim.suite import realization_line, run_suite, run_suites, suite_rows, suite_table


def test_one_course_prints_the_verdict_and_draws_the_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    plot = tmp_path / "doorway.png"
    assert main(["sim", "--course", "doorway", "--seed", "3", "--plot", str(plot), "--side-view"]) == 0
    out = capsys.readouterr().out
    for key in ("outcome:", "min clearance:", "path length:", "time:", str(plot)):
        assert key in out
    image = cv2.imread(str(plot))
    assert image is not None and image.shape[0] > 500 and image.shape[1] > 700


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["sim", "--course", "maze"], "unknown course 'maze'"),
        (["sim", "--course", "doorway", "--seed", "-4"], "bad seed -4"),
        (["sim", "--suite", "huge"], "unknown suite 'huge'"),
        (["sim", "--suite", "quick", "--plot", "x.png"], "go with --course"),
        (["sim", "--suite", "quick", "--kinds", "maze"], "unknown course kind 'maze'"),
        (["sim", "--course", "doorway", "--plot", "/no/such/dir/x.png"], "no such directory"),
        (["sim", "--course", "doorway", "--plot", "plot.txt"], "must be an image"),
        (["sim", "--course", "doorway", "--config", "/no/such.toml"], "cannot read config"),
        (["sim", "--course", "head-on", "--start", "1,2,3"], "expected N,E,ALT,YAW"),
        (["sim", "--course", "head-on", "--start", "1,0,x,0"], "expected N,E,ALT,YAW"),
        (["sim", "--course", "head-on", "--start", "1,0,0,0"], "altitude must be above 0 m"),
        (["sim", "--course", "head-on", "--start", "5,0,1.5,0"], "from an obstacle in head-on-0"),
        (["sim", "--course", "head-on", "--start=-50,0,1.5,0"], "outside head-on-0's bounds"),
        (["sim", "--suite", "quick", "--start", "1,0,1.5,0"], "go with --course"),
        (["sim", "--suite", "quick", "--realizations", "0"], "--realizations must be >= 1"),
        (["sim", "--suite", "quick", "--trace", "x.csv"], "go with --course"),
        (["sim", "--course", "doorway", "--trace-dir", "d"], "--trace-dir goes with --suite"),
        (["sim", "--course", "doorway", "--trace", "/no/such/dir/x.csv"], "no such directory for the trace"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(argv: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err


def test_demo_writes_the_plot_and_overlays_and_prints_where(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out_dir = tmp_path / "demo"
    assert main(["demo", "--out", str(out_dir), "--verbose"]) == 0
    out = capsys.readouterr().out
    assert "outcome:       goal" in out
    assert str(out_dir.resolve()) in out
    names = sorted(p.name for p in out_dir.iterdir())
    assert "flight.png" in names and sum(n.startswith("overlay_") for n in names) >= 3
    # The default course shows the product: an escape under an overhead block (the controller steers
    # down), and still the goal.
    frames = re.search(r"frames:\s+\d+ \(clear (\d+), avoid (\d+), brake (\d+)\)", out)
    assert frames is not None and int(frames.group(2)) > 0, out
    assert "descending" in out and re.search(r"escape by [A-Z]+\d", out), out  # the words, and with --verbose the rule
    assert any(n.startswith("overlay_") and "_avoid" in n for n in names), names


def test_demo_default_output_is_companion_demo_in_the_working_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    # A short course keeps this quick; the default course is covered above.
    assert main(["demo", "--course", "pitch", "--seed", "0"]) == 0
    assert (tmp_path / "companion-demo" / "flight.png").is_file()
    assert str(tmp_path / "companion-demo") in capsys.readouterr().out
    assert os.getcwd() == str(tmp_path)


def test_suite_runner_and_table_in_process() -> None:
    results = run_suite(CompanionConfig(), [("pitch", 0), ("doorway", 1)], workers=1)
    assert [r.course.name for r in results] == ["pitch-0", "doorway-1"]
    rows = suite_rows(results)
    assert [r.group for r in rows] == ["doorway", "pitch", "all"]
    assert rows[-1].flights == 2
    table = suite_table(results)
    assert "success" in table and "worst clear m" in table and "all" in table
    assert results[0].log is None  # logs are dropped unless asked for
    goals = sum(r.outcome is Outcome.GOAL for r in results)
    assert realization_line(3, results) == f"realization 3: goal {goals} of 2 not dead ends, 0 collisions"
    held_end = dataclasses.replace(results[0], course=make_course("deadend", 0), outcome=Outcome.HELD)
    assert realization_line(0, [held_end, results[1]]).endswith("of 1 not dead ends, 1 of 1 dead ends held, 0 collisions")


@pytest.mark.slow
def test_quick_suite_over_two_workers(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sim", "--suite", "quick", "--workers", "2"]) == 0
    out = capsys.readouterr().out
    assert "[ 16/16]" in out and "collisions" in out


@pytest.mark.slow
def test_a_suite_over_two_realizations_scores_them_together_and_one_by_one(capsys: pytest.CaptureFixture[str]) -> None:
    """--realizations 2: every course flown under sim.realization 0 and 1, one table for all, a line each."""
    assert main(["sim", "--suite", "quick", "--kinds", "pitch", "--realizations", "2", "--workers", "2"]) == 0
    out = capsys.readouterr().out
    assert "4 flights, realizations 0-1" in out
    assert "r0 [  2/2] pitch-" in out and "r1 [  2/2] pitch-" in out
    all_row = next(line for line in out.splitlines() if line.startswith("all"))
    assert all_row.split()[1] == "4"
    for r in (0, 1):
        assert f"realization {r}: goal " in out
    assert "of 2 not dead ends, 0 collisions" in out


@pytest.mark.slow
def test_draws_flown_on_one_set_of_workers_give_what_each_gives_alone() -> None:
    """Several configs (noise draws) share one set of workers; each flight's result is the one its own
    config gives flown alone, and progress counts each config's flights apart."""
    base = CompanionConfig()
    draws = [base.model_copy(update={"sim": base.sim.model_copy(update={"realization": r})}) for r in (0, 1)]
    seen: list[tuple[int, int, int, str]] = []
    together = run_suites(draws, [("pitch", 0)], workers=2,
                          progress=lambda j, done, total, r: seen.append((j, done, total, r.course.name)))
    alone = [run_suite(d, [("pitch", 0)], workers=1) for d in draws]
    assert together == alone
    assert sorted(seen) == [(0, 1, 1, "pitch-0"), (1, 1, 1, "pitch-0")]


def test_start_replays_a_course_from_another_pose(capsys: pytest.CaptureFixture[str]) -> None:
    """--start: past head-on's box (its face 4.7 m north), facing the goal line 3 m on, the flight
    begins there and reaches the goal at once; the course and its goal are unchanged."""
    assert main(["sim", "--course", "head-on", "--start", "6,0,1.5,0"]) == 0
    out = capsys.readouterr().out
    assert "outcome:       goal (success)" in out
    path = float(re.search(r"path length:\s+([\d.]+) m", out).group(1))
    assert path < 3.5  # from 6 m to the goal line at 8 m, not from the start 5 m before the box


def test_started_at_keeps_the_goal_and_sets_the_heading() -> None:
    import math

    from companion.core.pose import Pose
    from companion.sim.courses import make_course

    course = make_course("office", 3)
    moved = course.started_at(Pose.at(0.86, 1.54, 1.76, math.radians(-5.6)), 0.25)
    assert moved.start.position_ned_m == pytest.approx((0.86, 1.54, -1.76))
    assert math.degrees(moved.start.yaw_rad) == pytest.approx(-5.6)
    assert moved.goal_north_m == course.goal_north_m and moved.goal_east_m == course.goal_east_m
    assert moved.scene is course.scene
