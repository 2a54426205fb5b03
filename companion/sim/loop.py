"""The closed loop: camera → the product's pipeline → the local stack → vehicle, in simulated time.

Timing (all simulated; deterministic for a course and config):

* **physics** at ``sim.physics_rate_hz`` (default 200 Hz): the vehicle model integrates, the
  ground-truth clearance and the outcome are checked at every step;
* **camera** at ``sim.camera_rate_hz``: :class:`~companion.sim.camera.SimCamera` renders the frame
  seen from the pose at that instant, stamped with that time; the pipeline processes it at once
  (the result does not depend on when it runs) but its decision only **applies**
  ``sim.processing_latency_s`` later, as on the vehicle where the pipeline takes that long;
* **setpoints** at ``sim.setpoint_rate_hz`` (20 Hz): as the service makes them, the local stack
  (:class:`~companion.core.planner.stack.LocalStack`) on the newest applied decision with its age, so
  a frame older than ``command.stale_frame_timeout_s`` gives zero velocity; older than
  ``command.failsafe_timeout_s`` the vehicle is switched to HOLD. Each applied frame enters the
  stack's map from the pose at capture. The progress watchdog is the service's too
  (:class:`~companion.core.progress.GoalProgress`, the course being the start pose), on the same clock.

Events due at the same instant run in the order camera, decision, setpoint, physics. The flight ends
on the first outcome (:mod:`companion.sim.scoring`). ``realtime=True`` sleeps so that simulated time
keeps pace with the wall clock (the only place that reads a clock for anything but instrumentation).
"""

from __future__ import annotations

import enum
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from companion.backends import make_pipeline
from companion.config import CompanionConfig
from companion.core.goal import GoalSpec
from companion.core.pipeline import FrameResult, Pipeline
from companion.core.planner import compile_kernels
from companion.core.planner.stack import LocalStack
from companion.core.progress import NO_PROGRESS_HOLD, GoalProgress
from companion.core.types import ZERO_SETPOINT, DecisionKind, VelocitySetpoint
from companion.errors import CameraError, CompanionError
from companion.interfaces import Frame
from companion.interrupts import interrupt_after
from companion.jitcache import use_cache_dir_or_memory
from companion.sim.camera import SimCamera
from companion.sim.courses import Course
from companion.sim.render import Pose, TextureBank
from companion.sim.scoring import HELD_RADIUS_M, Judge, Outcome
from companion.sim.vehicle import SimVehicle, VehicleParams

logger = logging.getLogger(__name__)

#: Events scheduled at k/rate fire when the simulated time is within this of it (float steps).
_EPS_S = 1e-9


class LogKind(enum.IntEnum):
    """What drove the setpoint at a log row."""

    NONE = 0  #: no decision yet (zero velocity)
    CLEAR = 1
    AVOID = 2
    BRAKE = 3
    STALE = 4  #: the newest decision is older than the stale timeout (zero velocity)
    HOLD = 5  #: the vehicle is in HOLD (failsafe)
    DETOUR = 6  #: the planner was in its detour mode (going round, or turning to look)


_KIND_OF = {DecisionKind.CLEAR: LogKind.CLEAR, DecisionKind.AVOID: LogKind.AVOID, DecisionKind.BRAKE: LogKind.BRAKE}


