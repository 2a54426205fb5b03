"""Time the local stack's work per frame and per control tick on simulated courses.

Flies the courses and times :meth:`LocalStack.add_frame` (a frame into
the map) and :meth:`LocalStack.step` (the plan and the safety chain), milliseconds on this machine;
prints the median and p99 of each and the machine's load average.

    python tools/planner-tick.py --config my.toml --courses detour-0,pitch-2,forest-1 [--clock thread]
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
import time
from pathlib import Path

import numpy as np

from companion.config import load_config
from companion.core.planner.stack import LocalStack
from companion.core.planner import compile_kernels
from companion.sim.courses import make_course
from companion.sim.loop import fly, simulator_config


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, default=None)
    ap.add_argument("--courses", default="detour-0,pitch-2,forest-1")
    ap.add_argument(
        "--clock",
        choices=("wall", "thread"),
        default="wall",
        help="wall: elapsed time; thread: the CPU time of the calling thread (on a machine others load, "
        "what the work itself costs, without the time waited for a core)",
    )
    args = ap.parse_args()
    clock = time.perf_counter if args.clock == "wall" else time.thread_time
    cfg = load_config(args.config)
    compile_kernels()  # as the service does at start-up
    # And as it does once started: what start-up built is out of the garbage collector's full
    # collections (on this heap, 0.1 s in whatever call it falls on).
    gc.collect()
    gc.freeze()
    times: dict[str, list[float]] = {"add_frame": [], "step": []}
    originals = {name: getattr(LocalStack, name) for name in times}

    def timed(name: str):
        orig = originals[name]

        def wrapper(self, *a, **kw):
            t0 = clock()
            out = orig(self, *a, **kw)
            times[name].append((clock() - t0) * 1e3)
            return out

        return wrapper

    for name in times:
        setattr(LocalStack, name, timed(name))
    try:
        for spec in args.courses.split(","):
            kind, seed = spec.rsplit("-", 1)
            r = fly(make_course(kind, int(seed)), simulator_config(cfg))
            print(f"{spec}: {r.outcome.value} in {r.time_s:.1f} s")
    finally:
        for name, orig in originals.items():
            setattr(LocalStack, name, orig)
    for name, ms in times.items():
        a = np.asarray(ms)
        if len(a):
            print(f"{name}: n {len(a)}, median {np.median(a):.2f} ms, p99 {np.percentile(a, 99):.2f} ms, max {a.max():.2f} ms")
    print(f"clock {args.clock}; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
