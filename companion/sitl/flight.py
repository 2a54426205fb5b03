"""One course with PX4 or ArduPilot SITL in the loop, and a suite of them.

A flight, as a user would fly it:

1. the pilot (ground station) brings the vehicle to the ground, disarmed, ready to arm;
2. the pilot takes off to the course's start altitude; PX4 ends the take-off in Hold (ArduCopter's
   pilot switches to LOITER);
3. the service starts (``companion run``, camera ``sim`` rendering from the pose PX4 reports);
4. once the hover is steady, the course is placed at the vehicle: its start at the vehicle's position,
   its north axis along the vehicle's heading, its ground the start altitude below it
   (:class:`~companion.core.placement.CoursePlacement`; a live ``set_config``), so the flight starts
   at the course's start pose;
5. ``engage`` on the service's control socket; the service streams setpoints and enters offboard
   (ArduCopter: GUIDED);
6. the autopilot's own position telemetry, in the course frame, is judged against the true geometry by the
   same :class:`~companion.sim.scoring.Judge` as the kinematic simulator (goal, collision, held,
   out of bounds, timeout; minimum clearance). On a collision or leaving the bounds the pilot takes
   over with Hold at once, as a safety pilot would;
7. ``disengage`` (the service leaves offboard to Hold), the pilot lands, the service is stopped.

The result is a :class:`~companion.sim.loop.FlightResult` like the kinematic simulator's (so the same
tables and plots), plus what only SITL shows (:class:`SitlFlight`).
"""

from __future__ import annotations

import asyncio
import logging
import math
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import CompanionConfig
from companion.service.camera_sim import placement_fields
from companion.sim.courses import Course
from companion.sim.loop import (
    FlightLog,
    FlightResult,
    FlightTiming,
    LogKind,
    simulator_config,
)
from companion.core.placement import CoursePlacement
from companion.sim.scoring import HELD_RADIUS_M, Judge, Outcome
from companion.sitl.ardupilot import SITL_PARAMS as ARDUPILOT_SITL_PARAMS
from companion.sitl.ardupilot import ArduPilotBuild, ArduPilotPilot, ArduPilotPorts, ArduPilotSitl
from companion.sitl.pilot import Pilot, Sample
from companion.sitl.px4 import Px4Ports, Px4Sitl, SitlError
from companion.sitl.service import ServiceProcess

log = logging.getLogger(__name__)

#: PX4 parameters the harness sets before every flight (what they do: docs/sitl.md).
SITL_PARAMS: dict[str, float | int] = {
    "COM_OF_LOSS_T": 0.5,  # offboard setpoints missing this long = offboard loss, seconds
    "COM_OBL_RC_ACT": 5,  # offboard loss -> Hold
    # SIH only, never on a real vehicle: EKF2's noise model raised to SIH's simulated IMU noise
    # (simulator_sih/sih.cpp, armed: accel sigma 0.5/1.7/1.4 m/s^2, gyro 0.14/0.07/0.03 rad/s per 250 Hz
    # sample). With the defaults (0.35, 0.015) EKF2 trusted its IMU prediction too much: against SIH's
    # ground truth (in PX4's ULog) its yaw drifted 20-30 deg and its velocity 0.3-0.5 m/s within a
    # minute, so the vehicle crabbed 20-30 deg off where its camera looked. With these: 2-6 deg.
    "EKF2_GYR_NOISE": 0.1,
    "EKF2_ACC_NOISE": 1.0,
}


_KIND = {"clear": LogKind.CLEAR, "avoid": LogKind.AVOID, "brake": LogKind.BRAKE}

#: The parameters the harness sets before every flight, per autopilot.
PARAMS_BY_AUTOPILOT: dict[str, dict[str, float | int]] = {"px4": SITL_PARAMS, "ardupilot": ARDUPILOT_SITL_PARAMS}


@dataclass(frozen=True)
class SitlFlight:
    """One SITL flight.

    Attributes:
        result: the verdict, shaped like the kinematic simulator's (times from engagement, positions
            in the course frame).
        placement: where the course lay in the autopilot's local frame.
        engage_s: from the ``engage`` request to the autopilot reporting OFFBOARD (GUIDED), seconds.
        px4_modes: the autopilot's mode changes during the judged flight, ``(seconds since engagement,
            mode)`` (PX4's or ArduCopter's names).
        service_exit_code: the service's exit code after SIGTERM (0 = clean).
        max_speed_m_s: highest ground speed PX4 reported while judged, m/s.
    """

    result: FlightResult
    placement: CoursePlacement
    engage_s: float
    px4_modes: tuple[tuple[float, str], ...] = field(default=())
    service_exit_code: int | None = None
    max_speed_m_s: float = 0.0


