"""Suites and the tuner on Ray: one machine's cores or a cluster's (``companion sim --ray``, ``companion tune``).

Ray is an optional extra (``pip install 'companion[cluster]'``: ``ray[tune]``, ``optuna``, ``tqdm``); this
module is imported only when a command asks for Ray, and :func:`require_ray` turns its absence into one
line that says how to install it.

* :func:`fly_suites` flies suites' courses on long-lived Ray actors (one CPU each, each with its texture
  bank, as a local pool's worker), the results streamed to a callback as flights finish, a flight that
  fails retried once (on any node) and then reported with its course. A flight's result does not depend
  on where it flew: every flight uses one OpenCV thread, as in :func:`companion.sim.suite.run_suite`.
* :func:`run_tune` searches settings with Optuna (:class:`ray.tune.search.optuna.OptunaSearch`) through
  Ray Tune, each trial a candidate config validated whole (:mod:`companion.sim.tuning`) and flown on the
  suite's courses; the experiment lives under a storage folder and a killed or interrupted run resumes
  from it.

``address``: None starts a Ray for the call on this machine and shuts it down after; ``"auto"`` joins
the cluster this machine belongs to (``ray start``); ``"ray://host:10001"`` a remote cluster's client
server.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.util
import logging
import re
import sys
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.config import CompanionConfig, parse_config
from companion.errors import InputError
from companion.sim.loop import FlightResult
from companion.sim.suite import single_thread_config
from companion.sim.tuning import Setting, TrialScore, score_flights, with_settings

log = logging.getLogger(__name__)

#: How to get what ``--ray`` and ``companion tune`` need.
INSTALL_HINT = "pip install 'companion[cluster]' (ray[tune], optuna, tqdm)"

#: What a suite on Ray imports; a tune imports Optuna too.
SUITE_MODULES: tuple[str, ...] = ("ray", "tqdm")
TUNE_MODULES: tuple[str, ...] = (*SUITE_MODULES, "optuna")

#: The experiment's folder under a tune's storage (``--out``).
EXPERIMENT_DIR = "experiment"

#: How often a flight is tried again after it raised (on any node) before it is reported.
FLIGHT_RETRIES = 1


def missing_modules(modules: Sequence[str] = TUNE_MODULES) -> list[str]:
    """Those of ``modules`` that cannot be imported (looked up, not imported)."""
    return [m for m in modules if importlib.util.find_spec(m) is None]


def require_ray(modules: Sequence[str] = TUNE_MODULES) -> None:
    """Raise :class:`InputError` naming what of ``modules`` is missing and how to install it."""
    missing = missing_modules(modules)
    if missing:
        raise InputError(f"{', '.join(missing)} not installed: {INSTALL_HINT}")


@contextlib.contextmanager
def ray_session(address: str | None, num_cpus: int | None = None) -> Iterator[None]:
    """Ray connected for the ``with`` block, shut down after (whatever happened inside).

    Args:
        address: None = a Ray started here for the block; ``auto`` or ``ray://host:port`` = an existing
            cluster (left running; only this process disconnects).
        num_cpus: the CPUs a Ray started here offers (default: all of this machine's); ignored with an
            address (a cluster's CPUs are its nodes').

    Raises:
        InputError: Ray is missing, or the cluster at ``address`` cannot be reached.
    """
    require_ray(SUITE_MODULES)
    import ray

    kwargs: dict[str, Any] = {"include_dashboard": False, "logging_level": logging.WARNING}
    if address is None:
        # "local": a Ray of its own even where `ray start` left one running (or $RAY_ADDRESS names
        # one): Ray's default would join that one, and refuse num_cpus there.
        kwargs["address"] = "local"
        if num_cpus is not None:
            kwargs["num_cpus"] = num_cpus
        # Flights at the priority the local pool's run at: Ray's workers default to niceness 15, and
        # on a machine with other work they yield to all of it (beside one busy process, the flights
        # of a local Ray got a quarter of the CPU the pool's got). A cluster keeps its own setting.
        kwargs["_system_config"] = {"worker_niceness": 0}
    else:
        kwargs["address"] = address
    try:
        ray.init(**kwargs)
    except (ConnectionError, ValueError, RuntimeError) as err:
        ray.shutdown()
        where = address or "this machine"
        raise InputError(f"cannot start or reach Ray at {where}: {err}") from None
    try:
        yield
    finally:
        ray.shutdown()


@dataclass(frozen=True)
class FlightFailure:
    """A flight that raised on every try.

    Attributes:
        kind, seed: the course.
        error: the last try's exception, one line (type and message).
    """

    kind: str
    seed: int
    error: str

    def line(self) -> str:
        """``kind-seed: error``."""
        return f"{self.kind}-{self.seed}: {self.error}"


class _Flier:
    """A flight actor: one CPU, its texture bank built and the suites' configs (``cfg_data``, one JSON
    dict each) parsed once, as a local pool's worker does (a task of its own per flight paid both, and
    Ray's start of a worker, for every flight)."""

    def __init__(self, cfg_data: list[dict[str, Any]]) -> None:
        from companion.sim.camera import make_texture_bank

        self._bank = make_texture_bank()
        self._cfgs = [parse_config(d, source="suite") for d in cfg_data]

    def fly(self, draw: int, kind: str, seed: int, keep_logs: bool) -> FlightResult:
        """Fly ``kind``-``seed`` with the config of suite ``draw``."""
        from companion.sim.suite import fly_one

        return fly_one(kind, seed, self._cfgs[draw], self._bank, keep_logs)


