"""The closed loop flies the product's pipeline: deterministic, avoids, holds, stops on stale frames,
and really uses the configuration. Small images (the simulator's default 336x188) and short courses."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import CompanionConfig, apply_patch
from companion.core.types import DecisionKind
from companion.sim.camera import make_texture_bank
from companion.sim.courses import head_on_course, make_course
from companion.sim.loop import FlightResult, LogKind, fly
from companion.sim.scoring import Outcome

CFG = CompanionConfig()


@pytest.fixture(scope="module")
def bank():
    return make_texture_bank()


@pytest.fixture(scope="module")
def head_on(bank) -> FlightResult:
    return fly(head_on_course(seed=1, box_north_m=4.0, box_width_m=0.6), CFG, textures=bank)


def test_same_seed_same_flight(bank, head_on: FlightResult) -> None:
    again = fly(head_on_course(seed=1, box_north_m=4.0, box_width_m=0.6), CFG, textures=make_texture_bank())
    assert again == head_on  # outcome, time, path length, clearance, decision counts
    assert again.log is not None and head_on.log is not None
    assert again.log.equals(head_on.log)
    np.testing.assert_array_equal(again.frame_log.region_depths_m, head_on.frame_log.region_depths_m)


def test_a_realization_draws_other_noise_and_exposure_on_the_same_course(bank) -> None:
    """sim.realization: the same course (geometry, textures) under another draw of the sensor noise,
    the exposure steps and the eyes' mismatch; 0 is the seed's own draws, and each draw repeats."""
    from companion.core.geometry import StereoGeometry
    from companion.sim.camera import SimCamera
    from companion.sim.render import Pose

    course = make_course("pitch", 1)
    geometry = StereoGeometry.ideal(96, 64, hfov_deg=90.0, baseline_m=0.12)
    pose = Pose.at(1.0, 0.0, 1.5)

    def frames(realization: int, noise: float, t_s: float = 3.0) -> np.ndarray:
        cam = SimCamera(
            geometry, course.scene, lambda: (pose, t_s), seed=course.seed, realization=realization,
            textures=bank, noise_std_grey=noise, exposure_step_interval_s=2.0,
            exposure_gain_range=(0.8, 1.2), eye_gain_mismatch=0.04,
        )
        cam.open()
        return np.stack([cam.read().image for _ in range(2)])

    seed_own = frames(0, 2.0)
    assert np.array_equal(frames(0, 2.0), seed_own)
    other = frames(1, 2.0)
    assert not np.array_equal(other, seed_own) and np.array_equal(frames(1, 2.0), other)
    # What differs is drawn, not the course: without noise, exposure or mismatch the images are equal.
    plain = [
        SimCamera(geometry, course.scene, lambda: (pose, 3.0), seed=course.seed, realization=r, textures=bank)
        for r in (0, 1)
    ]
    for cam in plain:
        cam.open()
    assert np.array_equal(plain[0].read().image, plain[1].read().image)


def test_a_head_on_box_is_avoided(head_on: FlightResult) -> None:
    assert head_on.outcome is Outcome.GOAL, head_on.reason
    assert head_on.min_clearance_m > 0.05
    log = head_on.log
    assert log is not None
    # It did have to avoid: the local planner left its cruise mode to go round the box.
    assert any(p.split(":", 1)[0] in ("avoid", "detour") for p in log.planner), set(log.planner)
    # The path went around the box (0.6 m wide, dead ahead): at the box the vehicle was off the line.
    at_box = np.argmin(np.abs(log.position_ned_m[:, 0] - 4.0))
    assert abs(log.position_ned_m[at_box, 1]) > 0.3 + 0.25


def test_a_wide_head_on_box_is_gone_round(bank) -> None:
    """A box wider than the centre's view when it comes near (here 1.4 m at 2.25 m: +-17 deg) reaches
    into the left and right regions too: every region's robust minimum is the box, the paper's rules
    cancel, and the controller brakes. The local planner goes round the box to the goal."""
    course = head_on_course(seed=1, box_north_m=4.0, box_width_m=1.4)
    result = fly(course, CFG, textures=bank)
    assert result.outcome is Outcome.GOAL and result.min_clearance_m > 0.15, result.reason


def test_at_the_cameras_default_30_fps_the_boxes_are_avoided_and_gone_round(bank) -> None:
    """The simulator's camera runs at 15 Hz by default; the service's camera defaults to 30 fps
    (camera.fps_hz). The same config flies the same courses at that rate: the narrow box avoided,
    the wide one gone round (the timed settings mean the same time at either rate)."""
    fast = apply_patch(CFG, {"sim": {"camera_rate_hz": float(CFG.camera.fps_hz)}})
    assert fast.sim.camera_rate_hz == 30.0
    narrow = fly(head_on_course(seed=1, box_north_m=4.0, box_width_m=0.6), fast, textures=bank)
    assert narrow.outcome is Outcome.GOAL and narrow.min_clearance_m > 0.05, narrow.reason
    assert narrow.frames == pytest.approx(narrow.time_s * 30.0, abs=2)
    wide = fly(head_on_course(seed=1, box_north_m=4.0, box_width_m=1.4), fast, textures=bank)
    assert wide.outcome is Outcome.GOAL and wide.min_clearance_m > 0.15, wide.reason


def test_log_shapes_and_units(head_on: FlightResult) -> None:
    log = head_on.log
    assert log is not None
    n = log.t_s.shape[0]
    assert log.position_ned_m.shape == (n, 3) and log.setpoint.shape == (n, 4)
    assert np.all(np.diff(log.t_s) > 0)
    # setpoints at 20 Hz
    assert np.median(np.diff(log.t_s)) == pytest.approx(1.0 / CFG.sim.setpoint_rate_hz)
    assert head_on.frames == pytest.approx(head_on.time_s * CFG.sim.camera_rate_hz, abs=2)
    assert np.min(log.clearance_m) == pytest.approx(head_on.min_clearance_m, abs=0.02)
    assert head_on.path_length_m >= head_on.course.goal_north_m


def test_the_dead_end_ends_in_a_hold_not_a_collision(bank) -> None:
    result = fly(make_course("deadend", 1), CFG, textures=bank)
    assert result.outcome is Outcome.HELD, result.reason
    assert result.success and result.min_clearance_m > 0.1
    assert result.log is not None and np.any(result.log.kind == LogKind.BRAKE)


def test_stale_frames_stop_the_vehicle(bank) -> None:
    """The camera stops delivering at 2 s: the newest decision goes stale after the stale timeout,
    setpoint_for then commands zero, and the vehicle stops within its lag."""
    fail_s = 2.02  # not on a frame instant (2.0 = 30 frames at 15 Hz)
    result = fly(head_on_course(seed=2, box_north_m=25.0), CFG, textures=bank, camera_fail_after_s=fail_s)
    log = result.log
    assert log is not None
    cmd, sim = CFG.command, CFG.sim
    # The last frame was captured just before fail_s, its decision applied a latency later.
    stale_at = fail_s + cmd.stale_frame_timeout_s
    after = log.t_s > stale_at + 1.0 / sim.setpoint_rate_hz + 1e-9
    assert np.all(log.kind[after] != LogKind.CLEAR) and np.all(log.setpoint[after] == 0.0)
    assert np.any(log.kind[after] == LogKind.STALE)
    # Slowing from the first zero on, as the autopilot's response allows: after its delay, the fast
    # lag's share gone within three of its time constants (the deceleration limit permitting), the
    # slow lag's share (an autopilot's velocity integrator) decaying after.
    speed = np.linalg.norm(log.velocity_ned_m_s, axis=1)
    zero_from = stale_at + 1.0 / sim.setpoint_rate_hz + sim.response_delay_s
    v0 = float(speed[np.searchsorted(log.t_s, zero_from)])
    assert np.all(np.diff(speed[log.t_s >= zero_from + 0.05]) <= 1e-9)
    fast_by = zero_from + max(3.0 * sim.velocity_time_constant_s, v0 / sim.max_horizontal_accel_m_s2) + 0.2
    assert np.all(speed[log.t_s >= fast_by] < (sim.slow_response_fraction + 0.05) * v0 + 0.05)
    assert result.outcome is Outcome.HELD and result.min_clearance_m > 1.0
    assert result.frames == int(math.ceil(fail_s * sim.camera_rate_hz))


def test_failsafe_switches_to_hold_after_the_failsafe_timeout(bank) -> None:
    cfg = apply_patch(CFG, {"sim": {"held_after_s": 10.0}})
    result = fly(head_on_course(seed=2, box_north_m=25.0), cfg, textures=bank, camera_fail_after_s=1.0)
    log = result.log
    assert log is not None and result.outcome is Outcome.HELD
    hold = log.t_s[log.kind == LogKind.HOLD]
    assert hold.size and hold[0] == pytest.approx(1.0 + cfg.command.failsafe_timeout_s, abs=0.1)


def test_retuned_membership_functions_change_the_flight(bank, head_on: FlightResult) -> None:
    # 'near' and 'far' a metre farther out: the same box is seen as near earlier.
    far_terms = {
        "near": {"shape": "left_shoulder", "params_m": [1.75, 3.25]},
        "far": {"shape": "right_shoulder", "params_m": [1.75, 3.25]},
    }
    cfg = apply_patch(CFG, {"controller": {"input_terms": far_terms}})
    result = fly(head_on_course(seed=1, box_north_m=4.0, box_width_m=0.6), cfg, textures=bank)
    assert result.log is not None and head_on.log is not None
    assert not result.log.equals(head_on.log)

    # The flight changed because the decision did: on the depths the default flight saw, the retuned
    # controller steers otherwise (the local planner goes round before the centre region reads near,
    # and the controller's steer is a term of its cost).
    from companion.core.fuzzy.avoidance import AvoidanceController

    assert head_on.frame_log is not None
    default, retuned = (AvoidanceController(c.controller) for c in (CFG, cfg))

    def out(c: AvoidanceController, depths: np.ndarray) -> tuple[DecisionKind, float, float]:
        d = c.decide(depths)
        return d.kind, round(d.yaw, 3), round(d.pitch, 3)

    assert any(out(default, d) != out(retuned, d) for d in head_on.frame_log.region_depths_m)


def test_realtime_paces_simulated_time_to_the_clock(bank) -> None:
    now = {"t": 100.0}
    slept: list[float] = []

    def clock() -> float:
        return now["t"]

    def sleep(s: float) -> None:
        slept.append(s)
        now["t"] += s

    result = fly(head_on_course(seed=2, box_north_m=25.0), CFG, textures=bank, camera_fail_after_s=0.5,
                 realtime=True, clock=clock, sleep=sleep)
    # The fake clock only moves when the loop sleeps: it slept the whole simulated flight.
    assert sum(slept) == pytest.approx(result.time_s, abs=0.1)
    assert result.timing is not None and result.timing.wall_s == pytest.approx(sum(slept))


def test_the_progress_watchdog_holds_the_flight(bank) -> None:
    """Nothing counts as progress (50 m steps): after the time to fly planner.no_progress_distance_m
    at cruise (9 m at 3 m/s: 3 s) the loop substitutes the watchdog's brake, as the service does, and
    the flight ends held where it stopped."""
    cfg = apply_patch(CFG, {"planner": {"no_progress_distance_m": 9.0}, "command": {"progress_step_m": 50.0}})
    assert cfg.planner.no_progress_timeout_s == pytest.approx(3.0)
    result = fly(head_on_course(seed=2, box_north_m=25.0), cfg, textures=bank)
    log = result.log
    assert log is not None and result.outcome is Outcome.HELD, result.reason
    braking = log.t_s[log.kind == LogKind.BRAKE]
    assert braking.size and braking[0] == pytest.approx(3.0, abs=0.1)
    assert np.all(log.kind[log.t_s > braking[0]] == LogKind.BRAKE)
    assert result.min_clearance_m > 1.0


def _pipelines_that_fault(monkeypatch, good_frames: int, device_lost: bool) -> None:
    """The flights' pipelines match ``good_frames`` frames, then every frame raises the error a CUDA
    fault becomes (:class:`peers.fakes.FaultingEstimator`)."""
    from companion.sim import loop
    from peers.fakes import FaultingEstimator

    real = loop.make_pipeline

    def make(cfg, width_px, height_px, **kwargs):
        pipeline = real(cfg, width_px, height_px, **kwargs)
        pipeline.estimator = FaultingEstimator(pipeline.estimator, good_frames, device_lost)
        return pipeline

    monkeypatch.setattr(loop, "make_pipeline", make)


def test_a_gpu_fault_mid_flight_costs_one_frame_and_the_cpu_engine_flies_on(bank, monkeypatch) -> None:
    _pipelines_that_fault(monkeypatch, good_frames=30, device_lost=True)
    result = fly(head_on_course(seed=1, box_north_m=4.0, box_width_m=0.6), CFG, textures=bank)
    assert result.success and result.outcome is Outcome.GOAL and result.min_clearance_m > 0.0
    assert result.frames_lost == 1 and "illegal memory access" in result.reason


def test_frames_the_pipeline_keeps_failing_on_stop_the_flight_safely(bank, monkeypatch) -> None:
    """Every frame failing from 1 s on (an error that leaves no fallback): the frames go stale, the
    vehicle stops, and the flight ends held, as the service would, saying why."""
    _pipelines_that_fault(monkeypatch, good_frames=15, device_lost=False)
    cfg = apply_patch(CFG, {"sim": {"held_after_s": 10.0}})
    result = fly(head_on_course(seed=2, box_north_m=25.0), cfg, textures=bank)
    assert result.outcome is Outcome.HELD and result.min_clearance_m > 1.0
    assert result.frames == 15 and result.frames_lost > 0 and "frames lost" in result.reason