def sitl_config(
    cfg: CompanionConfig, course: Course, placement: CoursePlacement, connection: str, workdir: Path, system_id: int | None = None
) -> CompanionConfig:
    """The service's config for a SITL flight: ``cfg`` with the camera rendering ``course`` from the
    telemetry pose (the simulator's eye size, frame rate and noise), the vehicle link on
    ``connection`` (PX4's API link) as a component of the autopilot's ``system_id`` (when given), ZeroMQ on
    private ``ipc://`` endpoints in ``workdir``, and no calibration file (the rendered rig is ideal)."""
    cfg = simulator_config(cfg)
    sim = cfg.sim
    camera = cfg.camera.model_copy(
        update={
            "source": "sim",
            "width_px": sim.eye_width_px,
            "height_px": sim.eye_height_px,
            "fps_hz": sim.camera_rate_hz,
            "sim_world": "course",
            "sim_course": course.kind,
            "sim_course_seed": course.seed,
            "sim_pose": "telemetry",
            **placement_fields(placement),
            "sim_noise_grey": sim.noise_std_grey,
        }
    )
    data = cfg.model_dump(mode="python")
    data["camera"] = camera.model_dump(mode="python")
    data["vehicle"]["connection"] = connection
    if system_id is not None:
        data["vehicle"]["system_id"] = int(system_id)
    data["bus"].update(
        health_endpoint=f"ipc://{workdir}/health.sock", control_endpoint=f"ipc://{workdir}/control.sock"
    )
    data["view"]["preview_endpoint"] = f"ipc://{workdir}/preview.sock"
    data["service"]["autostart"] = False
    return CompanionConfig.model_validate(data)


class _Recorder:
    """Judges the autopilot's telemetry and keeps the rows of the flight log.

    Args:
        offboard_mode: the autopilot's mode the service commands in (``OFFBOARD``, ``GUIDED``);
            rows in any other mode are logged as the pilot's hold.
    """

    def __init__(
        self, course: Course, cfg: CompanionConfig, placement: CoursePlacement, first: Sample, offboard_mode: str = "OFFBOARD"
    ) -> None:
        self.placement = placement
        self.offboard_mode = offboard_mode
        self.t0 = first.time_s
        self.judge = Judge(
            course,
            cfg.sim.collision_radius_m,
            cfg.sim.held_speed_m_s,
            cfg.sim.held_after_s,
            placement.position_in_course(first.position_ned_m),
            start_time_s=0.0,
            held_radius_m=HELD_RADIUS_M,
        )
        self.rows: dict[str, list[Any]] = {k: [] for k in ("t", "pos", "vel", "att", "kind", "dyaw", "dpitch", "sp", "clear", "planner")}
        self.max_speed = 0.0

    def add(self, s: Sample, health: dict[str, Any] | None) -> Outcome | None:
        t = s.time_s - self.t0
        pos = self.placement.position_in_course(s.position_ned_m)
        vel = self.placement.vector_in_course(s.velocity_ned_m_s)
        speed = float(np.linalg.norm(vel))
        self.max_speed = max(self.max_speed, speed)
        outcome = self.judge.update(t, pos, speed, s.yaw_rate_rad_s)
        att = s.attitude_rad.copy()
        att[2] = math.remainder(att[2] - self.placement.yaw_rad, 2.0 * math.pi)
        h = health or {}
        state = h.get("state")
        decision = h.get("decision") or {}
        if s.flight_mode != self.offboard_mode:
            kind = LogKind.HOLD
        elif state == "degraded":
            kind = LogKind.STALE
        elif state == "paused":
            kind = LogKind.BRAKE  # holding (the progress watchdog, or an operator's pause), as the simulator logs it
        else:
            kind = _KIND.get(decision.get("kind"), LogKind.NONE)
        sp = h.get("setpoint") or {}
        r = self.rows
        r["t"].append(t)
        r["pos"].append(pos)
        r["vel"].append(vel)
        r["att"].append(att)
        r["kind"].append(int(kind))
        r["dyaw"].append(float(h.get("yaw") or 0.0))
        r["dpitch"].append(float(h.get("pitch") or 0.0))
        r["sp"].append(tuple(float(sp.get(k) or 0.0) for k in ("forward_m_s", "right_m_s", "down_m_s", "yaw_rate_deg_s")))
        r["clear"].append(self.judge.clearance_m)
        r["planner"].append(_planner_text(state, h))
        return outcome

    def log(self) -> FlightLog:
        r = self.rows
        return FlightLog(
            t_s=np.asarray(r["t"], dtype=np.float64),
            position_ned_m=np.asarray(r["pos"], dtype=np.float64).reshape(-1, 3),
            velocity_ned_m_s=np.asarray(r["vel"], dtype=np.float64).reshape(-1, 3),
            attitude_rad=np.asarray(r["att"], dtype=np.float64).reshape(-1, 3),
            kind=np.asarray(r["kind"], dtype=np.int8),
            decision_yaw=np.asarray(r["dyaw"], dtype=np.float64),
            decision_pitch=np.asarray(r["dpitch"], dtype=np.float64),
            setpoint=np.asarray(r["sp"], dtype=np.float64).reshape(-1, 4),
            clearance_m=np.asarray(r["clear"], dtype=np.float64),
            frame_t_s=np.full(len(r["t"]), math.nan),  # health gives the frame's age, not this clock's time
            planner=tuple(r["planner"]),
        )


