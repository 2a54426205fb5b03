"""The V4L2 camera sources (OpenCV's V4L2 backend): a side-by-side stereo camera over UVC (a ZED, or any
camera whose frame is both eyes side by side) and a pair of cameras, one per eye, joined into one
side-by-side frame.

A UVC camera sending YUYV with ``camera.pixels = "luma"`` hands over its (H, 2W, 2) bytes as they come;
every other frame is decoded to (H, 2W, 3) BGR.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable

import numpy as np

from companion.errors import CameraError
from companion.framepool import FrameBuffers
from companion.interfaces import Frame
from companion.service.camera_frame import check_frame

log = logging.getLogger(__name__)

Clock = Callable[[], float]


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
        self._yuyv = wants_yuyv(self.pixels, self.fourcc) and _hand_over_yuyv(self._cap, self.name)
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
        image = check_frame(image, self.name, self.width_px, self.height_px, yuyv=self._yuyv)
        self._seq += 1
        return Frame(image=image, timestamp_s=t, seq=self._seq)

    def close(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()



def wants_yuyv(pixels: str, fourcc: str) -> bool:
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

