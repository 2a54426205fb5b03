"""A UVC camera's YUYV bytes taken as they come (``camera.pixels = "luma"``): every CPU backend sees the
same grey as from the Y plane alone, and the service flies and previews on such frames."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import zmq
from peers.fakes import FakeLink, ServiceRunner, avoid_scene_camera, avoid_scene_preview_inputs, service_config

from companion.backends import make_pipeline
from companion.interfaces import Frame
from companion.service.daemon import Service
from companion.service.preview_frame import render_preview, unpack


def _yuyv(bgr: np.ndarray) -> np.ndarray:
    """A BGR side-by-side frame as a YUYV camera would send it: uint8 (H, 2W, 2)."""
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_YUYV)


class _YuyvCamera:
    """The avoid scene's sim camera, its frames as YUYV bytes."""

    def __init__(self) -> None:
        self.inner = avoid_scene_camera(15.0)
        self.name = "yuyv:avoid-scene"

    eye_size_px = property(lambda self: self.inner.eye_size_px)

    def open(self) -> None:
        self.inner.open()

    def read(self) -> Frame:
        frame = self.inner.read()
        return replace(frame, image=_yuyv(frame.image))

    def close(self) -> None:
        self.inner.close()


@pytest.mark.parametrize("backend", ["opencv-bm", "opencv-sgbm", "reference"])
def test_a_yuyv_frame_reads_as_its_luma_on_every_cpu_backend(tmp_path: Path, backend: str) -> None:
    camera = avoid_scene_camera()
    camera.open()
    yuyv = _yuyv(camera.read().image)
    assert yuyv.shape == (376, 2 * 672, 2)
    cfg = service_config(tmp_path, stereo={"backend": backend})
    from_yuyv = make_pipeline(cfg, 672, 376).process(yuyv, 0.0)
    from_luma = make_pipeline(cfg, 672, 376).process(np.ascontiguousarray(yuyv[..., 0]), 0.0)
    np.testing.assert_array_equal(from_yuyv.raw.depth_m, from_luma.raw.depth_m)
    assert from_yuyv.decision == from_luma.decision
    assert from_yuyv.decision.kind.name == "AVOID"  # the wall on the left-front, as in BGR


def test_the_preview_of_a_yuyv_frame_is_in_colour(tmp_path: Path) -> None:
    inputs = avoid_scene_preview_inputs(service_config(tmp_path))
    image = render_preview(replace(inputs, image=_yuyv(inputs.image)), 320)
    assert image.shape == (179, 320, 3) and image.dtype == np.uint8


def test_the_service_flies_and_previews_on_yuyv_frames(tmp_path: Path) -> None:
    cfg = service_config(tmp_path, view={"preview_rate_hz": 4.0, "preview_width_px": 320})
    service = Service(cfg, camera=_YuyvCamera(), link=FakeLink(), install_signals=False, environ={})
    with ServiceRunner(service):
        ctx = zmq.Context()
        sub = ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.SUBSCRIBE, b"preview")
        sub.connect(cfg.view.preview_endpoint)
        try:
            got = []
            deadline = time.monotonic() + 120.0  # generous: the preview worker starts on a busy machine
            while not got and time.monotonic() < deadline:
                if sub.poll(100):
                    got.append(unpack(sub.recv_multipart()))
        finally:
            sub.close(0)
            ctx.destroy(linger=0)
        assert got, "no preview of a YUYV frame"
        header, jpeg = got[0]
        assert header["decision"] == "avoid" and jpeg[:2] == b"\xff\xd8"
        assert service.vision.latest.result.decision.kind.name == "AVOID"
