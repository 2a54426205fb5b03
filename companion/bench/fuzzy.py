"""Micro-benchmark of the fuzzy controller (for ``companion bench`` and docs/benchmarks.md).

Speed targets live here, not in tests: one inference of the main avoidance system (9 inputs, the
default rule base, 2 outputs of 201 samples) should take <= 100 µs on the reference CPU.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from companion.config.core import ControllerConfig
from companion.core.fuzzy.avoidance import AvoidanceController


def _stats_us(samples_s: np.ndarray) -> tuple[float, float]:
    us = samples_s * 1e6
    return float(np.median(us)), float(np.percentile(us, 99))


def bench_fuzzy(
    n: int = 5000,
    *,
    cfg: ControllerConfig | None = None,
    seed: int = 0,
    clock: Callable[[], float] = time.perf_counter,
) -> dict[str, float]:
    """Time ``n`` main-system inferences and ``n`` full ``AvoidanceController.decide`` calls.

    Inputs are random region depths, uniform in [0, 4] m (the near/far transition and beyond), 5 % of
    them NaN for ``decide`` (NaN is not a valid engine input). Each call is timed on its own with
    ``clock`` after a warm-up of min(n, 200) calls.

    Args:
        n: calls per measurement, >= 1.
        cfg: the configuration (default ``ControllerConfig()``).
        seed: seed of the random inputs.
        clock: seconds, monotonic.

    Returns:
        ``n``; ``infer_median_us``, ``infer_p99_us`` (one ``FuzzySystem.infer`` of the main system);
        ``decide_median_us``, ``decide_p99_us`` (one ``decide``, main and, when needed, corner system);
        ``build_ms`` (constructing the controller: both systems compiled).
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    cfg = cfg if cfg is not None else ControllerConfig()
    t0 = clock()
    ctl = AvoidanceController(cfg)
    build_s = clock() - t0
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.0, 4.0, (n, 9))
    with_unknown = np.where(rng.random((n, 9)) < 0.05, np.nan, depth)
    system = ctl.main_system
    out: dict[str, float] = {"n": float(n), "build_ms": build_s * 1e3}
    for label, fn, data in (("infer", system.infer, depth), ("decide", ctl.decide, with_unknown)):
        for row in data[: min(n, 200)]:
            fn(row)
        times = np.empty(n)
        for i, row in enumerate(data):
            t = clock()
            fn(row)
            times[i] = clock() - t
        out[f"{label}_median_us"], out[f"{label}_p99_us"] = _stats_us(times)
    return out
