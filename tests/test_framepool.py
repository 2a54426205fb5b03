"""Frame buffers lent to the camera (companion/framepool.py), a UVC camera decoding into them, and the
service handing the GPU backend's pool to the camera. The GPU estimator reading them in place is in
tests/test_gpu.py (marker ``gpu``)."""

from __future__ import annotations

import gc
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.framepool import FrameBuffers, FramePool
from companion.service.camera_v4l2 import UvcCamera

SHAPE = (4, 10, 3)


def _pool(n: int = 2) -> tuple[FramePool, list[np.ndarray]]:
    buffers = [np.zeros(SHAPE, np.uint8) for _ in range(n)]
    return FramePool(buffers), buffers


def _owner(view: np.ndarray, buffers: list[np.ndarray]) -> int:
    return next(i for i, b in enumerate(buffers) if np.shares_memory(view, b))


def test_a_buffer_is_lent_once_and_comes_back_when_its_frame_is_gone() -> None:
    pool, buffers = _pool(2)
    a, b = pool.acquire(), pool.acquire()
    assert a is not None and b is not None and _owner(a, buffers) != _owner(b, buffers)
    assert pool.acquire() is None  # both out: the camera decodes elsewhere, nothing waits
    assert pool.stats() == {"size": 2, "free": 0, "lent": 2, "misses": 1}
    held = _owner(a, buffers)
    del a
    gc.collect()
    c = pool.acquire()
    assert c is not None and _owner(c, buffers) == held


