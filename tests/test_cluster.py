"""Suites and the tuner on Ray (``companion sim --ray``, ``companion tune``).

The Ray tests start a Ray of 2 CPUs on this machine and shut it down in a ``finally``; none depends on
how fast the machine is (a tune is stopped by its own first finished trial, not by a clock).
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import signal
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from companion.cli import main
from companion.config import CompanionConfig, apply_patch
from companion.errors import ConfigError, InputError
from companion.sim.suite import SUITES, run_suite, run_suites, select_kinds
from companion.sim.tuning import (
    INVALID_SCORE,
    best_patch,
    best_row,
    ctl_set_command,
    fragment_toml,
    load_space_file,
    parse_setting,
    resolve_settings,
    with_settings,
    write_report,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

needs_ray = pytest.mark.skipif(
    importlib.util.find_spec("ray") is None or importlib.util.find_spec("optuna") is None,
    reason="Ray and Optuna are not installed (pip install 'companion[cluster]')",
)


@pytest.fixture
def ray_shutdown(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Whatever a test did with Ray, no Ray is left running after it, and nothing of its files: Ray
    keeps its sessions and locks in a folder of the test's own (short: Ray's socket paths live there)
    instead of /tmp/ray."""
    folder = tempfile.mkdtemp(prefix="ray-test-")
    monkeypatch.setenv("RAY_TMPDIR", folder)
    try:
        yield
    finally:
        import ray

        ray.shutdown()
        shutil.rmtree(folder, ignore_errors=True)


# --- settings, scores, fragment: no Ray ---------------------------------------------------------------


def test_a_setting_is_a_dotted_path_and_a_range() -> None:
    assert parse_setting("planner.cruise_speed_m_s=0.5:1.5") == ("planner.cruise_speed_m_s", 0.5, 1.5)
    for bad in ("planner.cruise_speed_m_s", "planner.cruise_speed_m_s=1.5", "x=a:b", "x=2:1", "x=nan:1"):
        with pytest.raises(InputError):
            parse_setting(bad)


def test_ranges_are_clipped_to_the_field_bounds_and_the_envelope() -> None:
    cfg = CompanionConfig()
    speed, weight, breakpoint_, resolution = resolve_settings(
        cfg,
        [
            ("planner.cruise_speed_m_s", 0.5, 9.0),  # envelope.max_horizontal_speed_m_s = 4
            ("controller.main_rules.R7.weight", 0.2, 3.0),  # a rule by its name; weight <= 1
            ("controller.input_terms.near.params_m.1", 1.8, 2.6),  # a breakpoint: no bounds of its own
            ("controller.output_resolution", 10, 500),  # an integer >= 21
        ],
    )
    assert (speed.low, speed.high, speed.start) == (0.5, cfg.envelope.max_horizontal_speed_m_s, cfg.planner.cruise_speed_m_s)
    assert (weight.low, weight.high, weight.start) == (0.2, 1.0, 0.5)
    assert (breakpoint_.low, breakpoint_.high, breakpoint_.start) == (1.8, 2.6, 2.25)
    assert (resolution.low, resolution.high, resolution.integer) == (21, 500, True)
    # A tighter envelope bounds the search tighter: the envelope of the config searched.
    tight = apply_patch(cfg, {"envelope": {"max_horizontal_speed_m_s": 1.0}, "planner": {"cruise_speed_m_s": 1.0}})
    (clipped,) = resolve_settings(tight, [("planner.cruise_speed_m_s", 0.5, 9.0)])
    assert clipped.high == 1.0