@dataclass(frozen=True)
class FlightLog:
    """The flight at the setpoint rate, one row per setpoint (plus a last row at the end).

    Attributes:
        t_s: float64 ``(N,)`` simulated time, seconds.
        position_ned_m: float64 ``(N, 3)`` vehicle centre, NED metres.
        velocity_ned_m_s: float64 ``(N, 3)``, m/s.
        attitude_rad: float64 ``(N, 3)`` roll, pitch, yaw, radians (yaw from north, clockwise).
        kind: int8 ``(N,)`` :class:`LogKind` of what drove the setpoint.
        decision_yaw, decision_pitch: float64 ``(N,)`` the applied decision's outputs in [-1, 1]
            (0 without a decision).
        setpoint: float64 ``(N, 4)`` forward m/s, right m/s, down m/s, yaw rate deg/s as sent.
        clearance_m: float64 ``(N,)`` ground-truth clearance (see :mod:`companion.sim.scoring`), metres.
        frame_t_s: float64 ``(N,)`` capture time of the frame whose decision was applied (a row of
            :class:`FrameLog`), seconds; NaN before the first.
        planner: what the local planner was doing, per row: ``mode: reason`` (cruise, avoid, detour,
            hold), or "" before its first tick.
    """

    t_s: np.ndarray
    position_ned_m: np.ndarray
    velocity_ned_m_s: np.ndarray
    attitude_rad: np.ndarray
    kind: np.ndarray
    decision_yaw: np.ndarray
    decision_pitch: np.ndarray
    setpoint: np.ndarray
    clearance_m: np.ndarray
    frame_t_s: np.ndarray
    planner: tuple[str, ...]

    def equals(self, other: FlightLog) -> bool:
        """Exact equality of every field, arrays NaN for NaN (determinism checks)."""
        return all(_same(getattr(self, f), getattr(other, f)) for f in self.__dataclass_fields__)


def _same(a: object, b: object) -> bool:
    """Exact equality of two log fields: tuples (text) as tuples, arrays with NaN equal to NaN."""
    return a == b if isinstance(a, tuple) else bool(np.array_equal(a, b, equal_nan=True))


@dataclass(frozen=True)
class FrameLog:
    """One row per processed frame.

    Attributes:
        t_s: float64 ``(M,)`` capture time, seconds.
        position_ned_m: float64 ``(M, 3)`` vehicle centre at capture, NED metres.
        attitude_rad: float64 ``(M, 3)`` roll, pitch, yaw at capture, radians (with the position: the
            pose the frame was seen from).
        region_depths_m: float64 ``(M, 9)`` refined region depths, metres, NaN unknown.
        kind: int8 ``(M,)`` :class:`LogKind` (CLEAR, AVOID, BRAKE) of the frame's decision.
        yaw, pitch: float64 ``(M,)`` the decision's outputs.
        reason: the decision's one-line reason per frame.
    """

    t_s: np.ndarray
    position_ned_m: np.ndarray
    attitude_rad: np.ndarray
    region_depths_m: np.ndarray
    kind: np.ndarray
    yaw: np.ndarray
    pitch: np.ndarray
    reason: tuple[str, ...]


@dataclass(frozen=True)
class FlightTiming:
    """Instrumentation (wall clock: not deterministic, excluded from result equality).

    Attributes:
        wall_s: wall-clock duration of the whole flight, seconds.
        pipeline_ms: median pipeline time per frame, milliseconds.
        render_ms: median render time per frame, milliseconds.
    """

    wall_s: float
    pipeline_ms: float
    render_ms: float


@dataclass(frozen=True)
class FlightResult:
    """The verdict on one flight.

    Attributes:
        course: the course flown.
        outcome: how it ended.
        success: goal, or held where the course counts holding as success.
        time_s: simulated time at the end, seconds.
        path_length_m: length of the flown path (centre), metres.
        min_clearance_m: smallest ground-truth clearance along the flight, metres (negative on collision).
        min_clearance_at_ned_m: where that was, float64 ``(3,)`` NED metres.
        final_position_ned_m: float64 ``(3,)`` NED metres.
        collision_radius_m: the vehicle's collision radius, metres.
        frames: frames processed.
        decisions: frames per decision kind ("clear", "avoid", "brake").
        reason: one line saying why the flight ended.
        hold_reason: why the flight held, when it did (the progress watchdog, a dead end), else "".
        detours: times the planner entered its detour mode.
        frames_lost: frames the pipeline failed on (a broken frame, a GPU fault), which the service
            would lose too; ``reason`` then says the last.
        log: the setpoint-rate log.
        frame_log: the per-frame log.
        timing: wall-clock instrumentation (not compared).
    """

    course: Course
    outcome: Outcome
    success: bool
    time_s: float
    path_length_m: float
    min_clearance_m: float
    min_clearance_at_ned_m: np.ndarray = field(compare=False)
    final_position_ned_m: np.ndarray = field(compare=False)
    collision_radius_m: float = 0.25
    frames: int = 0
    decisions: dict[str, int] = field(default_factory=dict)
    reason: str = ""
    hold_reason: str = ""
    detours: int = 0
    frames_lost: int = 0
    log: FlightLog | None = field(default=None, compare=False)
    frame_log: FrameLog | None = field(default=None, compare=False)
    timing: FlightTiming | None = field(default=None, compare=False)

    def summary(self) -> str:
        """One line: course, outcome, clearance, path length, time."""
        return (
            f"{self.course.name}: {self.outcome.value}{'' if self.success else ' (FAIL)'}, min clearance "
            f"{self.min_clearance_m:.2f} m, path {self.path_length_m:.1f} m, time {self.time_s:.1f} s"
        )


