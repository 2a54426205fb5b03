"""Issue 21: the detour layer's histogram off the service's control loop. A deferred planner asks for
it (an immutable request), flies on safely until the result is offered, takes only the answer to its
latest request; the synchronous planner (the simulator) decides as before; the supervisor passes the
request out on its step output and the result in as a step input; the daemon computes it in a worker
thread while the control loop keeps stepping, and a failure there ends the detour in a hold."""

from __future__ import annotations

import asyncio
import logging
import math
import threading
from dataclasses import replace

import numpy as np
import pytest
from peers.fakes import FakeLink
from test_detour import BRAKE, CLEAR, DET, MEM, _trusted_memory, _wall

from companion.core import detour as detour_mod
from companion.core.course import CourseHold
from companion.core.detour import (
    DetourPlanner,
    HistogramRequest,
    HistogramResult,
    Phase,
    compute_histogram,
    wrap_pi,
)
from companion.core.goal import GoalSpec
from companion.core.supervisor import Goto, State, StepOutput
from companion.core.types import VelocitySetpoint

POS = np.array([0.0, 0.0, -1.5])


def _trigger(p: DetourPlanner, mem, t0: float = 0.0, yaw: float = 0.0, pos: np.ndarray = POS):
    """Brake until the detour layer starts; returns its first command and the time after it."""
    t = t0
    cmd = None
    while cmd is None and t < t0 + 3.0:
        cmd = p.update(t, BRAKE, pos, yaw, 0.0, 0.0, mem, MEM, DET, goal_distance_m=6.0)
        t += 0.05
    assert cmd is not None, p.reason
    return cmd, t


def _answer(p: DetourPlanner) -> HistogramResult:
    req = p.pending_request
    assert req is not None
    return HistogramResult(req.seq, compute_histogram(req))


# ---------------------------------------------------------------------------------------------- planner


def test_a_deferred_planner_holds_where_it_is_until_its_first_histogram_comes() -> None:
    mem = _trusted_memory(_wall(2.5, -8.0, 8.0))
    p = DetourPlanner(defer=True)
    cmd, t = _trigger(p, mem)
    req = p.pending_request
    assert req is not None and p.active
    # The snapshot: the map's points from where it was asked, nobody may change them.
    assert req.points_ne_m.shape[1] == 2 and len(req.points_ne_m) > 0 and not req.points_ne_m.flags.writeable
    assert np.array_equal(req.position_ned_m, POS) and req.goal_distance_m == 6.0 and req.cfg is DET
    # Meanwhile: a hold where it began (an anchor), facing as it does (no target), whatever the vehicle does.
    assert cmd.phase is Phase.SCAN and cmd.target_yaw_rad is None and np.array_equal(cmd.anchor_ned_m, POS)
    for k in range(20):
        drifted = POS + np.array([0.02 * k, -0.01 * k, 0.0])
        out = p.update(t, BRAKE if k % 2 else CLEAR, drifted, 0.1 * math.sin(k), 0.0, 0.0, mem, MEM, DET, goal_distance_m=6.0)
        t += 0.05
        assert out.phase is Phase.SCAN and out.target_yaw_rad is None and np.array_equal(out.anchor_ned_m, POS)
        assert p.pending_request is req  # one request, not a new one every step
    assert "mapping the way round" in p.reason