@pytest.mark.parametrize(
    ("path", "lo", "hi", "message"),
    [
        ("command.no_such_m", 0, 1, "not a setting here"),
        ("controller.main_rules.R99.weight", 0, 1, "no 'R99' here"),
        ("controller.preferred_yaw_side", 0, 1, "not a number"),
        ("envelope.max_horizontal_speed_m_s", 1, 3, "not searched"),
        ("planner.cruise_speed_m_s", 4.5, 5, "inside the safety envelope"),
        ("controller.main_rules.R7.weight", 2, 3, "outside the field's bounds"),
    ],
)
def test_a_setting_that_cannot_be_searched_is_refused(path: str, lo: float, hi: float, message: str) -> None:
    with pytest.raises(InputError, match=message):
        resolve_settings(CompanionConfig(), [(path, lo, hi)])


def test_a_candidate_is_validated_whole_before_it_flies() -> None:
    cfg = CompanionConfig()
    ok = with_settings(cfg, {"controller.main_rules.R7.weight": 0.8, "planner.cruise_speed_m_s": 1.1})
    assert ok.controller.main_rules[6].weight == 0.8 and ok.planner.cruise_speed_m_s == 1.1
    # "near" falling to 0 at 0.5 m, before it starts falling (0.75 m): not a membership function.
    with pytest.raises(ConfigError, match="non-decreasing"):
        with_settings(cfg, {"controller.input_terms.near.params_m.1": 0.5})


def test_the_space_file_reads_toml_and_yaml(tmp_path: Path) -> None:
    toml_file = tmp_path / "space.toml"
    toml_file.write_text(
        '"planner.cruise_speed_m_s" = [0.5, 1.5]\n[controller.main_rules.R7]\nweight = { low = 0.2, high = 1.0 }\n'
    )
    yaml_file = tmp_path / "space.yaml"
    yaml_file.write_text("planner.cruise_speed_m_s: [0.5, 1.5]\ncontroller.main_rules.R7.weight: {low: 0.2, high: 1.0}\n")
    want = [("planner.cruise_speed_m_s", 0.5, 1.5), ("controller.main_rules.R7.weight", 0.2, 1.0)]
    assert load_space_file(toml_file) == want
    assert load_space_file(yaml_file) == want
    (tmp_path / "bad.toml").write_text('"planner.cruise_speed_m_s" = 1.5\n')
    with pytest.raises(InputError, match=r"expected \[LOW, HIGH\]"):
        load_space_file(tmp_path / "bad.toml")


def test_the_best_settings_fragment_loads_with_the_config_models() -> None:
    cfg = CompanionConfig()
    values = {
        "planner.cruise_speed_m_s": 1.2,
        "controller.main_rules.R7.weight": 0.7,
        "controller.input_terms.near.params_m.1": 2.4,
    }
    patch = best_patch(cfg, values)
    # A value inside a list carries the list: a config's lists are replaced, not merged.
    assert set(patch) == {"planner.cruise_speed_m_s", "controller.main_rules", "controller.input_terms.near.params_m"}
    text = fragment_toml(patch, ["the best of 3 trials"])
    assert apply_patch(cfg, tomllib.loads(text)) == with_settings(cfg, values)
    from companion.service.client import parse_assignments

    line = ctl_set_command(patch)
    import shlex

    assert apply_patch(cfg, parse_assignments(shlex.split(line)[3:])) == with_settings(cfg, values)


def test_a_collision_ranks_a_candidate_below_every_one_without() -> None:
    from types import SimpleNamespace

    from companion.sim.scoring import Outcome
    from companion.sim.tuning import score_flights

    def flight(name: str, outcome: Outcome, time_s: float) -> Any:
        success = outcome in (Outcome.GOAL, Outcome.HELD)
        return SimpleNamespace(course=SimpleNamespace(name=name), outcome=outcome, success=success, time_s=time_s)

    slow = score_flights([flight("a-0", Outcome.GOAL, 40.0), flight("b-0", Outcome.TIMEOUT, 90.0)])
    assert (slow.success_pct, slow.goal_pct, slow.collisions, slow.mean_goal_time_s) == (50.0, 50.0, 0, 40.0)
    assert slow.score == pytest.approx(50.0 - 0.1 * 40.0) and slow.failed == "b-0: timeout"
    fast = score_flights([flight("a-0", Outcome.GOAL, 10.0), flight("b-0", Outcome.COLLISION, 5.0)])
    assert fast.score == -1.0 < slow.score
    faster = score_flights([flight("a-0", Outcome.GOAL, 20.0), flight("b-0", Outcome.GOAL, 20.0)])
    assert faster.score == pytest.approx(100.0 - 2.0) and faster.score > slow.score


