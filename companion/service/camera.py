"""Camera sources behind :class:`~companion.interfaces.CameraSource`: ``uvc`` (a ZED or another
side-by-side camera over V4L2, or a pair of V4L2 cameras), ``replay`` (a recording) and ``sim`` (the
renderer).

Every ``read`` blocks in the capture thread and returns a :class:`~companion.interfaces.Frame` whose
image is a uint8 (H, 2W, 3) BGR side-by-side frame (a UVC camera sending YUYV: its (H, 2W, 2) bytes
as they come, with ``camera.pixels = "luma"``), timestamped with ``clock()`` (the process's
monotonic clock, seconds) when it was read. A source never reuses an image array it has handed out
unless that array is read-only (the consumer may still be processing it).

:func:`make_camera` builds the source the config names; the sources themselves live in
:mod:`~companion.service.camera_v4l2` (``uvc``: UVC and pair cameras), :mod:`~companion.service.camera_replay`
and :mod:`~companion.service.camera_sim`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from companion.errors import CameraError
from companion.interfaces import CameraSource
from companion.service.camera_replay import ReplayCamera
from companion.service.camera_sim import PoseProvider, sim_camera_from_config
from companion.service.camera_v4l2 import PairCamera, UvcCamera, wants_yuyv

if TYPE_CHECKING:
    from companion.config import CompanionConfig
    from companion.config.service import CameraConfig

log = logging.getLogger(__name__)

Clock = Callable[[], float]


def frame_channels(cam: CameraConfig) -> int:
    """Bytes per pixel of the frames the configured camera will give: 2 for a UVC camera whose YUYV
    bytes are taken as they come (``camera.pixels`` luma), else 3 (BGR). (Where the driver then
    refuses YUYV, the camera decodes BGR after all and its frames go to the GPU through a host copy.)"""
    yuyv = cam.source == "uvc" and cam.model != "pair" and wants_yuyv(cam.pixels, cam.fourcc)
    return 2 if yuyv else 3


def make_camera(
    cfg: CompanionConfig,
    pose_provider: PoseProvider | None = None,
    clock: Clock = time.monotonic,
    *,
    require_calibration: bool = True,
) -> CameraSource:
    """The camera source ``cfg.camera.source`` names (not yet opened).

    Args:
        cfg: the whole config (the camera section, and the calibration for the check below).
        pose_provider: the sim camera's pose source (else its fixed pose).
        clock: the frames' clock.
        require_calibration: refuse a non-ZED UVC camera (``camera.model`` sbs or pair) without a
            calibration file, as the service must (its depths would be wrong); tools that capture the
            views to make one (``companion record``, ``companion calibrate``) pass False.

    Raises:
        CameraError: a non-ZED camera without a calibration (see above), or a replay recording that
            does not exist (a startup error at once: it will not appear by waiting).
    """
    cam = cfg.camera
    if cam.source == "uvc":
        if cam.model != "zed" and cfg.calibration.file is None and require_calibration:
            raise CameraError(
                f"camera.model = {cam.model!r} needs a stereo calibration (calibration.file): without one every "
                "depth would be wrong. Make one with `companion calibrate stereo --live --config FILE --board "
                "chessboard:9x6:0.025 --out calib.yaml` (see docs/calibration.md)"
            )
        if cam.model == "pair":
            assert cam.device_right is not None  # the config validator guarantees it
            return PairCamera(
                cam.device, cam.device_right, cam.width_px, cam.height_px, cam.fps_hz, clock=clock,
                fourcc=cam.fourcc, max_skew_ms=cam.pair_max_skew_ms,
            )
        if cam.model == "zed" and cfg.calibration.file is None:
            log.warning(
                "camera: a ZED with no calibration file: the frames are taken as already rectified by an ideal "
                "%.2f m, %.0f deg rig; set calibration.file to the ZED's factory SN<serial>.conf for true depths",
                cfg.calibration.ideal_baseline_m, cfg.calibration.ideal_hfov_deg,
            )
        return UvcCamera(cam.device, cam.width_px, cam.height_px, cam.fps_hz, clock=clock, model=cam.model,
                         fourcc=cam.fourcc, pixels=cam.pixels)
    if cam.source == "replay":
        assert cam.replay_path is not None  # the config validator guarantees it
        if not Path(cam.replay_path).exists():
            raise CameraError(f"replay:{cam.replay_path}: no such recording (camera.replay_path)")
        from companion.recorded.sequence import is_sequence

        if is_sequence(cam.replay_path):
            from companion.recorded.camera import RecordedCamera

            return RecordedCamera(
                cam.replay_path, cam.width_px, cam.height_px, rate_hz=cam.replay_rate_hz, loop=cam.replay_loop,
                left_topic=cam.replay_left_topic, right_topic=cam.replay_right_topic,
                max_skew_ms=cam.replay_max_skew_ms, clock=clock,
            )
        return ReplayCamera(
            cam.replay_path,
            cam.width_px,
            cam.height_px,
            rate_hz=cam.replay_rate_hz,
            fallback_fps_hz=cam.fps_hz,
            loop=cam.replay_loop,
            preload=cam.replay_preload,
            clock=clock,
        )
    return sim_camera_from_config(cfg, pose_provider=pose_provider, clock=clock)