def _one_line(err: BaseException) -> str:
    cause = getattr(err, "cause", None)  # a RayTaskError carries the flight's own exception
    err = cause if isinstance(cause, BaseException) else err
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[-1] if text else ''}".rstrip(": ")


def fly_suite(
    cfg: CompanionConfig,
    courses: Sequence[tuple[str, int]],
    *,
    keep_logs: bool = False,
    progress: Callable[[int, int, FlightResult], None] | None = None,
    failed: Callable[[int, int, FlightFailure], None] | None = None,
) -> tuple[list[FlightResult], list[FlightFailure]]:
    """One suite on the Ray this process is connected to (:func:`fly_suites` with one config).

    Returns:
        The results of the flights that finished, in the order of ``courses``, and the flights that
        raised on every try (each tried ``1 + FLIGHT_RETRIES`` times), in the order of ``courses``.
    """
    results, failures = fly_suites(
        [cfg],
        courses,
        keep_logs=keep_logs,
        progress=None if progress is None else (lambda _j, done, total, r: progress(done, total, r)),
        failed=None if failed is None else (lambda _j, done, total, f: failed(done, total, f)),
    )
    return results[0], failures


def fly_suites(
    cfgs: Sequence[CompanionConfig],
    courses: Sequence[tuple[str, int]],
    *,
    keep_logs: bool = False,
    progress: Callable[[int, int, int, FlightResult], None] | None = None,
    failed: Callable[[int, int, int, FlightFailure], None] | None = None,
) -> tuple[list[list[FlightResult]], list[FlightFailure]]:
    """Fly every ``(kind, seed)`` of ``courses`` with each config of ``cfgs`` on the Ray this process is
    connected to (inside a :func:`ray_session`), as the local pool does (:func:`companion.sim.suite.run_suites`).

    The flights run on long-lived actors, one per CPU Ray has free (at most one per flight), fed from
    one queue: the next config's flights fill the CPUs while the last ones of a config still fly. A
    flight that raises is tried again on the next free actor; an actor whose process died is replaced
    and its flight tried again; after ``1 + FLIGHT_RETRIES`` tries the flight is reported.

    Args:
        cfgs: the configurations (e.g. one per noise draw); each flight uses one OpenCV thread.
        courses: what to fly with each.
        keep_logs: keep the per-step logs in the results (memory and transfer; default drop them).
        progress: called as each flight finishes, in finishing order, with (config's index, flights of
            that config done, its total, result).
        failed: called likewise with a flight that failed its last try.

    Returns:
        One list per config of the results of its flights that finished, in the order of ``courses``;
        and the flights that failed every try, in the order of ``cfgs`` then ``courses``.
    """
    import ray

    total = len(courses)
    queue = [(j, i) for j in range(len(cfgs)) for i in range(total)]
    if not queue:
        return [[] for _ in cfgs], []
    flier = ray.remote(num_cpus=1, max_restarts=0)(_Flier)
    cfg_ref = ray.put([single_thread_config(c).model_dump(mode="json") for c in cfgs])  # sent once per actor
    size = max(1, min(int(ray.available_resources().get("CPU", 1)), len(queue)))
    idle = [flier.remote(cfg_ref) for _ in range(size)]
    queue.reverse()  # popped from the end: courses in order
    tries: dict[tuple[int, int], int] = {}
    pending: dict[Any, tuple[Any, tuple[int, int]]] = {}  # call -> (actor, (config, course))
    out: list[list[FlightResult | None]] = [[None] * total for _ in cfgs]
    failures: dict[tuple[int, int], FlightFailure] = {}
    done = [0] * len(cfgs)
    try:
        while queue or pending:
            while queue and idle:
                actor = idle.pop()
                j, i = key = queue.pop()
                kind, seed = courses[i]
                pending[actor.fly.remote(j, kind, int(seed), keep_logs)] = (actor, key)
            ready, _ = ray.wait(list(pending), num_returns=1)
            actor, key = pending.pop(ready[0])
            j, i = key
            try:
                result = ray.get(ready[0])
            except Exception as err:  # the flight's own error or its actor's death: tried again, then reported
                if isinstance(err, ray.exceptions.RayActorError):
                    ray.kill(actor)
                    actor = flier.remote(cfg_ref)
                idle.append(actor)
                tries[key] = tries.get(key, 1) + 1
                if tries[key] <= 1 + FLIGHT_RETRIES:
                    queue.append(key)
                    continue
                kind, seed = courses[i]
                failures[key] = FlightFailure(kind, int(seed), _one_line(err))
                log.debug("flight %s-%s failed after %d tries: %s", kind, seed, 1 + FLIGHT_RETRIES, failures[key].error)
                done[j] += 1
                if failed is not None:
                    failed(j, done[j], total, failures[key])
                continue
            idle.append(actor)
            done[j] += 1
            out[j][i] = result
            if progress is not None:
                progress(j, done[j], total, result)
    finally:  # an interrupted suite leaves no flight running
        for actor in [*idle, *(a for a, _ in pending.values())]:
            ray.kill(actor)
    return [[r for r in draw if r is not None] for draw in out], [failures[k] for k in sorted(failures)]


