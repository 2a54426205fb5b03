"""The control step's cost during a detour with a full obstacle memory, the histogram inside the step
(as the simulator computes it) or deferred (as the
service computes it now: the step asks, a worker computes, a later step takes the result).

A wall 2 m ahead (north 2.0-2.4 m, east -5..+5 m, within 0.4 m of the vehicle's altitude, 5 cm cubes)
trusted in the memory, which keeps its most: 20 000 points. An engaged :class:`Supervisor` with a goal
8 m north, the controller braking, the vehicle turning as commanded in place: the detour layer looks
round, flies, replans and finally holds (a dead end: it never moves). Every ``Supervisor.step`` of
30 s at 20 Hz is timed (``time.perf_counter``), and each histogram the worker would compute.

    PYTHONPATH=. python tools/detour_step_timing.py [--steps 600]
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import numpy as np

from companion.config import parse_config
from companion.core.detour import HistogramResult, compute_histogram
from companion.core.goal import GoalSpec
from companion.core.memory import ObstacleMemory
from companion.core.supervisor import (
    Action,
    ActionResult,
    Engage,
    Goto,
    Supervisor,
    SupervisorConfig,
)
from companion.core.types import Decision, DecisionKind
from companion.interfaces import VehicleState

BRAKE = Decision(DecisionKind.BRAKE, yaw=0.0, pitch=0.0, speed_fraction=0.0, reason="brake")
POS = np.array([0.0, 0.0, -1.5])


class _Frame:
    def __init__(self, t_s: float) -> None:
        self.timestamp_s = t_s
        self.decision = BRAKE


def _wall_memory(t_s: float, cfg) -> ObstacleMemory:
    n, e, d = np.meshgrid(np.arange(2.0, 2.41, 0.05), np.arange(-5.0, 5.0001, 0.05), np.arange(-0.4, 0.4001, 0.05), indexing="ij")
    wall = np.stack([n.ravel(), e.ravel(), POS[2] + d.ravel()], 1)
    mem = ObstacleMemory()
    for k, vp in enumerate(([0.0, -0.5, POS[2]], [0.0, 0.5, POS[2]])):
        mem.add(wall, t_s + 0.1 * k, cfg.duration_s, ranges_m=np.full(len(wall), 2.0), viewpoint_ned_m=np.array(vp), cfg=cfg)
    return mem


def run(deferred: bool, steps: int) -> None:
    cfg = parse_config({"detour": {"trigger_after_s": 0.8}})
    sup = Supervisor(SupervisorConfig.from_config(cfg), defer_histogram=deferred)
    now = 100.0
    v = VehicleState(connected=True, armed=True, flight_mode="POSCTL", in_offboard=False, position_ned_m=POS.copy(), attitude_rad=np.zeros(3))
    sup.step(now, _Frame(now), v, [Engage()])
    while True:  # engage as the service does: prestream, start offboard, confirmed
        now += 0.05
        if Action.START_OFFBOARD in sup.step(now, _Frame(now - 0.02), v).actions:
            break
    v = replace(v, flight_mode="OFFBOARD", in_offboard=True)
    now += 0.05
    sup.step(now, _Frame(now - 0.02), v, [ActionResult(Action.START_OFFBOARD, True)])
    now += 0.05
    sup.step(now, _Frame(now - 0.02), v, [Goto(GoalSpec(kind="point", north_m=8.0, east_m=0.0))])
    sup._m.obstacles = _wall_memory(now, cfg.memory)  # a full memory (the test of a busy map, not a flight)
    step_s, asking_s, worker_s, yaw, result = [], [], [], 0.0, None
    for _ in range(steps):
        now += 0.05
        t0 = time.perf_counter()
        out = sup.step(now, _Frame(now - 0.02), v, histogram=result)
        step_s.append(time.perf_counter() - t0)
        result = None
        if out.histogram_request is not None:  # the worker's share, here at once, the next step takes it
            asking_s.append(step_s[-1])
            t1 = time.perf_counter()
            result = HistogramResult(out.histogram_request.seq, compute_histogram(out.histogram_request))
            worker_s.append(time.perf_counter() - t1)
        yaw += np.radians(out.setpoint.yaw_rate_deg_s) * 0.05
        v = replace(v, attitude_rad=np.array([0.0, 0.0, yaw]))
    ms = [1e3 * x for x in step_s]
    slow = [x for x in ms if x > 10.0]
    print(
        f"{'deferred' if deferred else 'in the step'}: Supervisor.step median {statistics.median(ms):.2f} ms, "
        f"max {max(ms):.2f} ms; {len(slow)} of {len(ms)} steps over 10 ms"
        + (f" (median {statistics.median(slow):.2f} ms)" if slow else "")
        + f"; ends {sup.state.value}, detour {sup.goal_status(POS)['detour']['phase']}"
    )
    if asking_s:
        a, w = [1e3 * x for x in asking_s], [1e3 * x for x in worker_s]
        print(
            f"  {len(a)} steps asking: median {statistics.median(a):.2f} ms, max {max(a):.2f} ms; "
            f"the worker's histograms: median {statistics.median(w):.2f} ms, max {max(w):.2f} ms"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=600, help="control steps at 20 Hz (default 600: 30 s)")
    args = ap.parse_args()
    run(False, args.steps)
    run(True, args.steps)


if __name__ == "__main__":
    main()