def test_a_deferred_planner_keeps_its_direction_while_a_replan_is_computed() -> None:
    # A wall with its end 3 m to the right: a detour flies round the right.
    mem = _trusted_memory(_wall(2.5, -8.0, 3.0))
    p = DetourPlanner(defer=True)
    _, t = _trigger(p, mem)
    yaw = 0.0
    chosen = None
    for _ in range(400):  # turn as asked, answering every request at once, until it flies a direction
        if p.pending_request is not None:
            assert p.offer(_answer(p))
        cmd = p.update(t, CLEAR, POS, yaw, 0.0, 0.0, mem, MEM, DET, goal_distance_m=6.0)
        t += 0.05
        if cmd is not None and cmd.phase is Phase.FLY and cmd.anchor_ned_m is None:
            chosen = cmd.target_yaw_rad
            break
        if cmd is not None and cmd.target_yaw_rad is not None:
            yaw += max(-0.1, min(0.1, wrap_pi(cmd.target_yaw_rad - yaw)))
    assert chosen is not None, p.reason
    yaw = chosen
    # Fly on to the next replan: a request, and until its result comes the same direction, flown.
    asked = None
    for _ in range(40):
        cmd = p.update(t, CLEAR, POS, yaw, 0.0, 0.0, mem, MEM, DET, goal_distance_m=6.0)
        t += 0.05
        assert cmd is not None and cmd.phase is Phase.FLY and cmd.target_yaw_rad == chosen
        if p.pending_request is not None:
            asked = p.pending_request
            break
    assert asked is not None
    for _ in range(30):  # longer than replan_interval_s: still one request, the same direction
        cmd = p.update(t, BRAKE, POS, yaw, 0.0, 0.0, mem, MEM, DET, goal_distance_m=6.0)
        t += 0.05
        assert cmd.phase is Phase.FLY and cmd.target_yaw_rad == chosen and p.pending_request is asked
    assert p.offer(HistogramResult(asked.seq, compute_histogram(asked)))
    assert p.pending_request is None
    cmd = p.update(t, CLEAR, POS, yaw, 0.0, 0.0, mem, MEM, DET, goal_distance_m=6.0)
    assert cmd is not None and cmd.phase in (Phase.FLY, Phase.HANDBACK) and p.pending_request is None


def test_after_a_look_round_it_keeps_turning_in_place_while_the_histogram_is_computed() -> None:
    # A wall near ahead: no way round in view, so a look round first.
    mem = _trusted_memory(_wall(1.5, -8.0, 8.0))
    p = DetourPlanner(defer=True)
    _, t = _trigger(p, mem)
    assert p.offer(_answer(p))
    cmd = p.update(t, BRAKE, POS, 0.0, 0.0, 0.0, mem, MEM, DET, goal_distance_m=6.0)
    t += 0.05
    assert cmd.phase is Phase.SCAN and cmd.target_yaw_rad is not None and p.pending_request is None  # looking round
    assert "looking round" in p.reason and "mapping" not in p.reason
    anchor = cmd.anchor_ned_m.copy()
    yaw = 0.0
    last_target = None
    for _ in range(400):  # turn as asked until the look ends and a choice is asked for
        if cmd.target_yaw_rad is not None:
            last_target = cmd.target_yaw_rad
            yaw += max(-0.1, min(0.1, wrap_pi(cmd.target_yaw_rad - yaw)))
        cmd = p.update(t, BRAKE, POS, yaw, 0.0, 0.0, mem, MEM, DET, goal_distance_m=6.0)
        t += 0.05
        if p.pending_request is not None:
            if p.reason.startswith("looking round"):
                # Facing the goal mid-way: a look at the map (the wall still blocks it: look on),
                # meanwhile facing the goal where the look began.
                assert cmd.phase is Phase.SCAN and np.array_equal(cmd.anchor_ned_m, anchor)
                assert cmd.target_yaw_rad == pytest.approx(0.0)
                assert p.offer(_answer(p))
                continue
            break
    assert p.pending_request is not None
    assert p.reason == "looked round: mapping the way round"
    for _ in range(10):  # meanwhile: turning in place where it looked round, to the look's last heading
        assert cmd.phase is Phase.SCAN and np.array_equal(cmd.anchor_ned_m, anchor)
        assert cmd.target_yaw_rad == last_target
        cmd = p.update(t, BRAKE, POS, yaw, 0.0, 0.0, mem, MEM, DET, goal_distance_m=6.0)
        t += 0.05