class SuiteOnRay:
    """Suites flown on one Ray session, with a progress bar (on a terminal) over all their flights.

    ``with SuiteOnRay(total, address, num_cpus) as ray_suites:`` then :meth:`fly` with every config (e.g.
    one per noise realization); :attr:`failures` collects the flights that failed every try.

    Raises:
        InputError: Ray is missing or unreachable (on entering).
    """

    def __init__(self, total_flights: int, address: str | None = None, num_cpus: int | None = None) -> None:
        require_ray(SUITE_MODULES)
        self._total = total_flights
        self._session = ray_session(address, num_cpus)
        self._bar: Any = None
        self.failures: list[FlightFailure] = []

    def __enter__(self) -> SuiteOnRay:
        from tqdm import tqdm

        self._session.__enter__()
        self._bar = tqdm(total=self._total, unit="flight", disable=None, file=sys.stderr, leave=False)
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self._bar.close()
        finally:
            self._session.__exit__(*exc)

    def fly(
        self,
        cfgs: Sequence[CompanionConfig],
        courses: Sequence[tuple[str, int]],
        *,
        keep_logs: bool = False,
        progress: Callable[[int, int, int, FlightResult], None] | None = None,
        failed: Callable[[int, int, int, FlightFailure], None] | None = None,
    ) -> list[list[FlightResult]]:
        """Fly the suites (:func:`fly_suites`); the callbacks' printing goes above the bar."""

        def on_result(j: int, done: int, total: int, result: FlightResult) -> None:
            if progress is not None:
                with self._bar.external_write_mode():
                    progress(j, done, total, result)
            self._bar.update(1)

        def on_failure(j: int, done: int, total: int, failure: FlightFailure) -> None:
            self.failures.append(failure)
            if failed is not None:
                with self._bar.external_write_mode():
                    failed(j, done, total, failure)
            self._bar.update(1)

        results, _ = fly_suites(cfgs, courses, keep_logs=keep_logs, progress=on_result, failed=on_failure)
        return results


# --- the tuner ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TuneSpec:
    """What a tune searches and how it judges.

    Attributes:
        base: the config every candidate starts from (the user's file, or the defaults).
        settings: the settings searched, each with its range already clipped to the field's bounds and
            the envelope (:func:`companion.sim.tuning.resolve_settings`).
        courses: the ``(kind, seed)`` courses every candidate flies.
        trials: how many candidates in all (the first is ``base``'s own values).
        time_weight_per_s: score points one second of mean time to goal costs
            (:func:`companion.sim.tuning.score_flights`).
        seed: the sampler's seed (the same seed proposes the same candidates).
    """

    base: CompanionConfig
    settings: tuple[Setting, ...]
    courses: tuple[tuple[str, int], ...]
    trials: int
    time_weight_per_s: float = 0.1
    seed: int = 0


def flight_trial(params: dict[str, Any], *, base_data: dict[str, Any], settings: tuple[Setting, ...],
                 courses: tuple[tuple[str, int], ...], time_weight_per_s: float) -> None:
    """One Ray Tune trial: validate the candidate whole, fly it on every course, report its score."""
    from ray import tune

    from companion.errors import ConfigError
    from companion.sim.camera import make_texture_bank
    from companion.sim.suite import fly_one

    base = parse_config(base_data, source="tune")
    values = {s.path: s.cast(params[s.key]) for s in settings}
    try:
        cfg = single_thread_config(with_settings(base, values))
    except ConfigError as err:  # never flown: a candidate must be a valid config whole
        tune.report(dataclasses.asdict(TrialScore.invalid(str(err))))
        return
    bank = make_texture_bank()
    results = [fly_one(kind, seed, cfg, bank, False) for kind, seed in courses]
    tune.report(dataclasses.asdict(score_flights(results, time_weight_per_s)))