def _planner_text(state: object, health: dict[str, Any]) -> str:
    """:attr:`FlightLog.planner` from a health message: ``held: reason`` while paused, the local
    planner's ``mode: reason`` while it flies, else ""."""
    if state == "paused":
        return f"held: {health.get('reason') or ''}"
    plan = health.get("planner") or {}
    mode = plan.get("mode")
    return "" if mode is None else f"{mode}: {plan.get('reason') or ''}"


def placement_at(pilot: Pilot, course: Course) -> CoursePlacement:
    """The course placed at the vehicle now: its start at the vehicle's position, its north along the
    vehicle's heading, its ground the course's start altitude below the vehicle (whatever height
    PX4's estimator put the ground at), so that the flight starts at the course's start pose."""
    hover = pilot.latest()
    start_altitude_m = -float(course.start.position_ned_m[2])
    n, e, d = (float(x) for x in hover.position_ned_m)
    return CoursePlacement((n, e, d + start_altitude_m), float(hover.attitude_rad[2]))


async def prepare_flight(
    course: Course,
    cfg: CompanionConfig,
    pilot: Pilot,
    ports: Px4Ports | ArduPilotPorts,
    workdir: Path,
    service_log_level: str = "INFO",
    service_url: str | None = None,
) -> ServiceProcess:
    """Steps 1 and 2 (ready, parameters, take-off); returns the service of step 4, not yet started
    (its config has the course placed where the vehicle hovers now; :func:`start_and_place` moves it)."""
    await pilot.make_ready()
    await pilot.set_params(PARAMS_BY_AUTOPILOT[pilot.AUTOPILOT])
    await pilot.take_off(-float(course.start.position_ned_m[2]))
    service_cfg = sitl_config(
        cfg, course, placement_at(pilot, course), service_url or ports.service_url, workdir, ports.system_id
    )
    return ServiceProcess(service_cfg, workdir, service_log_level)


async def start_and_place(service: ServiceProcess, pilot: Pilot, course: Course) -> CoursePlacement:
    """Steps 4 and 3: start the service, wait for a steady hover, and place the course at the vehicle
    *now* with a live ``set_config`` of ``camera.sim_origin_*`` (the hover drifts while the service
    starts: a placement taken earlier would start the flight off the course's start pose). When
    either step fails, the service is stopped before the error goes on: nothing is left running."""
    await service.start()
    try:
        return await place_course(service, pilot, course)
    except BaseException:
        await service.stop()
        raise


def placement_patch(cfg: CompanionConfig, placement: CoursePlacement) -> dict[str, dict[str, float]]:
    """The live ``set_config`` patch that puts the service's course at ``placement``: the camera's
    ``sim_origin_*``, and the local planner's band (``planner.floor_m``, ``planner.ceiling_m`` of
    ``cfg``, the user's) moved to the same height over the course's ground as the user set over the
    take-off point.

    The course's ground lies ``placement.origin_ned_m[2]`` metres below the autopilot's local origin
    (:func:`placement_at`: wherever the hover put it, 0.17–0.19 m *above* PX4's take-off ground in
    one flight), and the rendered floor and the judge's are the course's. Left at the take-off point,
    a 0.5 m floor stood ~0.32 m over that ground, within the autopilot's lag of the collision sphere,
    and a 3 m ceiling stood 0.6 m over the course's 3 m walls: the planner climbed to fly over them,
    into the wall's top.
    """
    ground_down_m = float(placement.origin_ned_m[2])
    p = cfg.planner
    band_floor = max(0.0, p.floor_m - ground_down_m)
    band = {"floor_m": band_floor, "ceiling_m": max(band_floor + 0.1, p.ceiling_m - ground_down_m)}
    return {"camera": placement_fields(placement), "planner": band}