def test_only_the_answer_to_the_latest_request_is_taken() -> None:
    mem = _trusted_memory(_wall(2.5, -8.0, 8.0))
    p = DetourPlanner(defer=True)
    _, t = _trigger(p, mem)
    first = p.pending_request
    old = HistogramResult(first.seq, compute_histogram(first))
    assert not p.offer(HistogramResult(first.seq + 7, old.histogram))  # not an answer to it
    p.reset()  # the detour ended (a new goal, resume, take-over)
    assert p.pending_request is None and not p.offer(old)
    _, t = _trigger(p, mem, t + 1.0)
    second = p.pending_request
    assert second is not None and second.seq != first.seq
    assert not p.offer(old)  # asked before the reset: dropped
    assert p.offer(_answer(p)) and not p.offer(_answer_of(second))  # answered once only
    # A new goal on course hold drops what its detour waits for too.
    hold = CourseHold(defer_histogram=True)
    hold.engage(POS, 0.0, GoalSpec(kind="point", north_m=6.0, east_m=0.0))
    _trigger(hold.detour, mem)
    asked = hold.detour.pending_request
    hold.set_goal(GoalSpec(kind="point", north_m=0.0, east_m=6.0), POS, 0.0)
    assert hold.detour.pending_request is None and not hold.detour.offer(_answer_of(asked))


def _answer_of(req: HistogramRequest) -> HistogramResult:
    return HistogramResult(req.seq, compute_histogram(req))


def test_a_deferred_planner_decides_as_the_synchronous_one_from_the_same_snapshot() -> None:
    # The way round in view (a wall ending 1 m to the right): the first choice needs no look round.
    mem = _trusted_memory(_wall(2.5, -8.0, 1.0))
    sync, deferred = DetourPlanner(), DetourPlanner(defer=True)
    want, _ = _trigger(sync, mem)
    held, t = _trigger(deferred, mem)
    assert sync.pending_request is None  # the synchronous planner never leaves one
    assert held.phase is Phase.SCAN and held.target_yaw_rad is None
    assert deferred.offer(_answer(deferred))
    got = deferred.update(t, BRAKE, POS, 0.0, 0.0, 0.0, mem, MEM, DET, goal_distance_m=6.0)
    assert want.phase is got.phase is Phase.FLY
    assert got.target_yaw_rad == want.target_yaw_rad and deferred.reason == sync.reason


def test_the_synchronous_planner_computes_each_request_inside_update(monkeypatch) -> None:
    asked: list[HistogramRequest] = []
    real = detour_mod.compute_histogram

    def spy(req: HistogramRequest):
        asked.append(req)
        return real(req)

    monkeypatch.setattr(detour_mod, "compute_histogram", spy)
    mem = _trusted_memory(_wall(2.5, -8.0, 8.0))
    p = DetourPlanner()
    cmd, _ = _trigger(p, mem)
    assert len(asked) == 1 and cmd.target_yaw_rad is not None and p.pending_request is None
    # The snapshot it computed from: what it used to compute from the memory directly.
    pts = mem.map_points(POS, asked[0].asked_s, MEM, max(DET.radius_m, MEM.map_depth_m) + DET.clearance_m)
    assert np.array_equal(asked[0].points_ne_m, pts)


# ---------------------------------------------------------------------------------------------- supervisor


def _engaged_harness():
    from test_supervisor import Harness, default_config, vehicle

    h = Harness(default_config(detour=DET, memory=MEM))
    h.sup = type(h.sup)(h.cfg, defer_histogram=True)
    flying = replace(vehicle("OFFBOARD"), position_ned_m=POS.copy(), attitude_rad=np.zeros(3))
    h.engage()
    h.vehicle = flying
    assert h.step(Goto(GoalSpec(kind="point", north_m=6.0, east_m=0.0))).replies[0].ok  # from where it is
    h.sup._m.obstacles = _trusted_memory(_wall(2.5, -8.0, 8.0), t_s=h.now)
    h.frame = replace(h.frame, decision=BRAKE)
    return h