def test_the_report_lists_every_trial_best_first(tmp_path: Path) -> None:
    (setting,) = resolve_settings(CompanionConfig(), [("planner.cruise_speed_m_s", 0.5, 1.5)])
    rows: list[dict[str, Any]] = [
        {"trial": 1, "planner.cruise_speed_m_s": 0.7, "score": 90.0, "success_pct": 100.0, "goal_pct": 100.0,
         "collisions": 0, "mean_goal_time_s": 100.0, "flights": 2, "problem": ""},
        {"trial": 2, "planner.cruise_speed_m_s": 1.5, "score": -1.0, "success_pct": 50.0, "goal_pct": 50.0,
         "collisions": 1, "mean_goal_time_s": 10.0, "flights": 2, "problem": ""},
        {"trial": 3, "planner.cruise_speed_m_s": 1.0, "score": INVALID_SCORE, "success_pct": 0.0, "goal_pct": 0.0,
         "collisions": 0, "mean_goal_time_s": 0.0, "flights": 0, "problem": "candidate: invalid config: ..."},
    ]
    files = write_report(rows, [setting], tmp_path, "a tune")
    assert {f.name for f in files} == {"trials.csv", "report.md", "settings.png", "progress.png"}
    report = (tmp_path / "report.md").read_text()
    assert report.index("| 1 (base)") < report.index("| 2 ") < report.index("| 3 ")
    assert "Not scored (refused by the config models, or failed)" in report
    assert best_row(rows) is rows[0]  # a collision never wins, however fast