def run_tune(
    spec: TuneSpec,
    storage: Path,
    *,
    resume: bool = False,
    address: str | None = None,
    num_cpus: int | None = None,
    verbose: int = 1,
    callbacks: Sequence[Any] = (),
) -> tuple[list[dict[str, Any]], bool]:
    """Run (or resume) the search of ``spec`` with its experiment under ``storage``.

    Args:
        spec: what to search.
        storage: the experiment's folder (absolute; made if missing): Ray Tune's state, one folder per
            trial, the searcher's state. A run stopped by Ctrl-C or killed resumes from it.
        resume: continue the experiment in ``storage`` (its unfinished and errored trials run again);
            False needs no experiment there yet.
        address, num_cpus: where Ray runs (:func:`ray_session`).
        verbose: Ray Tune's console output (0 silent, 1 status, 2 per trial).
        callbacks: Ray Tune callbacks (:class:`ray.tune.Callback`) of a new experiment; a resumed one
            keeps those it was started with.

    Returns:
        One row per trial that finished or failed (``trial``: its number from 1, the setting values under
        their paths, and the :class:`~companion.sim.tuning.TrialScore` fields; a failed trial's
        ``problem`` says why), in the order the trials were made, and whether every trial of
        ``spec.trials`` has its row (False: stopped early; resume to go on).

    Raises:
        InputError: Ray is missing or unreachable, ``resume`` without an experiment in ``storage`` or an
            experiment there without ``resume``.
    """
    require_ray()
    from ray import tune
    from ray.tune.search.optuna import OptunaSearch

    storage = storage.expanduser().resolve()
    path = storage / EXPERIMENT_DIR
    exists = tune.Tuner.can_restore(str(path)) if path.exists() else False
    if resume and not exists:
        raise InputError(f"{path}: no tune to resume here")
    if not resume and path.exists():
        raise InputError(f"{path}: a tune is already here; --resume to go on with it, or another --out")
    trainable = tune.with_resources(
        tune.with_parameters(
            flight_trial,
            base_data=spec.base.model_dump(mode="json"),
            settings=spec.settings,
            courses=spec.courses,
            time_weight_per_s=spec.time_weight_per_s,
        ),
        {"cpu": 1},
    )
    with ray_session(address, num_cpus):
        if resume:
            tuner = tune.Tuner.restore(str(path), trainable=trainable, resume_unfinished=True, resume_errored=True)
        else:
            import optuna

            space = {s.key: s.distribution(optuna) for s in spec.settings}
            search = OptunaSearch(
                space=space,
                metric="score",
                mode="max",
                points_to_evaluate=[{s.key: s.start for s in spec.settings}],
                seed=spec.seed,
            )
            tuner = tune.Tuner(
                trainable,
                tune_config=tune.TuneConfig(search_alg=search, num_samples=spec.trials),
                run_config=tune.RunConfig(
                    storage_path=str(storage),
                    name=EXPERIMENT_DIR,
                    verbose=verbose,
                    failure_config=tune.FailureConfig(max_failures=FLIGHT_RETRIES),
                    callbacks=list(callbacks),
                ),
            )
        rows = _rows(tuner.fit(), spec.settings)
    return rows, len(rows) >= spec.trials


def _rows(grid: Any, settings: Sequence[Setting]) -> list[dict[str, Any]]:
    """One row per trial of ``grid`` (a ResultGrid) that finished or failed, in the order the trials were
    made; a trial that failed on every try is a row of :meth:`TrialScore.invalid` saying why. Trials not
    finished (a stopped run) have no row."""
    rows = []
    for result in grid:
        metrics = result.metrics or {}
        if "score" in metrics:
            score = {f.name: metrics.get(f.name, f.default) for f in dataclasses.fields(TrialScore)}
        elif result.error is not None:
            score = dataclasses.asdict(TrialScore.invalid(f"the trial failed twice: {_one_line(result.error)}"))
        else:
            continue
        config = result.config or {}
        row: dict[str, Any] = {"trial": _trial_number(result.path)}
        row.update({s.path: s.cast(config[s.key]) for s in settings if s.key in config})
        row.update(score)
        rows.append(row)
    rows.sort(key=lambda r: r["trial"])
    return rows


def _trial_number(path: str | None) -> int:
    """The trial's number, counting from 1 in the order Tune made them (its folder is named
    ``flight_trial_<trial id>_<number>_<settings>_<date>``); 0 when the folder does not say."""
    m = re.match(re.escape(flight_trial.__name__) + r"_[0-9a-f]+_(\d+)_", Path(path or "").name)
    return int(m.group(1)) if m else 0