@dataclass(frozen=True)
class SimStep:
    """What the loop commanded at one setpoint tick (for a live view of the flight).

    Attributes:
        t_s: simulated time, seconds.
        setpoint: the setpoint sent (zero while not in offboard).
        kind: what it was (:class:`LogKind`).
        result: the newest applied pipeline result, or None before the first.
        frame_age_s: how old that result's frame was, seconds (None before the first).
        position_ned_m, velocity_ned_m_s: float64 ``(3,)`` the vehicle's, NED, metres and m/s.
        attitude_rad: float64 ``(3,)`` roll, pitch, yaw, radians.
        in_offboard: the vehicle is in offboard (else it was switched to HOLD).
    """

    t_s: float
    setpoint: VelocitySetpoint
    kind: LogKind
    result: FrameResult | None
    frame_age_s: float | None
    position_ned_m: np.ndarray
    velocity_ned_m_s: np.ndarray
    attitude_rad: np.ndarray
    in_offboard: bool


def simulator_config(cfg: CompanionConfig) -> CompanionConfig:
    """``cfg`` as the simulator flies it: the simulated rig is ideal and already rectified, so a
    calibration file (which describes a real camera) is dropped."""
    if cfg.calibration.file is None:
        return cfg
    return cfg.model_copy(update={"calibration": cfg.calibration.model_copy(update={"file": None})})


def simulated_rig_check_lines(cfg: CompanionConfig) -> list[str]:
    """The rig check of the rig the simulator flies (its ideal eyes, ``sim.eye_*_px``, and the
    calibration section's ideal field of view and baseline), in the words every tool prints."""
    from companion.core.geometry import StereoGeometry
    from companion.core.rig_check import check_rig, rig_check_lines

    sim = cfg.sim
    geometry = StereoGeometry.ideal(
        sim.eye_width_px, sim.eye_height_px, cfg.calibration.ideal_hfov_deg, cfg.calibration.ideal_baseline_m
    )
    return rig_check_lines(check_rig(geometry, cfg.stereo, cfg.regions, cfg.controller))


def make_camera(
    course: Course,
    cfg: CompanionConfig,
    vehicle: SimVehicle,
    pipeline: Pipeline,
    textures: TextureBank | None = None,
    fail_after_s: float | None = None,
) -> SimCamera:
    """The simulated ZED riding on ``vehicle``, with the rig the pipeline expects."""
    sim = cfg.sim
    return SimCamera(
        pipeline.geometry,
        course.scene,
        lambda: (vehicle.pose(), vehicle.time_s),
        seed=course.seed,
        realization=sim.realization,
        textures=textures,
        noise_std_grey=sim.noise_std_grey,
        exposure_step_interval_s=sim.exposure_step_interval_s,
        exposure_gain_range=sim.exposure_gain_range,
        eye_gain_mismatch=sim.eye_gain_mismatch,
        fail_after_s=fail_after_s,
    )


class _Rows:
    """Growing lists of log rows turned into arrays at the end."""

    def __init__(self) -> None:
        self.t: list[float] = []
        self.pos: list[np.ndarray] = []
        self.vel: list[np.ndarray] = []
        self.att: list[tuple[float, float, float]] = []
        self.kind: list[int] = []
        self.dyaw: list[float] = []
        self.dpitch: list[float] = []
        self.sp: list[tuple[float, float, float, float]] = []
        self.clear: list[float] = []
        self.frame_t: list[float] = []
        self.planner: list[str] = []