def test_without_ray_the_suite_says_how_to_install_it(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ray" else real(name, *a))
    for argv in (["sim", "--suite", "quick", "--ray"], ["tune", "planner.cruise_speed_m_s=0.5:1", "--suite", "quick",
                                                       "--out", "x"]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert "ray not installed" in err and "pip install 'companion[cluster]'" in err and "\n" not in err


def test_a_suite_on_ray_does_not_need_the_tuners_search(monkeypatch: pytest.MonkeyPatch) -> None:
    """Optuna is the tuner's alone: without it a suite may still fly on Ray, and a tune says it is missing."""
    from companion.sim.cluster import SUITE_MODULES, require_ray

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "optuna" else real(name, *a))
    if real("ray") is not None and real("tqdm") is not None:
        require_ray(SUITE_MODULES)
    with pytest.raises(InputError, match="optuna not installed: pip install 'companion\\[cluster\\]'"):
        require_ray()


@needs_ray
@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["x=2:1"], "low 2 is above high 1"),
        (["planner.cruise_speed_m_s=4.5:5"], "inside the safety envelope"),
        ([], "name at least one setting"),
        (["planner.cruise_speed_m_s=0.5:1", "--trials", "0"], "--trials must be >= 1"),
        (["planner.cruise_speed_m_s=0.5:1", "--kinds", "maze"], "unknown course kind 'maze'"),
        (["planner.cruise_speed_m_s=0.5:1", "--resume"], "no tune to resume here"),
    ],
)
def test_tune_input_errors_are_one_line_and_exit_2(
    argv: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Each is refused before any Ray starts."""
    assert main(["tune", *argv, "--suite", "quick", "--out", str(tmp_path / "t")]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err


@needs_ray
def test_a_resume_that_searches_otherwise_names_what_differs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A tune moved to a machine whose 'auto' backend resolves otherwise (here: a config that names
    another matcher) would mix trials that do not compare: refused, in one line saying what differs."""
    out = tmp_path / "t"
    argv = ["tune", "planner.cruise_speed_m_s=0.5:1", "--suite", "quick", "--out", str(out)]
    here = tmp_path / "here.toml"
    here.write_text('[stereo]\nbackend = "opencv-sgbm"\n', encoding="utf-8")
    there = tmp_path / "there.toml"
    there.write_text('[stereo]\nbackend = "opencv-bm"\n', encoding="utf-8")
    from companion.cli.tune import _check_same_search
    from companion.config import load_config
    from companion.sim.cluster import TuneSpec
    from companion.sim.tuning import parse_setting, resolve_settings

    cfg = load_config(there)
    spec = TuneSpec(base=cfg, settings=resolve_settings(cfg, [parse_setting("planner.cruise_speed_m_s=0.5:1")]),
                    courses=tuple(SUITES["quick"]), trials=20)
    # The search kept beside an experiment, as a tune on the other machine wrote it.
    out.mkdir()
    _check_same_search(out / "search.json", spec, resume=False)
    (out / "experiment").mkdir()
    assert main([*argv, "--config", str(here), "--resume"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith('differs: base.stereo.backend: "opencv-bm" there, "opencv-sgbm" here'), err  # only that
    assert "\n" not in err


def test_ray_goes_with_a_suite(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sim", "--course", "doorway", "--ray"]) == 2
    assert "--ray goes with --suite" in capsys.readouterr().err


# --- on Ray --------------------------------------------------------------------------------------------


@needs_ray
@pytest.mark.slow
def test_a_suite_on_ray_gives_the_local_pools_verdicts(ray_shutdown: None, monkeypatch: pytest.MonkeyPatch) -> None:
    """Flights are deterministic: the quick suite gives the same results on Ray as on the local pool, and a
    flight that raises is reported with its course, the others still flown. ``--ray`` alone starts a Ray
    of its own even where the environment names another cluster (here one that is not there)."""
    from companion.sim.cluster import fly_suite, ray_session

    monkeypatch.setenv("RAY_ADDRESS", "127.0.0.1:9")
    cfg = CompanionConfig()
    courses = SUITES["quick"]
    pool = run_suite(cfg, courses, workers=2)
    seen: list[str] = []
    with ray_session(None, num_cpus=2):
        on_ray, failures = fly_suite(
            cfg, [*courses, ("maze", 0)], progress=lambda done, total, r: seen.append(r.course.name)
        )
    assert on_ray == pool
    assert [(r.outcome, r.time_s, r.min_clearance_m) for r in on_ray] == [
        (r.outcome, r.time_s, r.min_clearance_m) for r in pool
    ]
    assert sorted(seen) == sorted(r.course.name for r in pool)
    assert [(f.kind, f.seed) for f in failures] == [("maze", 0)]
    assert "unknown course 'maze'" in failures[0].line() and failures[0].line().startswith("maze-0: ")


def _kill_a_busy_flier() -> bool:
    """SIGKILL one process of this test's Ray (its environment names the test's ``RAY_TMPDIR``) flying a
    flight on an actor (its title is ``ray::_Flier.fly``); whether there was one."""
    mine = f"RAY_TMPDIR={os.environ['RAY_TMPDIR']}".encode()
    for pid in (int(p) for p in os.listdir("/proc") if p.isdigit()):
        try:
            title = Path(f"/proc/{pid}/cmdline").read_bytes()
            env = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0") if title.startswith(b"ray::_Flier.fly") else []
        except OSError:  # gone, or another user's
            continue
        if mine in env:
            os.kill(pid, signal.SIGKILL)
            return True
    return False


@needs_ray
@pytest.mark.slow
def test_a_flight_whose_process_dies_is_flown_again_on_a_new_actor(ray_shutdown: None) -> None:
    """An actor's process killed mid-flight (a node lost, the kernel's OOM killer) costs that flight one
    try: a new actor flies it, and every config's results are those of the local pool."""
    from companion.sim.cluster import fly_suites, ray_session

    base = CompanionConfig()
    cfgs = [base, base.model_copy(update={"sim": base.sim.model_copy(update={"realization": 1})})]
    courses = select_kinds(SUITES["quick"], "pitch")
    killed: list[int] = []

    def kill_once(j: int, done: int, total: int, result: Any) -> None:
        if not killed and _kill_a_busy_flier():
            killed.append(j)

    with ray_session(None, num_cpus=2):
        on_ray, failures = fly_suites(cfgs, courses, progress=kill_once)
    assert killed, "no flight was in the air to kill"
    assert failures == []
    assert on_ray == run_suites(cfgs, courses, workers=2)


@needs_ray
@pytest.mark.slow
def test_a_ray_started_here_flies_at_this_process_s_priority(ray_shutdown: None) -> None:
    """Ray's workers default to a niceness 15 above their driver's: beside any other work on the
    machine, the flights of a local Ray yielded to it, where the local pool's (at this process's
    priority) did not."""
    import ray

    from companion.sim.cluster import ray_session

    with ray_session(None, num_cpus=1):
        assert ray.get(ray.remote(lambda: os.nice(0)).remote()) == os.nice(0)


def _ctrl_c_after_first_trial() -> Any:
    """A Ray Tune callback that presses Ctrl-C (SIGINT to this process) when the experiment's first trial
    finishes; a resumed experiment, which already has a finished trial, is let run."""
    from ray.tune import Callback

    class CtrlC(Callback):
        def on_trial_complete(self, iteration: int, trials: list[Any], trial: Any, **info: Any) -> None:
            if not any(t is not trial and t.status == "TERMINATED" for t in trials):
                os.kill(os.getpid(), signal.SIGINT)

    return CtrlC()


@needs_ray
@pytest.mark.slow
def test_a_tune_stopped_by_ctrl_c_resumes_and_writes_its_best_settings(tmp_path: Path, ray_shutdown: None) -> None:
    from companion.sim.cluster import TuneSpec, run_tune

    cfg = CompanionConfig()
    settings = resolve_settings(cfg, [("planner.cruise_speed_m_s", 2.0, 3.5), ("controller.main_rules.R7.weight", 0.3, 1.0)])
    spec = TuneSpec(base=cfg, settings=settings, courses=(("pitch", 0),), trials=3, seed=1)
    storage = tmp_path / "tune"
    rows, complete = run_tune(spec, storage, num_cpus=2, verbose=0, callbacks=[_ctrl_c_after_first_trial()])
    assert not complete and 1 <= len(rows) < 3
    with pytest.raises(InputError, match="already here"):
        run_tune(spec, storage, num_cpus=2, verbose=0)
    rows, complete = run_tune(spec, storage, resume=True, num_cpus=2, verbose=0)
    assert complete
    assert [r["trial"] for r in rows] == [1, 2, 3]
    first = rows[0]
    assert (first["planner.cruise_speed_m_s"], first["controller.main_rules.R7.weight"]) == (3.0, 0.5)  # the base
    for r in rows:
        assert 2.0 <= r["planner.cruise_speed_m_s"] <= 3.5 and 0.3 <= r["controller.main_rules.R7.weight"] <= 1.0
        assert r["flights"] == 1 and r["problem"] == ""
    best = best_row(rows)
    assert best is not None and best["score"] >= first["score"]
    values = {s.path: best[s.path] for s in settings}
    text = fragment_toml(best_patch(cfg, values))
    assert apply_patch(cfg, tomllib.loads(text)) == with_settings(cfg, values)


def test_ray_is_imported_only_when_asked_for() -> None:
    import subprocess

    code = (
        "import sys; from companion.cli import build_parser; build_parser(); import companion.sim.suite, "
        "companion.sim.tuning; sys.exit(sorted(m for m in ('ray', 'optuna', 'tqdm') if m in sys.modules) != [])"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    assert subprocess.run([sys.executable, "-c", code], env=env, timeout=120).returncode == 0