async def place_course(service: ServiceProcess, pilot: Pilot, course: Course) -> CoursePlacement:
    """Step 3 alone: wait for a steady hover and move the running service's course (and its floor:
    :func:`placement_patch`) under the vehicle."""
    await pilot.wait_steady(1.0)
    placement = placement_at(pilot, course)
    await service.request({"cmd": "set_config", "patch": placement_patch(service.cfg, placement)})
    return placement


async def fly_course(
    course: Course,
    cfg: CompanionConfig,
    pilot: Pilot,
    ports: Px4Ports | ArduPilotPorts,
    workdir: Path,
    *,
    service_log_level: str = "INFO",
    service_url: str | None = None,
) -> SitlFlight:
    """Fly ``course`` with PX4 or ArduPilot SITL (already running, ``pilot`` connected to it: a
    :class:`~companion.sitl.pilot.Pilot` or an :class:`~companion.sitl.ardupilot.ArduPilotPilot`) and
    the service.

    Raises:
        SitlError: the autopilot or the service did not do what a step needed (the step is named).
    """
    wall0 = time.monotonic()
    service = await prepare_flight(course, cfg, pilot, ports, workdir, service_log_level, service_url)
    exit_code: int | None = None
    try:
        placement = await start_and_place(service, pilot, course)
        t_req = time.monotonic()
        # The goal the simulator's flights have (sim.goal = "point"): the course's goal point, in the autopilot's frame.
        goal_local = placement.position_in_local(np.asarray(course.goal_point_ned_m, dtype=np.float64))
        goal = {"kind": "point", "north_m": float(goal_local[0]), "east_m": float(goal_local[1])}
        await service.request({"cmd": "engage", "goal": goal} if cfg.sim.goal == "point" else {"cmd": "engage"})
        t_offboard = await pilot.wait_for(f"{pilot.OFFBOARD_MODE} after engage", lambda: pilot.in_offboard, 10.0)
        recorder = _Recorder(course, cfg, placement, pilot.latest(), pilot.OFFBOARD_MODE)
        seen = len(pilot.samples)
        modes_from = len(pilot.mode_changes)
        outcome: Outcome | None = None
        while outcome is None:
            await asyncio.sleep(0.02)
            fresh = pilot.samples[seen:]
            seen += len(fresh)
            for s in fresh:
                outcome = recorder.add(s, service.health)
                if outcome is not None:
                    break
            if not fresh and time.monotonic() - pilot.latest().time_s > 2.0:
                raise SitlError(f"{pilot.NAME} position telemetry stopped for 2 s during the flight")
        if outcome in (Outcome.COLLISION, Outcome.OUT_OF_BOUNDS):
            await pilot.hold()  # the safety pilot takes over
        elif service.state in ("engaged", "engaging", "degraded", "paused", "override", "failsafe"):
            await service.request({"cmd": "disengage"})
            # Let the service finish leaving offboard (its Hold) before the pilot commands Land.
            await pilot.wait_for(
                f"{pilot.NAME} out of {pilot.OFFBOARD_MODE} after disengage", lambda: not pilot.in_offboard, 10.0
            )
            await service.wait_state(("disengaged", "passive"), 5.0)
        modes = tuple((t - recorder.t0, m) for t, m in pilot.mode_changes[modes_from:])
        await pilot.land()
    finally:
        exit_code = await service.stop()
    judge = recorder.judge
    assert judge.outcome is not None
    processed = [h.get("processed_frames", 0) for t, h in service.health_history if t >= t_offboard]
    frames = int(processed[-1] - processed[0]) if processed else 0
    flight_log = recorder.log()
    kinds = flight_log.kind
    result = FlightResult(
        course=course,
        outcome=judge.outcome,
        success=judge.success,
        time_s=float(flight_log.t_s[-1]) if len(flight_log.t_s) else 0.0,
        path_length_m=judge.path_length_m,
        min_clearance_m=judge.min_clearance_m,
        min_clearance_at_ned_m=judge.min_clearance_at_ned_m,
        final_position_ned_m=judge.position_ned_m,
        collision_radius_m=judge.radius_m,
        frames=frames,
        # Telemetry rows (50 Hz) per decision kind: the share of the flight each kind drove.
        decisions={name: int(np.count_nonzero(kinds == int(k))) for name, k in _KIND.items()},
        reason=judge.reason,
        log=flight_log,
        timing=FlightTiming(wall_s=time.monotonic() - wall0, pipeline_ms=float("nan"), render_ms=float("nan")),
    )
    return SitlFlight(
        result=result,
        placement=placement,
        engage_s=t_offboard - t_req,
        px4_modes=modes,
        service_exit_code=exit_code,
        max_speed_m_s=recorder.max_speed,
    )