def fly(
    course: Course,
    cfg: CompanionConfig,
    *,
    textures: TextureBank | None = None,
    realtime: bool = False,
    camera_fail_after_s: float | None = None,
    on_frame: Callable[[Frame, FrameResult], None] | None = None,
    want_disparity: bool = False,
    on_step: Callable[[SimStep], None] | None = None,
    clock: Callable[[], float] = time.perf_counter,
    sleep: Callable[[float], None] = time.sleep,
) -> FlightResult:
    """Fly ``course`` closed-loop with the configuration ``cfg`` and score it.

    Args:
        course: the course.
        cfg: the whole configuration (pipeline, controller, command, and ``sim``).
        textures: a texture bank shared between flights (saves generating textures per flight).
        realtime: pace simulated time to the wall clock.
        camera_fail_after_s: the camera stops delivering frames from this simulated time on.
        on_frame: called with every frame and its pipeline result (overlays, recordings).
        want_disparity: ask the pipeline for the disparity image (for ``on_frame`` overlays).
        on_step: called at every setpoint tick with what was commanded (a live view).
        clock, sleep: wall clock and sleep, for ``realtime`` and the timing instrumentation.
    """
    # The planner's kernels compile once per process, before the flight's clock starts; a Ctrl-C
    # meanwhile is delivered after (the compiler's callbacks would drop it).
    with interrupt_after():
        use_cache_dir_or_memory(logger)
        compile_kernels()
    wall0 = clock()
    cfg = simulator_config(cfg)
    sim, cmd = cfg.sim, cfg.command
    pipeline = make_pipeline(cfg, sim.eye_width_px, sim.eye_height_px)
    params = VehicleParams.from_config(sim)
    vehicle = SimVehicle(params, course.start, seed=course.seed, realization=sim.realization)
    camera = make_camera(course, cfg, vehicle, pipeline, textures, camera_fail_after_s)
    camera.open()
    radius = params.collision_radius_m

    dt = 1.0 / sim.physics_rate_hz
    cam_period = 1.0 / sim.camera_rate_hz
    sp_period = 1.0 / sim.setpoint_rate_hz

    # Engage as the service does: a first (zero) setpoint, then offboard.
    vehicle.set_setpoint(ZERO_SETPOINT)
    vehicle.set_offboard()

    rows = _Rows()
    f_t: list[float] = []
    f_pos: list[np.ndarray] = []
    f_att: list[tuple[float, float, float]] = []
    f_depth: list[np.ndarray] = []
    f_kind: list[int] = []
    f_yaw: list[float] = []
    f_pitch: list[float] = []
    f_reason: list[str] = []
    pipe_ms: list[float] = []
    render_ms: list[float] = []

    pending: deque[tuple[float, FrameResult, Pose]] = deque()
    latest: FrameResult | None = None
    camera_ok = True
    n_cam = n_sp = 0
    goal = GoalSpec()  # the course: the start pose
    if sim.goal == "point":
        north, east, _ = course.goal_point_ned_m
        goal = GoalSpec(kind="point", north_m=north, east_m=east)
    start = np.asarray(course.start.position_ned_m, dtype=np.float64)
    progress = GoalProgress()  # the service's progress watchdog
    progress.engage(start, course.start.yaw_rad, goal)
    local = LocalStack(cfg)
    local.engage(start, course.start.yaw_rad, goal)
    stalled = False  # the progress watchdog (or a dead end) fired: the service pauses; here the flight holds
    hold_reason = ""
    detours = 0
    frames_lost = 0
    last_loss = ""
    judge = Judge(
        course,
        radius,
        sim.held_speed_m_s,
        sim.held_after_s,
        vehicle.model.position_ned_m,
        # With drift the velocity no longer tells whether the vehicle stays put: judge as with PX4.
        held_radius_m=HELD_RADIUS_M if sim.drift_speed_m_s > 0.0 else None,
    )
    sp = ZERO_SETPOINT
    kind = LogKind.NONE
    detouring = False
    planner = ""

    def log_row(t: float) -> None:
        m = vehicle.model
        rows.t.append(t)
        rows.pos.append(m.position_ned_m.copy())
        rows.vel.append(m.velocity_ned_m_s.copy())
        rows.att.append((m.roll_rad, m.pitch_rad, m.yaw_rad))
        rows.kind.append(int(kind))
        d = latest.decision if latest is not None else None
        rows.dyaw.append(d.yaw if d is not None else 0.0)
        rows.dpitch.append(d.pitch if d is not None else 0.0)
        rows.sp.append((sp.forward_m_s, sp.right_m_s, sp.down_m_s, sp.yaw_rate_deg_s))
        rows.clear.append(judge.clearance_m)
        rows.frame_t.append(latest.timestamp_s if latest is not None else math.nan)
        rows.planner.append(planner)

    while True:
        t = vehicle.time_s
        # -- camera: capture now, decision applies after the processing latency
        if camera_ok and t >= n_cam * cam_period - _EPS_S:
            n_cam += 1
            try:
                r0 = clock()
                frame = camera.read()
            except CameraError:
                camera_ok = False  # a camera that stopped delivering: the setpoint rule takes over
            else:
                p0 = clock()
                try:
                    res = pipeline.process(frame.image, frame.timestamp_s, want_disparity=want_disparity)
                except CompanionError as err:  # lost, as the service loses it: the frames age, the filters act
                    frames_lost += 1
                    last_loss = str(err)
                else:
                    p1 = clock()
                    render_ms.append((p0 - r0) * 1e3)
                    pipe_ms.append((p1 - p0) * 1e3)
                    pending.append((frame.timestamp_s + sim.processing_latency_s, res, vehicle.pose()))
                    f_t.append(frame.timestamp_s)
                    f_pos.append(vehicle.model.position_ned_m.copy())
                    f_att.append((vehicle.model.roll_rad, vehicle.model.pitch_rad, vehicle.model.yaw_rad))
                    f_depth.append(np.asarray(res.refined.depth_m, dtype=np.float64).copy())
                    f_kind.append(int(_KIND_OF[res.decision.kind]))
                    f_yaw.append(res.decision.yaw)
                    f_pitch.append(res.decision.pitch)
                    f_reason.append(res.decision.reason)
                    if on_frame is not None:
                        on_frame(frame, res)
        while pending and pending[0][0] <= t + _EPS_S:
            _, latest, seen_from = pending.popleft()
            if latest.near_blocks is not None:
                local.add_frame(latest.near_blocks, pipeline.geometry, cfg.planner.block_px, seen_from, latest.timestamp_s)

        # -- setpoint, at the service's rate and by the service's rule
        if t >= n_sp * sp_period - _EPS_S:
            n_sp += 1
            age = t - latest.timestamp_s if latest is not None else t
            if vehicle.in_offboard and age > cmd.failsafe_timeout_s:
                vehicle.set_hold()
            decision = latest.decision if latest is not None else None
            m = vehicle.model
            if not stalled and progress.no_progress(m.position_ned_m, t, cmd.progress_step_m, cfg.planner.no_progress_timeout_s):
                stalled = True  # the service's watchdog, as the service applies it
                hold_reason = "progress watchdog (no_progress)"
                local.stop(hold_reason)
            if stalled and decision is not None:
                decision = NO_PROGRESS_HOLD
            step = local.step(t, age, decision, latest.refined.depth_m if latest is not None else None,
                              m.position_ned_m, m.velocity_ned_m_s, m.yaw_rad)
            sp = step.setpoint
            if not stalled and local.holding_reason is not None:
                stalled, hold_reason = True, local.holding_reason
            planner = f"{step.plan.mode.value}: {step.plan.reason}"
            detours += int(step.plan.mode.value == "detour" and not detouring)
            detouring = step.plan.mode.value == "detour"
            if vehicle.in_offboard:
                vehicle.set_setpoint(sp)
                if decision is None:
                    kind = LogKind.NONE
                elif age > cmd.stale_frame_timeout_s:
                    kind = LogKind.STALE
                elif detouring:
                    kind = LogKind.DETOUR
                else:
                    kind = _KIND_OF[decision.kind]
            else:
                sp, kind = ZERO_SETPOINT, LogKind.HOLD
            log_row(t)
            if on_step is not None:
                on_step(
                    SimStep(
                        t_s=t,
                        setpoint=sp,
                        kind=kind,
                        result=latest,
                        frame_age_s=age if latest is not None else None,
                        position_ned_m=m.position_ned_m.copy(),
                        velocity_ned_m_s=m.velocity_ned_m_s.copy(),
                        attitude_rad=np.array([m.roll_rad, m.pitch_rad, m.yaw_rad]),
                        in_offboard=vehicle.in_offboard,
                    )
                )
            if realtime:
                delay = wall0 + t - clock()
                if delay > 0.0:
                    sleep(delay)

        # -- physics and the verdict
        vehicle.step(dt)
        m = vehicle.model
        if judge.update(vehicle.time_s, m.position_ned_m, m.speed_m_s, m.yaw_rate_rad_s) is not None:
            log_row(vehicle.time_s)
            break

    camera.close()
    counts = {k.value: 0 for k in DecisionKind}
    for code in f_kind:
        counts[LogKind(code).name.lower()] += 1
    log = FlightLog(
        t_s=np.asarray(rows.t, dtype=np.float64),
        position_ned_m=np.asarray(rows.pos, dtype=np.float64).reshape(-1, 3),
        velocity_ned_m_s=np.asarray(rows.vel, dtype=np.float64).reshape(-1, 3),
        attitude_rad=np.asarray(rows.att, dtype=np.float64).reshape(-1, 3),
        kind=np.asarray(rows.kind, dtype=np.int8),
        decision_yaw=np.asarray(rows.dyaw, dtype=np.float64),
        decision_pitch=np.asarray(rows.dpitch, dtype=np.float64),
        setpoint=np.asarray(rows.sp, dtype=np.float64).reshape(-1, 4),
        clearance_m=np.asarray(rows.clear, dtype=np.float64),
        frame_t_s=np.asarray(rows.frame_t, dtype=np.float64),
        planner=tuple(rows.planner),
    )
    frame_log = FrameLog(
        t_s=np.asarray(f_t, dtype=np.float64),
        position_ned_m=np.asarray(f_pos, dtype=np.float64).reshape(-1, 3),
        attitude_rad=np.asarray(f_att, dtype=np.float64).reshape(-1, 3),
        region_depths_m=np.asarray(f_depth, dtype=np.float64).reshape(-1, 9),
        kind=np.asarray(f_kind, dtype=np.int8),
        yaw=np.asarray(f_yaw, dtype=np.float64),
        pitch=np.asarray(f_pitch, dtype=np.float64),
        reason=tuple(f_reason),
    )
    timing = FlightTiming(
        wall_s=clock() - wall0,
        pipeline_ms=float(np.median(pipe_ms)) if pipe_ms else 0.0,
        render_ms=float(np.median(render_ms)) if render_ms else 0.0,
    )
    outcome = judge.outcome
    assert outcome is not None
    return FlightResult(
        course=course,
        outcome=outcome,
        success=judge.success,
        time_s=vehicle.time_s,
        path_length_m=judge.path_length_m,
        min_clearance_m=judge.min_clearance_m,
        min_clearance_at_ned_m=judge.min_clearance_at_ned_m,
        final_position_ned_m=judge.position_ned_m,
        collision_radius_m=radius,
        frames=len(f_t),
        decisions=counts,
        reason=judge.reason + (f"; {frames_lost} frames lost, the last: {last_loss}" if frames_lost else ""),
        hold_reason=hold_reason,
        frames_lost=frames_lost,
        detours=detours,
        log=log,
        frame_log=frame_log,
        timing=timing,
    )