def test_a_view_of_the_frame_keeps_its_buffer_out() -> None:
    # The pipeline, a preview or a recording may keep a slice (one eye) after the frame itself.
    pool, buffers = _pool(1)
    frame = pool.acquire()
    assert frame is not None
    left_eye = frame[:, : SHAPE[1] // 2]
    del frame
    gc.collect()
    assert pool.acquire() is None
    left_eye[...] = 7  # still the frame's memory, not overwritten by another
    assert (buffers[0][:, : SHAPE[1] // 2] == 7).all()
    del left_eye
    gc.collect()
    assert pool.acquire() is not None


def test_buffers_come_back_from_any_thread() -> None:
    pool, _ = _pool(3)
    frames = [pool.acquire() for _ in range(3)]
    assert pool.acquire() is None

    def drop() -> None:
        frames.clear()
        gc.collect()

    t = threading.Thread(target=drop)
    t.start()
    t.join()
    assert pool.stats()["free"] == 3


def test_a_pool_refuses_buffers_it_cannot_lend() -> None:
    with pytest.raises(ValueError, match="at least one"):
        FramePool([])
    with pytest.raises(ValueError, match="one shape"):
        FramePool([np.zeros((2, 2, 3), np.uint8), np.zeros((2, 4, 3), np.uint8)])
    with pytest.raises(ValueError, match="uint8"):
        FramePool([np.zeros((2, 2, 3), np.float32)])
    with pytest.raises(ValueError, match="C-contiguous"):
        FramePool([np.zeros((2, 4, 3), np.uint8)[:, ::2]])


def test_the_camera_asks_for_its_own_shape_only() -> None:
    holder = FrameBuffers()
    assert holder.acquire(SHAPE) is None  # no pool (the CPU backends)
    pool, _ = _pool(1)
    holder.pool = pool
    assert holder.acquire((4, 12, 3)) is None  # another mode: the camera decodes into its own memory
    assert holder.acquire(SHAPE) is not None


class _DecodingCapture:
    """cv2.VideoCapture's read([image]): decodes into ``image`` when it has the frame's shape and
    type (as OpenCV does), else returns an array of its own; BGR, or with ``CAP_PROP_CONVERT_RGB`` off
    the driver's YUYV bytes, (H, W, 2) (as OpenCV's V4L2 backend gives them)."""

    def __init__(self, width: int, height: int) -> None:
        self.props = {cv2.CAP_PROP_FRAME_WIDTH: width, cv2.CAP_PROP_FRAME_HEIGHT: height, cv2.CAP_PROP_FPS: 30.0,
                      cv2.CAP_PROP_CONVERT_RGB: 1.0}
        self.value = 0

    def isOpened(self) -> bool:
        return True

    def set(self, prop: int, value: float) -> bool:
        self.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        return float(self.props.get(prop, 0.0))

    def read(self, image: np.ndarray | None = None):
        self.value += 1
        h, w = int(self.props[cv2.CAP_PROP_FRAME_HEIGHT]), int(self.props[cv2.CAP_PROP_FRAME_WIDTH])
        shape = (h, w, 3 if self.props[cv2.CAP_PROP_CONVERT_RGB] else 2)
        if image is None or image.shape != shape or image.dtype != np.uint8:
            return True, np.full(shape, self.value, np.uint8)
        image[...] = self.value
        return True, image

    def release(self) -> None:
        pass


@pytest.mark.parametrize(("pixels", "channels"), [("luma", 2), ("bgr", 3)])
def test_a_uvc_camera_decodes_into_the_pool_and_falls_back_when_it_is_empty(pixels: str, channels: int) -> None:
    cap = _DecodingCapture(2 * 8, 6)
    cam = UvcCamera("/dev/video0", 8, 6, 30.0, model="sbs", pixels=pixels, capture_factory=lambda d: cap)
    cam.open()
    plain = cam.read()  # no pool: memory of its own
    assert plain.image.shape == (6, 16, channels)
    buffers = [np.zeros((6, 16, channels), np.uint8) for _ in range(2)]
    holder = FrameBuffers()
    holder.pool = FramePool(buffers)
    cam.frame_buffers = holder
    f1, f2 = cam.read(), cam.read()
    assert not any(np.shares_memory(plain.image, b) for b in buffers)
    assert _owner(f1.image, buffers) != _owner(f2.image, buffers)
    assert (f1.image == 2).all() and (f2.image == 3).all()  # each frame kept its own content
    f3 = cam.read()  # both buffers held by the frames: decoded elsewhere, no wait, no overwrite
    assert not any(np.shares_memory(f3.image, b) for b in buffers) and (f3.image == 4).all()
    assert (f1.image == 2).all() and (f2.image == 3).all()
    kept = _owner(f1.image, buffers)
    del f1
    gc.collect()
    f4 = cam.read()
    assert _owner(f4.image, buffers) == kept and (f4.image == 5).all()
    cam.close()


def test_the_service_gives_the_camera_the_gpu_backends_pool_and_none_otherwise(tmp_path: Path) -> None:
    from companion.service.daemon import Service

    from peers.fakes import FakeLink, avoid_scene_camera, service_config

    cfg = service_config(tmp_path)
    service = Service(cfg, camera=avoid_scene_camera(10.0), link=FakeLink(), install_signals=False, environ={})

    class _Estimator:  # the GPU backend's frame_pool (the CPU backends have none)
        def __init__(self) -> None:
            self.asked: list[int] = []

        def frame_pool(self, count: int, channels: int = 3) -> FramePool:
            self.asked.append((count, channels))
            return FramePool([np.zeros(SHAPE, np.uint8) for _ in range(count)])

    class _Pipeline:
        def __init__(self, estimator: object) -> None:
            self.estimator = estimator

    gpu = _Estimator()
    service.vision.offer_frame_pool(_Pipeline(gpu), cfg)
    assert gpu.asked == [(cfg.gpu.camera_frame_buffers, 3)] and service.vision.frame_buffers.acquire(SHAPE) is not None
    off = cfg.model_copy(update={"gpu": cfg.gpu.model_copy(update={"camera_frame_buffers": 0})})
    service.vision.offer_frame_pool(_Pipeline(gpu), off)
    assert service.vision.frame_buffers.pool is None
    service.vision.offer_frame_pool(_Pipeline(object()), cfg)  # a CPU estimator
    assert service.vision.frame_buffers.pool is None


def test_a_lost_gpu_takes_its_pool_from_the_camera_and_health_names_the_cpu_engine(tmp_path: Path) -> None:
    """A fault that loses the GPU: the pipeline matches with the CPU engine from the next frame on, the
    camera stops decoding into the lost backend's pinned buffers, and health's counters say which
    backend matches and what lost the device."""
    from companion.backends import make_pipeline
    from companion.core.estimator import CpuRegionEstimator
    from companion.errors import BackendError
    from companion.interfaces import Frame
    from companion.service.daemon import Service

    from peers.fakes import FakeLink, FaultingEstimator, avoid_scene_camera, service_config

    cfg = service_config(tmp_path)
    w, h = cfg.camera.width_px, cfg.camera.height_px
    service = Service(cfg, camera=avoid_scene_camera(10.0), link=FakeLink(), install_signals=False, environ={})

    class _Gpu(FaultingEstimator):  # with the GPU backend's pinned pool for the camera
        def frame_pool(self, count: int, channels: int = 3) -> FramePool:
            return FramePool([np.zeros((h, 2 * w, channels), np.uint8) for _ in range(count)])

    pipeline = make_pipeline(cfg, w, h, estimator=_Gpu(CpuRegionEstimator(cfg, w, h), good_frames=0, device_lost=True))
    vision = service.vision
    vision.pipeline = pipeline
    vision.offer_frame_pool(pipeline, cfg)
    assert vision.frame_buffers.pool is not None and vision.counts(0.0).backend == "cupy"
    with pytest.raises(BackendError, match="illegal memory access"):
        vision._process(Frame(np.zeros((h, 2 * w, 3), np.uint8), 0.0, 1))
    assert vision.frame_buffers.pool is None
    counts = vision.counts(0.0)
    assert counts.backend == "cpu-sgm" and "illegal memory access" in counts.device_lost
    assert vision._process(Frame(np.zeros((h, 2 * w, 3), np.uint8), 0.1, 2)).refined.depth_m.shape == (9,)


def test_a_uvc_camera_takes_yuyv_bytes_only_where_the_driver_gives_yuyv(caplog: pytest.LogCaptureFixture) -> None:
    cap = _DecodingCapture(2 * 8, 6)
    cam = UvcCamera("/dev/video0", 8, 6, 30.0, model="sbs", fourcc="YUYV", capture_factory=lambda d: cap)
    cam.open()
    assert cap.props[cv2.CAP_PROP_CONVERT_RGB] == 0 and cam.read().image.shape == (6, 16, 2)

    class _MjpgDriver(_DecodingCapture):  # a driver that settles on MJPG whatever it is asked
        def get(self, prop: int) -> float:
            return float(cv2.VideoWriter_fourcc(*"MJPG")) if prop == cv2.CAP_PROP_FOURCC else super().get(prop)

    mjpg = _MjpgDriver(2 * 8, 6)
    cam = UvcCamera("/dev/video0", 8, 6, 30.0, model="sbs", capture_factory=lambda d: mjpg)
    with caplog.at_level("WARNING"):
        cam.open()
    assert "asked for YUYV but the driver gives 'MJPG'" in caplog.text
    assert mjpg.props[cv2.CAP_PROP_CONVERT_RGB] == 1 and cam.read().image.shape == (6, 16, 3)


def test_the_camera_config_says_how_many_bytes_a_pixel_its_frames_have() -> None:
    from companion.config import CameraConfig
    from companion.service.camera import frame_channels

    zed = {"source": "uvc", "model": "zed", "width_px": 672, "height_px": 376}
    assert frame_channels(CameraConfig(**zed)) == 2  # the default: YUYV taken as it comes
    assert frame_channels(CameraConfig(**zed, pixels="bgr")) == 3
    assert frame_channels(CameraConfig(**zed, fourcc="MJPG")) == 3
    assert frame_channels(CameraConfig()) == 3  # the simulator renders BGR
    pair = {"source": "uvc", "model": "pair", "device_right": "/dev/video2"}
    assert frame_channels(CameraConfig(**pair)) == 3
