"""Many seeded flights, in worker processes, and the table that scores them.

A *suite* is a list of ``(kind, seed)`` courses (:data:`SUITES`); :func:`run_suite` flies each with
one configuration (:func:`run_suites` with several, e.g. one per noise draw), over ``workers``
processes (each with its own texture bank and one OpenCV thread, so a flight's result does not depend
on how many workers ran it), and :func:`suite_table` summarises the results per course kind and
overall.
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import queue
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.config import CompanionConfig, parse_config
from companion.errors import InputError
from companion.sim.courses import COURSE_KINDS
from companion.sim.loop import FlightResult
from companion.sim.scoring import Outcome

#: Named suites: ``standard`` = 9 seeds of each kind of :data:`COURSE_KINDS` (72 flights with
#: ``office`` and ``detour``); ``quick`` = 2 of each (16).
SUITES: dict[str, tuple[tuple[str, int], ...]] = {
    "standard": tuple((kind, seed) for seed in range(9) for kind in COURSE_KINDS),
    "quick": tuple((kind, seed) for seed in range(2) for kind in COURSE_KINDS),
}


def suite_courses(name: str) -> tuple[tuple[str, int], ...]:
    """The ``(kind, seed)`` list of suite ``name``. Raises InputError for an unknown name."""
    if name not in SUITES:
        raise InputError(f"unknown suite {name!r}; suites are {', '.join(SUITES)}")
    return SUITES[name]


def select_kinds(courses: Sequence[tuple[str, int]], kinds: str) -> tuple[tuple[str, int], ...]:
    """The courses of ``courses`` whose kind is one of ``kinds`` (comma-separated names).

    Raises:
        InputError: a name that is not a course kind, or no course left.
    """
    wanted = [k.strip() for k in kinds.split(",") if k.strip()]
    unknown = [k for k in wanted if k not in COURSE_KINDS]
    if unknown:
        raise InputError(f"unknown course kind {unknown[0]!r}; kinds are {', '.join(COURSE_KINDS)}")
    picked = tuple(c for c in courses if c[0] in wanted)
    if not picked:
        raise InputError(f"the suite has no course of kind {', '.join(wanted)}")
    return picked


def single_thread_config(cfg: CompanionConfig) -> CompanionConfig:
    """``cfg`` with one OpenCV thread (workers share the cores; results do not depend on it)."""
    return cfg.model_copy(update={"stereo": cfg.stereo.model_copy(update={"cpu_threads": 1})})


def fly_one(kind: str, seed: int, cfg: CompanionConfig, bank: Any, keep_logs: bool) -> FlightResult:
    """Fly course ``kind``-``seed`` with ``cfg`` and the texture bank ``bank``; without ``keep_logs`` the
    result drops its per-step logs."""
    from companion.sim.courses import make_course
    from companion.sim.loop import fly

    result = fly(make_course(kind, seed), cfg, textures=bank)
    if not keep_logs:
        result = dataclasses.replace(result, log=None, frame_log=None)
    return result


def _worker(cfg_data: list[dict[str, Any]], keep_logs: bool, tasks: Any, results: Any) -> None:
    """Worker process: fly tasks ``(draw, index, kind, seed)`` with ``cfg_data[draw]`` until a ``None``
    arrives; each config is parsed once, on its first task."""
    from companion.sim.camera import make_texture_bank

    cfgs: dict[int, CompanionConfig] = {}
    bank = make_texture_bank()
    while True:
        task = tasks.get()
        if task is None:
            return
        draw, index, kind, seed = task
        try:
            if draw not in cfgs:
                cfgs[draw] = parse_config(cfg_data[draw], source="suite")
            results.put((draw, index, fly_one(kind, seed, cfgs[draw], bank, keep_logs), None))
        except Exception as err:  # reported to the parent, which raises it
            results.put((draw, index, None, f"{kind}-{seed}: {type(err).__name__}: {err}"))


def run_suite(
    cfg: CompanionConfig,
    courses: Sequence[tuple[str, int]],
    *,
    workers: int = 2,
    keep_logs: bool = False,
    progress: Callable[[int, int, FlightResult], None] | None = None,
) -> list[FlightResult]:
    """Fly every ``(kind, seed)`` of ``courses`` with ``cfg``; results in the order of ``courses``.

    Args:
        cfg: the configuration (every flight uses one OpenCV thread, see :func:`single_thread_config`).
        courses: what to fly.
        workers: processes (1 = in this process).
        keep_logs: keep the per-step logs in the results (memory; default drop them).
        progress: called after each flight with (done, total, result).

    Raises:
        RuntimeError: a flight raised in a worker (the message names the course).
    """
    on_flight = None if progress is None else (lambda _draw, done, total, result: progress(done, total, result))
    return run_suites([cfg], courses, workers=workers, keep_logs=keep_logs, progress=on_flight)[0]


def run_suites(
    cfgs: Sequence[CompanionConfig],
    courses: Sequence[tuple[str, int]],
    *,
    workers: int = 2,
    keep_logs: bool = False,
    progress: Callable[[int, int, int, FlightResult], None] | None = None,
) -> list[list[FlightResult]]:
    """Fly every ``(kind, seed)`` of ``courses`` with each config of ``cfgs`` (e.g. one per noise draw,
    ``sim.realization``) on one set of workers: the workers start once for all, and the next config's
    flights fill the cores while the last ones of a config still fly.

    Args:
        cfgs: the configurations (every flight uses one OpenCV thread, see :func:`single_thread_config`).
        courses: what to fly with each.
        workers: processes (1 = in this process).
        keep_logs: keep the per-step logs in the results (memory; default drop them).
        progress: called after each flight with (config's index in ``cfgs``, flights of that config
            done, its total, result).

    Returns:
        One list per config, in the order of ``cfgs``, of its results in the order of ``courses``.

    Raises:
        RuntimeError: a flight raised in a worker (the message names the course).
    """
    cfgs = [single_thread_config(c) for c in cfgs]
    total = len(courses)
    out: list[list[FlightResult | None]] = [[None] * total for _ in cfgs]
    done = [0] * len(cfgs)
    if workers <= 1 or total * len(cfgs) <= 1:
        from companion.core.disparity.opencv import set_cv_threads
        from companion.sim.camera import make_texture_bank

        bank = make_texture_bank()
        try:
            for j, cfg in enumerate(cfgs):
                for i, (kind, seed) in enumerate(courses):
                    out[j][i] = result = fly_one(kind, seed, cfg, bank, keep_logs)
                    done[j] += 1
                    if progress is not None:
                        progress(j, done[j], total, result)
        finally:
            set_cv_threads(0)
        return [[r for r in draw if r is not None] for draw in out]

    # spawn: a clean interpreter per worker (no forked OpenCV thread pools).
    ctx = mp.get_context("spawn")
    tasks: Any = ctx.Queue()
    results: Any = ctx.Queue()
    for j in range(len(cfgs)):
        for i, (kind, seed) in enumerate(courses):
            tasks.put((j, i, kind, int(seed)))
    n = min(workers, total * len(cfgs))
    for _ in range(n):
        tasks.put(None)
    data = [c.model_dump(mode="json") for c in cfgs]
    procs = [ctx.Process(target=_worker, args=(data, keep_logs, tasks, results), daemon=True) for _ in range(n)]
    for p in procs:
        p.start()
    error: str | None = None
    try:
        while sum(done) < total * len(cfgs):
            try:
                j, index, result, err = results.get(timeout=1.0)
            except queue.Empty:
                if not any(p.is_alive() for p in procs):
                    raise RuntimeError("suite workers exited before finishing the suite") from None
                continue
            done[j] += 1
            if err is not None:
                error = error or err
                continue
            out[j][index] = result
            if progress is not None:
                progress(j, done[j], total, result)
    finally:
        for p in procs:
            p.join(timeout=5.0)
            if p.is_alive():
                p.terminate()
    if error is not None:
        raise RuntimeError(f"a flight failed: {error}")
    return [[r for r in draw if r is not None] for draw in out]


@dataclass(frozen=True)
class SuiteRow:
    """Scores of one group of flights.

    Attributes:
        group: a course kind or ``all``.
        flights: number of flights.
        success_pct: goal reached or held safely (where that counts), percent.
        goal_pct: goal reached, percent.
        held: flights that ended held safely.
        collisions: flights that ended in a collision.
        other_failures: timeouts and out-of-bounds.
        mean_clearance_m: mean over flights of the minimum clearance, metres.
        worst_clearance_m: the smallest minimum clearance, metres.
        mean_time_s: mean flight time, seconds.
    """

    group: str
    flights: int
    success_pct: float
    goal_pct: float
    held: int
    collisions: int
    other_failures: int
    mean_clearance_m: float
    worst_clearance_m: float
    mean_time_s: float


def _row(group: str, rs: Sequence[FlightResult]) -> SuiteRow:
    n = len(rs)
    clear = np.array([r.min_clearance_m for r in rs])
    return SuiteRow(
        group=group,
        flights=n,
        success_pct=100.0 * sum(r.success for r in rs) / n,
        goal_pct=100.0 * sum(r.outcome is Outcome.GOAL for r in rs) / n,
        held=sum(r.outcome is Outcome.HELD for r in rs),
        collisions=sum(r.outcome is Outcome.COLLISION for r in rs),
        other_failures=sum(r.outcome in (Outcome.TIMEOUT, Outcome.OUT_OF_BOUNDS) for r in rs),
        mean_clearance_m=float(clear.mean()),
        worst_clearance_m=float(clear.min()),
        mean_time_s=float(np.mean([r.time_s for r in rs])),
    )


def suite_rows(results: Sequence[FlightResult]) -> list[SuiteRow]:
    """One row per course kind present (in :data:`COURSE_KINDS` order), then ``all``."""
    kinds = [k for k in COURSE_KINDS if any(r.course.kind == k for r in results)]
    kinds += sorted({r.course.kind for r in results} - set(kinds))
    rows = [_row(k, [r for r in results if r.course.kind == k]) for k in kinds]
    if results:
        rows.append(_row("all", results))
    return rows


def realization_line(realization: int, results: Sequence[FlightResult]) -> str:
    """One line for the flights of one ``sim.realization``: goals among the flights whose course is
    not a dead end (where holding is the right answer), held dead ends, collisions."""
    live = [r for r in results if r.course.kind != "deadend"]
    goals = sum(r.outcome is Outcome.GOAL for r in live)
    dead = [r for r in results if r.course.kind == "deadend"]
    held = sum(r.outcome is Outcome.HELD for r in dead)
    collisions = sum(r.outcome is Outcome.COLLISION for r in results)
    held_part = f"{held} of {len(dead)} dead ends held, " if dead else ""
    return f"realization {realization}: goal {goals} of {len(live)} not dead ends, {held_part}{collisions} collisions"


def suite_table(results: Sequence[FlightResult]) -> str:
    """The suite's scores as a fixed-width text table."""
    from companion.report import format_table

    header = ["course", "flights", "success", "goal", "held", "collisions", "timeout/out",
              "mean clear m", "worst clear m", "mean time s"]
    body = [
        [r.group, r.flights, f"{r.success_pct:.0f}%", f"{r.goal_pct:.0f}%", r.held, r.collisions,
         r.other_failures, f"{r.mean_clearance_m:.2f}", f"{r.worst_clearance_m:.2f}", f"{r.mean_time_s:.1f}"]
        for r in suite_rows(results)
    ]
    return format_table(body, header)