def _step(h, histogram=None) -> StepOutput:
    h.now += 0.05
    h.frame = replace(h.frame, timestamp_s=h.now - 0.02)
    out = h.sup.step(h.now, h.frame, h.vehicle, (), histogram=histogram)
    h.outputs.append(out)
    return out


def test_the_supervisor_asks_on_its_output_and_takes_the_result_as_an_input() -> None:
    h = _engaged_harness()
    out = None
    for _ in range(40):
        out = _step(h)
        if out.histogram_request is not None:
            break
    req = out.histogram_request
    assert req is not None and out.state is State.ENGAGED
    assert h.sup.goal_status(POS)["detour"]["phase"] == "scan"
    for _ in range(5):  # not answered: asked again (the same request), holding meanwhile
        out = _step(h)
        assert out.histogram_request is req and out.setpoint is not None
        assert abs(out.setpoint.forward_m_s) < 0.3 and abs(out.setpoint.yaw_rate_deg_s) < 1e-9
    out = _step(h, HistogramResult(req.seq, compute_histogram(req)))
    assert out.histogram_request is None and out.state is State.ENGAGED
    status = h.sup.goal_status(POS)["detour"]
    assert status["phase"] in ("scan", "fly") and status["heading_deg"] is not None  # a way chosen, or a look round
    # A stale answer (its request is gone) changes nothing.
    before = h.sup.goal_status(POS)["detour"]
    out = _step(h, HistogramResult(req.seq, compute_histogram(req)))
    assert h.sup.goal_status(POS)["detour"] == before


def test_a_failed_histogram_ends_the_detour_in_a_hold_that_says_why() -> None:
    h = _engaged_harness()
    req = None
    for _ in range(40):
        req = _step(h).histogram_request
        if req is not None:
            break
    assert req is not None
    _step(h, HistogramResult(req.seq, None, "RuntimeError: boom"))
    out = _step(h)
    assert out.state is State.PAUSED and "could not be computed" in out.reason and "boom" in out.reason
    assert out.histogram_request is None and out.setpoint is not None and abs(out.setpoint.forward_m_s) < 0.3


# ---------------------------------------------------------------------------------------------- daemon


class _AskingSupervisor:
    """Stands in for the supervisor: engaged, a setpoint every step, and a histogram request until a
    step brings its result; records what each step was handed."""

    def __init__(self, request: HistogramRequest) -> None:
        self.request = request
        self.steps: list[tuple[float, HistogramResult | None, str]] = []
        self.answer: HistogramResult | None = None
        self.engaged = True

    def step(self, now_s, latest, vehicle, requests=(), camera_ok=True, histogram=None) -> StepOutput:
        self.steps.append((now_s, histogram, threading.current_thread().name))
        if histogram is not None and histogram.seq == self.request.seq:
            self.answer = histogram
        return StepOutput(
            setpoint=VelocitySetpoint(0.5, 0.0, 0.0, 0.0),
            actions=(),
            state=State.ENGAGED,
            reason="engaged",
            replies=(),
            changed=False,
            frame_age_s=0.0,
            histogram_request=None if self.answer is not None else self.request,
        )


def _request(seq: int = 1) -> HistogramRequest:
    p = DetourPlanner(defer=True)
    p._next_seq = seq - 1
    _trigger(p, _trusted_memory(_wall(2.5, -8.0, 8.0)))
    return p.pending_request


def _daemon(tmp_path, histogram_fn):
    from peers.fakes import service_config

    from companion.service.daemon import Service

    return Service(service_config(tmp_path), link=FakeLink(), install_signals=False, environ={}, histogram_fn=histogram_fn)


async def _run_control_loop(service, until, timeout_s: float = 10.0) -> None:
    """Run the daemon's control loop until ``until()`` holds (checked every 10 ms)."""
    service.control_loop.bind(asyncio.get_running_loop())
    task = asyncio.get_running_loop().create_task(service.control_loop.run())
    try:
        for _ in range(int(timeout_s / 0.01)):
            if until():
                return
            await asyncio.sleep(0.01)
        raise AssertionError("timed out")
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