def warm_backend(cfg: CompanionConfig) -> None:
    """Build the disparity backend of ``cfg`` once in this process and match one frame: a compiled
    backend (cpu-sgm) fills its on-disk cache, so that each flight's service loads the kernels instead
    of compiling them for a minute or more past the harness's wait for it to be ready."""
    from companion.backends import make_pipeline

    w, h = cfg.sim.eye_width_px, cfg.sim.eye_height_px
    frame = np.random.default_rng(0).integers(0, 256, (h, 2 * w, 3), dtype=np.uint8)
    make_pipeline(cfg, w, h).process(frame, 0.0)


async def fly_courses(
    courses: Sequence[Course],
    cfg: CompanionConfig,
    *,
    ports: Px4Ports | ArduPilotPorts,
    pilot_url: str,
    workdir: Path | None = None,
    px4_build: Path | None = None,
    ardupilot_build: ArduPilotBuild | None = None,
    progress: Callable[[int, int, SitlFlight], None] | None = None,
    service_log_level: str = "INFO",
    service_url: str | None = None,
) -> list[SitlFlight]:
    """Fly ``courses`` one after another, with PX4 (``ports`` a :class:`Px4Ports`) or ArduPilot
    (an :class:`~companion.sitl.ardupilot.ArduPilotPorts`).

    With ``px4_build`` (or ``ardupilot_build``), the autopilot is started fresh (new parameters and
    storage) for every course and stopped after it: every flight starts from the same vehicle. A course
    whose autopilot or service step fails is then flown once more with another fresh one (SIH sometimes
    starts without baro or compass data, fails its preflight checks and lands: a fault of the
    simulator's start, not a verdict on the service); its files are under ``retry/``. Without it, the
    autopilot must already be running on ``ports``; between courses the vehicle lands where it is, and
    the next course is placed under it. ``service_url`` overrides the service's vehicle link (default:
    the autopilot's API link of ``ports``).

    Raises:
        SitlError: the autopilot or the service failed a step (the course is named), twice with a build.
    """
    ardupilot = isinstance(ports, ArduPilotPorts)
    build: Any = ardupilot_build if ardupilot else px4_build
    await asyncio.to_thread(warm_backend, cfg)
    name = "ArduPilot" if ardupilot else "PX4"
    own_tmp = None
    if workdir is None:
        own_tmp = tempfile.TemporaryDirectory(prefix="companion-sitl-")
        workdir = Path(own_tmp.name)
    flights: list[SitlFlight] = []
    pilot: Pilot | None = None
    sitl: Px4Sitl | ArduPilotSitl | None = None
    try:
        for i, course in enumerate(courses):
            attempts = 2 if build is not None else 1
            for attempt in range(attempts):
                run_dir = workdir / f"{i:02d}-{course.name}"
                if attempt:
                    run_dir = run_dir / "retry"
                try:
                    if build is not None and sitl is None:
                        if ardupilot:
                            sitl = ArduPilotSitl(build, run_dir / "ardupilot", ports.instance)
                        else:
                            sitl = Px4Sitl(build, run_dir / "px4", ports.instance)
                        await asyncio.to_thread(sitl.start)
                    if pilot is None:
                        if ardupilot:
                            pilot = ArduPilotPilot(pilot_url, ports.system_id, rc_port=ports.rc_port)
                        else:
                            pilot = Pilot(pilot_url, ports.system_id)
                        await pilot.connect()
                    flight = await fly_course(
                        course, cfg, pilot, ports, run_dir / "service", service_log_level=service_log_level, service_url=service_url
                    )
                except SitlError as err:
                    if attempt + 1 == attempts:
                        raise SitlError(f"{course.name}: {err}") from None
                    log.warning("%s: %s; flying it again with a fresh %s", course.name, err, name)
                    continue
                finally:
                    if sitl is not None:  # a fresh autopilot (and a fresh link to it) for the next course or attempt
                        if pilot is not None:
                            await pilot.close()
                            pilot = None
                        await asyncio.to_thread(sitl.stop)
                        sitl = None
                flights.append(flight)
                if progress is not None:
                    progress(i + 1, len(courses), flight)
                break
    finally:
        if pilot is not None:
            await pilot.close()
        if sitl is not None:
            await asyncio.to_thread(sitl.stop)
        if own_tmp is not None:
            own_tmp.cleanup()
    return flights
