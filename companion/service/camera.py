"""Camera sources behind :class:`~companion.interfaces.CameraSource`: ``uvc`` (a ZED or another
side-by-side camera over V4L2, or a pair of V4L2 cameras), ``replay`` (a recording) and ``sim`` (the
renderer).

Every ``read`` blocks in the capture thread and returns a :class:`~companion.interfaces.Frame` whose
image is a uint8 (H, 2W, 3) BGR side-by-side frame (a UVC camera sending YUYV: its (H, 2W, 2) bytes
as they come, with ``camera.pixels = "luma"``), timestamped with ``clock()`` (the process's
monotonic clock, seconds) when it was read. A source never reuses an image array it has handed out
unless that array is read-only (the consumer may still be processing it).
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from companion.core.geometry import StereoGeometry
from companion.core.placement import CoursePlacement
from companion.core.pose import Pose
from companion.errors import CameraError
from companion.framepool import FrameBuffers
from companion.interfaces import CameraSource, Frame, VehicleState
from companion.pacing import RatePacer, RecordedPacer

if TYPE_CHECKING:
    from companion.config import CompanionConfig
    from companion.config.service import CameraConfig
    from companion.sim.render import Scene

log = logging.getLogger(__name__)

Clock = Callable[[], float]
#: Returns the pose to render and when it was true, on the camera's clock (seconds). Raises
#: :class:`PoseUnavailable` while there is no usable pose.
PoseProvider = Callable[[], "tuple[Pose, float]"]


class PoseUnavailable(CameraError):
    """The pose provider has no usable pose now (none received yet, or too old)."""


def _check_frame(image: object, source: str, width_px: int, height_px: int, yuyv: bool = False) -> np.ndarray:
    """A frame as the pipeline needs it, or a CameraError naming what is wrong with it.

    ``yuyv``: the capture was asked for its bytes undecoded: a uint8 (H, 2W, 2) YUYV frame (one that
    comes flat, (1, H·2W·2), is reshaped), or BGR where the backend decoded it anyway."""
    if yuyv and isinstance(image, np.ndarray) and image.dtype == np.uint8 and image.ndim == 2 \
            and image.shape[0] == 1 and image.size == height_px * 2 * width_px * 2:
        image = image.reshape(height_px, 2 * width_px, 2)
    channels = (2, 3) if yuyv else (3,)
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] not in channels:
        shape = getattr(image, "shape", None)
        dtype = getattr(image, "dtype", type(image).__name__)
        expected = "(H, 2W, 2) YUYV or (H, 2W, 3) BGR" if yuyv else "(H, 2W, 3) BGR"
        raise CameraError(f"{source}: frame is {dtype} {shape}, expected uint8 {expected}")
    if image.shape[:2] != (height_px, 2 * width_px):
        raise CameraError(
            f"{source}: frame is {image.shape[1]}x{image.shape[0]}, expected side-by-side "
            f"{2 * width_px}x{height_px} (two {width_px}x{height_px} eyes)"
        )
    return image


# ---------------------------------------------------------------------------------------------- UVC


#: Makes an OpenCV capture: ``factory(index_or_path) -> cv2.VideoCapture``-like (tests pass a fake).
CaptureFactory = Callable[[int | str], object]


def _v4l2_capture(index: int | str) -> object:
    import cv2

    return cv2.VideoCapture(index, cv2.CAP_V4L2)


def _device_index(device: str) -> int | str:
    return int(device) if device.isdigit() else device


def _open_v4l2(
    factory: CaptureFactory, device: str, name: str, width_px: int, height_px: int, fps_hz: float, fourcc: str, hint: str
) -> object:
    """Open one V4L2 device in a mode, checking that the driver gives that size; returns the capture."""
    import cv2

    cap = factory(_device_index(device))
    if not cap.isOpened():
        cap.release()
        raise CameraError(f"{name}: cannot open {device} (unplugged, or no permission: group 'video')")
    cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*fourcc))
    cap.set(cv2.CAP_PROP_FRAME_WIDTH, width_px)
    cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height_px)
    cap.set(cv2.CAP_PROP_FPS, fps_hz)
    # One buffered frame: the newest frame matters, not a queue of old ones.
    cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
    got_w = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
    got_h = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    if (got_w, got_h) != (width_px, height_px):
        cap.release()
        raise CameraError(
            f"{name}: asked {device} for {width_px}x{height_px} ({fourcc}) but the driver gives {got_w}x{got_h}; {hint}"
        )
    got_fps = cap.get(cv2.CAP_PROP_FPS)
    if got_fps and abs(got_fps - fps_hz) > 0.5:
        log.warning("%s: asked %s for %.0f fps, the driver reports %.1f", name, device, fps_hz, got_fps)
    return cap


class UvcCamera:
    """A side-by-side stereo camera over UVC (OpenCV's V4L2 backend): a ZED, or any camera whose
    frame is both eyes side by side (width 2·W).

    ``model`` ``zed``: the mode (W, H, fps) was validated against the ZED's modes at config time;
    ``sbs``: any mode, checked only against what the driver actually gives. The mode is asked for
    with ``fourcc`` (YUYV for the ZED).

    ``pixels`` ``luma`` (with YUYV): OpenCV hands over the driver's bytes undecoded
    (``CAP_PROP_CONVERT_RGB`` off), a uint8 (H, 2W, 2) frame whose Y bytes are the grey the pipeline
    matches: no colour decoding on the CPU, and 2 bytes a pixel for the GPU instead of 3. When the
    driver settles on another format, or OpenCV will not hand the bytes over, the camera says so once
    and decodes BGR. ``bgr``: every frame is decoded to BGR.

    :attr:`frame_buffers` (set by the service when the GPU backend offers pinned buffers,
    :mod:`companion.framepool`): each frame is decoded straight into one of them, so that the GPU reads
    it with no host copy; when none is free, or OpenCV would not decode into it, into memory of its own.
    """

    def __init__(
        self,
        device: str,
        width_px: int,
        height_px: int,
        fps_hz: float,
        clock: Clock = time.monotonic,
        *,
        model: str = "zed",
        fourcc: str = "YUYV",
        pixels: str = "luma",
        capture_factory: CaptureFactory = _v4l2_capture,
    ):
        self.name = f"uvc:{device}"
        self.device = device
        self.width_px = width_px
        self.height_px = height_px
        self.fps_hz = fps_hz
        self.model = model
        self.fourcc = fourcc
        self._factory = capture_factory
        self._clock = clock
        self.pixels = pixels
        self._cap = None
        self._seq = 0
        self._yuyv = False  # this capture hands over YUYV bytes (pixels "luma", and the driver agreed)
        self.frame_buffers: FrameBuffers | None = None

    @property
    def eye_size_px(self) -> tuple[int, int]:
        return (self.width_px, self.height_px)

    def open(self) -> None:
        self.close()
        if self.model == "zed":
            hint = "is it a ZED, and is the mode one it supports?"
        else:
            hint = (f"is it a side-by-side camera with {self.width_px}x{self.height_px} eyes? "
                    "`v4l2-ctl -d DEVICE --list-formats-ext` lists its modes (the width there is both eyes')")
        self._cap = _open_v4l2(
            self._factory, self.device, self.name, 2 * self.width_px, self.height_px, self.fps_hz, self.fourcc, hint
        )
        self._yuyv = _wants_yuyv(self.pixels, self.fourcc) and _hand_over_yuyv(self._cap, self.name)
        log.info("%s: open at %dx%d@%g (%s, side by side; %s)", self.name, 2 * self.width_px, self.height_px,
                 self.fps_hz, self.fourcc, "its luma taken as it comes" if self._yuyv else "decoded to BGR")

    def read(self) -> Frame:
        cap = self._cap
        if cap is None:
            raise CameraError(f"{self.name}: not open")
        pool = self.frame_buffers
        shape = (self.height_px, 2 * self.width_px, 2 if self._yuyv else 3)
        buf = pool.acquire(shape) if pool is not None else None
        ok, image = cap.read(buf) if buf is not None else cap.read()
        t = self._clock()
        if not ok or image is None:
            raise CameraError(f"{self.name}: no frame (camera unplugged or stalled)")
        # (OpenCV decodes into buf when its shape and type fit; else it returns an array of its own and
        # buf goes back to the pool when dropped here)
        image = _check_frame(image, self.name, self.width_px, self.height_px, yuyv=self._yuyv)
        self._seq += 1
        return Frame(image=image, timestamp_s=t, seq=self._seq)

    def close(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()


def frame_channels(cam: CameraConfig) -> int:
    """Bytes per pixel of the frames the configured camera will give: 2 for a UVC camera whose YUYV
    bytes are taken as they come (``camera.pixels`` luma), else 3 (BGR). (Where the driver then
    refuses YUYV, the camera decodes BGR after all and its frames go to the GPU through a host copy.)"""
    yuyv = cam.source == "uvc" and cam.model != "pair" and _wants_yuyv(cam.pixels, cam.fourcc)
    return 2 if yuyv else 3


def _wants_yuyv(pixels: str, fourcc: str) -> bool:
    """``camera.pixels`` asks for the YUYV bytes as they come, and the camera is asked for YUYV."""
    return pixels == "luma" and fourcc.upper() == "YUYV"


def _hand_over_yuyv(cap: object, name: str) -> bool:
    """Ask an open capture for its YUYV bytes undecoded; False (and it decodes BGR, as before) when the
    driver settled on another format or OpenCV refuses, said once in the log."""
    import cv2

    got = int(cap.get(cv2.CAP_PROP_FOURCC)) & 0xFFFFFFFF
    if got != cv2.VideoWriter_fourcc(*"YUYV"):
        text = "".join(chr((got >> (8 * i)) & 0xFF) for i in range(4)) if got else "no format"
        log.warning("%s: asked for YUYV but the driver gives %r: decoding BGR (camera.pixels luma needs YUYV)",
                    name, text)
        return False
    if not cap.set(cv2.CAP_PROP_CONVERT_RGB, 0) or cap.get(cv2.CAP_PROP_CONVERT_RGB) != 0:
        cap.set(cv2.CAP_PROP_CONVERT_RGB, 1)
        log.warning("%s: OpenCV will not hand over the YUYV bytes undecoded: decoding BGR", name)
        return False
    return True


# ---------------------------------------------------------------------------------------------- pair


class PairCamera:
    """Two V4L2 cameras, one per eye, joined into one side-by-side frame.

    Each read grabs both cameras back to back (``grab`` only dequeues a buffer; the slower decoding,
    ``retrieve``, comes after both), so the two frames are as close in time as the drivers allow. The
    skew between them is measured from the drivers' buffer timestamps (``CAP_PROP_POS_MSEC``, the
    kernel's capture time) when both give one, else from when each grab returned; when it exceeds
    ``max_skew_ms`` the earlier camera is grabbed once more (its next frame is nearer the other's).
    :meth:`skew_status` reports it (health: ``camera.skew_ms``).

    Args:
        left_device, right_device: the two V4L2 devices (nodes or indices).
        width_px, height_px: one eye's (one camera's) frame size, pixels.
        fps_hz: requested rate of both, Hz.
        fourcc: pixel format asked of both drivers.
        max_skew_ms: see above, milliseconds.
        capture_factory: makes the OpenCV captures (tests pass fakes).
    """

    def __init__(
        self,
        left_device: str,
        right_device: str,
        width_px: int,
        height_px: int,
        fps_hz: float,
        clock: Clock = time.monotonic,
        *,
        fourcc: str = "YUYV",
        max_skew_ms: float = 8.0,
        capture_factory: CaptureFactory = _v4l2_capture,
    ) -> None:
        self.name = f"pair:{left_device}+{right_device}"
        self.devices = (left_device, right_device)
        self.width_px = width_px
        self.height_px = height_px
        self.fps_hz = fps_hz
        self.fourcc = fourcc
        self.max_skew_ms = max_skew_ms
        self._factory = capture_factory
        self._clock = clock
        self._caps: tuple[object, object] | None = None
        self._seq = 0
        self._lock = threading.Lock()
        self._skews_ms: collections.deque[float] = collections.deque(maxlen=300)
        self._skew_source = "host"
        self._regrabs = 0

    @property
    def eye_size_px(self) -> tuple[int, int]:
        return (self.width_px, self.height_px)

    def open(self) -> None:
        self.close()
        hint = "`v4l2-ctl -d DEVICE --list-formats-ext` lists its modes; both cameras need the same one"
        left = _open_v4l2(self._factory, self.devices[0], self.name, self.width_px, self.height_px, self.fps_hz,
                          self.fourcc, hint)
        try:
            right = _open_v4l2(self._factory, self.devices[1], self.name, self.width_px, self.height_px, self.fps_hz,
                               self.fourcc, hint)
        except BaseException:
            left.release()
            raise
        self._caps = (left, right)
        log.info("%s: open at %dx%d@%g (%s) each", self.name, self.width_px, self.height_px, self.fps_hz, self.fourcc)

    def _grab(self, cap: object, which: str) -> tuple[float, float]:
        """Grab one camera: (when the grab returned on our clock, the driver's timestamp in ms or 0)."""
        import cv2

        if not cap.grab():
            raise CameraError(f"{self.name}: no frame from the {which} camera (unplugged or stalled)")
        return self._clock(), float(cap.get(cv2.CAP_PROP_POS_MSEC) or 0.0)

    def read(self) -> Frame:
        caps = self._caps
        if caps is None:
            raise CameraError(f"{self.name}: not open")
        (t_l, d_l), (t_r, d_r) = self._grab(caps[0], "left"), self._grab(caps[1], "right")
        driver = d_l > 0 and d_r > 0
        skew = (d_r - d_l) if driver else (t_r - t_l) * 1e3
        if driver and abs(skew) > self.max_skew_ms:
            # The earlier frame's successor is nearer the later one: take it instead (once).
            if skew > 0:
                t_l, d_l = self._grab(caps[0], "left")
            else:
                t_r, d_r = self._grab(caps[1], "right")
            skew = d_r - d_l
            with self._lock:
                self._regrabs += 1
        images = []
        for cap, which in zip(caps, ("left", "right")):
            ok, image = cap.retrieve()
            if not ok or image is None:
                raise CameraError(f"{self.name}: the {which} camera's frame could not be decoded")
            if not isinstance(image, np.ndarray) or image.shape != (self.height_px, self.width_px, 3) or image.dtype != np.uint8:
                raise CameraError(
                    f"{self.name}: the {which} camera's frame is {getattr(image, 'dtype', '?')} "
                    f"{getattr(image, 'shape', '?')}, expected uint8 ({self.height_px}, {self.width_px}, 3)"
                )
            images.append(image)
        frame = np.empty((self.height_px, 2 * self.width_px, 3), np.uint8)
        frame[:, : self.width_px] = images[0]
        frame[:, self.width_px :] = images[1]
        with self._lock:
            self._skews_ms.append(float(skew))
            self._skew_source = "driver" if driver else "host"
        self._seq += 1
        return Frame(image=frame, timestamp_s=0.5 * (t_l + t_r), seq=self._seq)

    def skew_status(self) -> dict[str, float | int | str | None]:
        """The skew between the eyes over the last 300 frames: ``last``, ``median`` and ``max`` (of
        the absolute value), milliseconds, right minus left for ``last``; ``source`` (``driver``: the
        drivers' capture timestamps; ``host``: when each grab returned, an upper bound); ``regrabs``:
        frames where the earlier camera was grabbed again."""
        with self._lock:
            skews = np.asarray(self._skews_ms, dtype=np.float64)
            if skews.size == 0:
                return {"last": None, "median": None, "max": None, "source": self._skew_source, "regrabs": self._regrabs}
            return {
                "last": float(skews[-1]),
                "median": float(np.median(np.abs(skews))),
                "max": float(np.abs(skews).max()),
                "source": self._skew_source,
                "regrabs": self._regrabs,
            }

    def close(self) -> None:
        caps, self._caps = self._caps, None
        if caps is not None:
            for cap in caps:
                cap.release()


# ---------------------------------------------------------------------------------------------- replay


class ReplayCamera:
    """Frames from a recording (see :mod:`companion.service.recording`), at the recorded rate (its
    timestamps) or at ``rate_hz``; optionally looping. The end of a non-looping recording raises a
    CameraError with ``ended=True`` in its context (the capture thread then stops reopening it).

    Args:
        path: the recording (a folder of PNGs with timestamps.csv, or an .mkv/.avi with its sidecar).
        width_px, height_px: the expected eye size (a recording of another size is an error).
        rate_hz: deliver at this rate; None = the recorded timestamps (``fallback_fps_hz`` without them).
        loop: start again at the end.
        preload: decode every frame at open (costs memory: H·2W·3 bytes a frame).
    """

    def __init__(
        self,
        path: Path,
        width_px: int,
        height_px: int,
        *,
        rate_hz: float | None = None,
        fallback_fps_hz: float = 30.0,
        loop: bool = False,
        preload: bool = False,
        clock: Clock = time.monotonic,
    ) -> None:
        self.name = f"replay:{path}"
        self.path = Path(path)
        self.width_px = width_px
        self.height_px = height_px
        self.rate_hz = rate_hz
        self.fallback_fps_hz = fallback_fps_hz
        self.loop = loop
        self.preload = preload
        self._clock = clock
        self._stop = threading.Event()
        self._video = None
        self._files: list[Path] = []
        self._frames: list[np.ndarray] | None = None
        self._times: np.ndarray | None = None
        self._index = 0
        self._seq = 0
        self._at_recorded = RecordedPacer(clock, self._stop)
        self._pacer: RatePacer | None = None
        self._opened = False

    @property
    def eye_size_px(self) -> tuple[int, int]:
        return (self.width_px, self.height_px)

    @property
    def frame_count(self) -> int:
        if self._frames is not None:
            return len(self._frames)
        return len(self._files) if self._files else (len(self._times) if self._times is not None else 0)

    def open(self) -> None:
        from companion.service.recording import VIDEO_SUFFIXES, read_timestamps

        self.close()
        self._stop.clear()
        p = self.path
        if not p.exists():
            # Permanent: retrying will not make it appear (the capture thread stops on ended=True).
            raise CameraError(f"{self.name}: no such recording", ended=True)
        ts = read_timestamps(p)
        self._times = ts.timestamp_s if ts is not None else None
        if p.is_dir():
            self._files = sorted(p.glob("frame_*.png"))
            if not self._files:
                raise CameraError(f"{self.name}: no frame_*.png in the folder", ended=True)
            if self._times is not None and len(self._times) != len(self._files):
                raise CameraError(
                    f"{self.name}: {len(self._files)} frames but {len(self._times)} timestamps"
                )
        elif p.suffix.lower() in VIDEO_SUFFIXES:
            self._open_video()
        else:
            raise CameraError(
                f"{self.name}: not a recording (a folder, or a {'/'.join(VIDEO_SUFFIXES)} file)", ended=True
            )
        if self.preload:
            frames = []
            while True:
                image = self._decode_next(allow_end=True)
                if image is None:
                    break
                frames.append(image)
            if not frames:
                raise CameraError(f"{self.name}: the recording has no frames")
            self._frames = frames
            self._release_video()
        self._index = 0
        self._at_recorded.restart()
        period = 1.0 / (self.rate_hz or self.fallback_fps_hz)
        self._pacer = RatePacer(period, self._clock, self._stop)
        self._opened = True
        log.info("%s: open (%s)", self.name, "preloaded" if self.preload else "streaming from disk")

    def _open_video(self) -> None:
        import cv2

        self._release_video()
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise CameraError(f"{self.name}: OpenCV cannot open the video")
        self._video = cap

    def _release_video(self) -> None:
        video, self._video = self._video, None
        if video is not None:
            video.release()

    def _decode_next(self, allow_end: bool) -> np.ndarray | None:
        """The frame at ``self._index`` (advancing it), or None at the end."""
        import cv2

        i = self._index
        if self._frames is not None:
            if i >= len(self._frames):
                return None
            self._index += 1
            return self._frames[i]
        if self._files:
            if i >= len(self._files):
                return None
            image = cv2.imread(str(self._files[i]), cv2.IMREAD_COLOR)
            if image is None:
                raise CameraError(f"{self.name}: cannot decode {self._files[i].name}")
        else:
            if self._video is None:
                return None
            ok, image = self._video.read()
            if not ok:
                return None
        self._index += 1
        return _check_frame(image, f"{self.name} frame {i}", self.width_px, self.height_px)

    def _rewind(self) -> None:
        self._index = 0
        if self._video is not None:
            self._open_video()

    def read(self) -> Frame:
        if not self._opened:
            raise CameraError(f"{self.name}: not open")
        index = self._index
        image = self._decode_next(allow_end=True)
        if image is None:
            if not self.loop:
                raise CameraError(f"{self.name}: end of the recording", ended=True)
            self._rewind()
            self._at_recorded.restart()
            index = 0
            image = self._decode_next(allow_end=False)
            if image is None:
                raise CameraError(f"{self.name}: the recording has no frames", ended=True)
        self._wait_for(index)
        t = self._clock()
        self._seq += 1
        return Frame(image=image, timestamp_s=t, seq=self._seq)

    def _wait_for(self, index: int) -> None:
        if self.rate_hz is None and self._times is not None and index < len(self._times):
            self._at_recorded.wait(float(self._times[index]))  # at the recorded timestamps
            return
        assert self._pacer is not None
        self._pacer.wait()

    def close(self) -> None:
        self._stop.set()
        self._release_video()
        self._opened = False


# ---------------------------------------------------------------------------------------------- sim


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