def test_the_daemon_computes_the_histogram_off_the_control_loop(tmp_path) -> None:
    release = threading.Event()
    calls: list[tuple[int, str]] = []

    def slow(req: HistogramRequest):
        calls.append((req.seq, threading.current_thread().name))
        release.wait(30.0)  # as long as the test wants: the loop must not wait for it
        return compute_histogram(req)

    service = _daemon(tmp_path, slow)
    req = _request()
    sup = service.control_loop.supervisor = _AskingSupervisor(req)

    async def scenario() -> None:
        await _run_control_loop(service, lambda: len(calls) == 1 and len(service.link.sent) >= 20)
        # The worker is blocked; the loop stepped and sent setpoints all along, asking once only.
        assert all(h is None for _, h, _ in sup.steps)
        release.set()
        await _run_control_loop(service, lambda: sup.answer is not None)
        await service.control_loop.stop(10.0)

    asyncio.run(scenario())
    assert len(calls) == 1 and calls[0][0] == req.seq
    loop_thread = sup.steps[0][2]
    assert calls[0][1] != loop_thread and calls[0][1].startswith("detour-histogram")
    assert {name for _, _, name in sup.steps} == {loop_thread}  # every step on the loop
    want = compute_histogram(req)
    assert sup.answer.error is None and np.array_equal(sup.answer.histogram.free_m, want.free_m)
    assert service.histogram_stats == {"computed": 1, "failed": 0}


def test_a_failure_in_the_worker_is_logged_and_handed_to_the_supervisor(tmp_path, caplog) -> None:
    def broken(req: HistogramRequest):
        raise RuntimeError("boom")

    service = _daemon(tmp_path, broken)
    req = _request(seq=5)
    sup = service.control_loop.supervisor = _AskingSupervisor(req)
    caplog.set_level(logging.ERROR, logger="companion.service.control_loop")

    async def scenario() -> None:
        await _run_control_loop(service, lambda: sup.answer is not None and len(service.link.sent) >= 5)
        await service.control_loop.stop(10.0)

    asyncio.run(scenario())
    assert sup.answer.histogram is None and "RuntimeError: boom" in sup.answer.error
    assert service.histogram_stats["failed"] == 1
    assert "detour histogram" in (service.errors.message or "") and "boom" in service.errors.message
    records = [r for r in caplog.records if "detour histogram failed" in r.getMessage()]
    assert records and "request 5" in records[0].getMessage() and records[0].exc_info is not None



def test_a_deferred_line_up_slides_from_where_the_histogram_was_seen() -> None:
    # A door between -0.1 and 0.75 m east, 1 m ahead: its middle (for line_up_clearance_m) 0.33 m east
    # of where the vehicle asked. It drifts 0.1 m west before the answer comes: the slide's end is
    # still the door's middle, not 0.33 m east of where the vehicle is then.
    mem = _trusted_memory(np.concatenate([_wall(1.0, -4.0, -0.1), _wall(1.0, 0.75, 4.0)]))
    p = DetourPlanner(defer=True)
    _, t = _trigger(p, mem)
    answer = _answer(p)
    assert answer.histogram is not None and answer.histogram.line_up_m is not None
    moved = POS + np.array([0.0, -0.1, 0.0])
    assert p.offer(answer)
    cmd = p.update(t, BRAKE, moved, 0.0, 0.0, 0.0, mem, MEM, DET, goal_distance_m=6.0)
    assert cmd is not None and cmd.phase is Phase.HANDBACK and "lining up" in p.reason
    assert cmd.anchor_ned_m[1] == pytest.approx(answer.histogram.line_up_m, abs=1e-9)
    assert cmd.anchor_ned_m[1] == pytest.approx(0.325, abs=0.03)
