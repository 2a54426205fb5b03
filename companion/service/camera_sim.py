"""The ``sim`` camera source: side-by-side frames rendered by :mod:`companion.sim.render`, at a fixed
pose or at the vehicle's (the simulator's, or the autopilot's telemetry placed in the scene).

The renderer is imported only when a ``sim`` source is built: the flight service never loads it.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from companion.core.geometry import StereoGeometry
from companion.core.placement import CoursePlacement
from companion.core.pose import Pose
from companion.errors import CameraError
from companion.interfaces import Frame, VehicleState
from companion.pacing import RatePacer

if TYPE_CHECKING:
    from companion.config import CompanionConfig
    from companion.sim.render import Scene

Clock = Callable[[], float]
#: Returns the pose to render and when it was true, on the camera's clock (seconds). Raises
#: :class:`PoseUnavailable` while there is no usable pose.
PoseProvider = Callable[[], "tuple[Pose, float]"]


class PoseUnavailable(CameraError):
    """The pose provider has no usable pose now (none received yet, or too old)."""


class SimCamera:
    """Side-by-side frames rendered by :mod:`companion.sim.render` at ``fps_hz``.

    The pose comes from ``pose_provider`` (the simulator drives it from its vehicle's pose) or is the
    fixed ``pose``; with a fixed pose and no noise the frame is rendered once and handed out read-only.
    The rig is the ideal one of the calibration config (no calibration file), so the pipeline sees the
    same geometry the renderer used.

    Args:
        geometry: the rectified rig (one eye's size, focal length, baseline).
        scene: the world to draw.
        fps_hz: frame rate, Hz.
        pose: the fixed pose when there is no provider.
        pose_provider: called once per frame, in the capture thread; returns ``(pose, time_s)``, the
            frame is stamped with ``time_s``. While it raises :class:`PoseUnavailable`, ``read`` retries
            once per frame period for up to ``pose_wait_s``, then raises that CameraError (frames stop,
            so the service's stale-frame failsafe acts).
        noise_grey: per-frame Gaussian sensor noise, grey levels (0 = none).
        pose_wait_s: see ``pose_provider``, seconds.
    """

    def __init__(
        self,
        geometry,
        scene: Scene,
        fps_hz: float,
        *,
        pose: Pose | None = None,
        pose_provider: PoseProvider | None = None,
        noise_grey: float = 0.0,
        seed: int = 0,
        clock: Clock = time.monotonic,
        pose_wait_s: float = 1.0,
    ) -> None:
        self.name = "sim"
        self.geometry = geometry
        self.scene = scene
        self.fps_hz = fps_hz
        self.pose = pose if pose is not None else Pose.at(2.0, 0.0, 1.5)
        self.pose_provider = pose_provider
        self.noise_grey = noise_grey
        self.seed = seed
        self.pose_wait_s = pose_wait_s
        self._clock = clock
        self._stop = threading.Event()
        self._renderer = None
        self._rng = np.random.default_rng(seed)
        self._fixed: np.ndarray | None = None
        self._pacer: RatePacer | None = None
        self._seq = 0

    @property
    def eye_size_px(self) -> tuple[int, int]:
        return (self.geometry.width_px, self.geometry.height_px)

    def open(self) -> None:
        from companion.sim.render import StereoRenderer

        self._stop.clear()
        if self._renderer is None:
            self._renderer = StereoRenderer(self.geometry, self.scene, seed=self.seed)
        self._pacer = RatePacer(1.0 / self.fps_hz, self._clock, self._stop)

    def _render(self, pose: Pose) -> np.ndarray:
        from companion.sim.render import Photometry

        assert self._renderer is not None
        if self.noise_grey > 0:
            noise = Photometry(noise_std=self.noise_grey)
            return self._renderer.render_side_by_side(pose, left=noise, right=noise, rng=self._rng)
        return self._renderer.render_side_by_side(pose)

    def read(self) -> Frame:
        if self._renderer is None or self._pacer is None:
            raise CameraError("sim: not open")
        self._pacer.wait()
        if self.pose_provider is not None:
            pose, t = self._next_pose()
            image = self._render(pose)
            self._seq += 1
            return Frame(image=image, timestamp_s=t, seq=self._seq)
        if self.noise_grey > 0:
            image = self._render(self.pose)
        else:
            if self._fixed is None:
                self._fixed = self._render(self.pose)
                self._fixed.setflags(write=False)
            image = self._fixed
        t = self._clock()
        self._seq += 1
        return Frame(image=image, timestamp_s=t, seq=self._seq)

    def _next_pose(self) -> tuple[Pose, float]:
        assert self.pose_provider is not None
        deadline = self._clock() + self.pose_wait_s
        while True:
            try:
                pose, t = self.pose_provider()
            except PoseUnavailable:
                if self._clock() >= deadline or self._stop.is_set():
                    raise
                self._stop.wait(1.0 / self.fps_hz)
            except Exception as err:
                raise CameraError(f"sim: the pose provider failed: {type(err).__name__}: {err}") from err
            else:
                return pose, t

    def close(self) -> None:
        self._stop.set()


class TelemetryPose:
    """A pose provider that reads the vehicle link's telemetry (``state``: a vehicle link's ``state``):
    the newest local position and attitude, placed in the scene by :attr:`placement`, stamped with the
    time the position arrived.

    ``placement`` may be replaced at any time (the daemon does it on a live config change); a read uses
    the one it finds.

    Raises (when called): :class:`PoseUnavailable` when no position or attitude has arrived yet or the
    newest position is older than ``max_age_s`` seconds.
    """

    def __init__(
        self, state: Callable[[], VehicleState], placement: CoursePlacement, max_age_s: float, clock: Clock
    ) -> None:
        self._state = state
        self.placement = placement
        self.max_age_s = max_age_s
        self._clock = clock

    def __call__(self) -> tuple[Pose, float]:
        v = self._state()
        if v.position_ned_m is None or v.attitude_rad is None or v.position_timestamp_s is None:
            raise PoseUnavailable("sim: no vehicle pose from telemetry yet")
        age_s = self._clock() - v.position_timestamp_s
        if age_s > self.max_age_s:
            raise PoseUnavailable(
                f"sim: the vehicle's telemetry pose is {age_s:.2f} s old (camera.sim_pose_max_age_s = {self.max_age_s:g} s)"
            )
        return self.placement.pose_in_course(v.position_ned_m, v.attitude_rad), v.position_timestamp_s


def sim_scene_from_config(cfg: CompanionConfig) -> Scene:
    """The scene ``cfg.camera`` names: the corridor, or a course of the simulator's library."""
    from companion.sim.render import corridor_scene

    cam = cfg.camera
    if cam.sim_world == "course":
        from companion.sim.courses import make_course

        return make_course(cam.sim_course, cam.sim_course_seed).scene
    return corridor_scene(n_obstacles=cam.sim_obstacles, seed=cam.sim_scene_seed)


def placement_from_config(cfg: CompanionConfig) -> CoursePlacement:
    """Where ``cfg.camera.sim_origin_*`` puts the scene in the autopilot's local frame."""
    cam = cfg.camera
    return CoursePlacement(
        (cam.sim_origin_north_m, cam.sim_origin_east_m, cam.sim_origin_down_m), math.radians(cam.sim_origin_yaw_deg)
    )


def placement_fields(placement: CoursePlacement) -> dict[str, float]:
    """``camera.sim_origin_*`` for ``placement`` (the inverse of :func:`placement_from_config`)."""
    n, e, d = placement.origin_ned_m
    return {
        "sim_origin_north_m": n,
        "sim_origin_east_m": e,
        "sim_origin_down_m": d,
        "sim_origin_yaw_deg": math.degrees(placement.yaw_rad),
    }


def sim_camera_from_config(
    cfg: CompanionConfig, pose_provider: PoseProvider | None = None, clock: Clock = time.monotonic
) -> SimCamera:
    """The ``sim`` source of ``cfg.camera``: its scene (:func:`sim_scene_from_config`), the ideal rig of
    ``cfg.calibration``; the pose is fixed unless a ``pose_provider`` is given."""
    cam = cfg.camera
    geometry = StereoGeometry.ideal(
        cam.width_px, cam.height_px, hfov_deg=cfg.calibration.ideal_hfov_deg, baseline_m=cfg.calibration.ideal_baseline_m
    )
    scene = sim_scene_from_config(cfg)
    seed = cam.sim_course_seed if cam.sim_world == "course" else cam.sim_scene_seed
    pose = Pose.at(cam.sim_north_m, cam.sim_east_m, cam.sim_altitude_m, yaw_rad=math.radians(cam.sim_yaw_deg))
    return SimCamera(
        geometry,
        scene,
        cam.fps_hz,
        pose=pose,
        pose_provider=pose_provider,
        noise_grey=cam.sim_noise_grey,
        seed=seed,
        clock=clock,
    )

