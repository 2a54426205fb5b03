"""How a frame reaches the GPU estimator's device: pinned staging, in-place buffers and the banded DMA.

A frame from the caller's own memory is copied band by band into a pinned staging buffer (``np.copyto``,
or OpenCV's parallel BGR->RGB shuffle with ``gpu.host_copy_engine = "opencv"``, optionally on several
threads) and each band's DMA is queued on the copy stream; with ``gpu.register_frames`` the caller's
pages are locked for the DMA instead. A frame written into the staging buffer, or decoded by the camera
into one of the pinned buffers of :meth:`FrameUpload.frame_pool`, is not copied at all: the DMA reads it
in place (with ``gpu.zero_copy`` the kernels read the buffer's mapping, Jetsons).
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.framepool import FramePool
from companion.gpu.bands import Band

log = logging.getLogger(__name__)

#: The staging buffer holds the largest frame: 4 channels (BGRA).
_MAX_CHANNELS = 4


class FrameUpload:
    """The host side of :class:`~companion.gpu.estimator.CupyRegionEstimator`: staging, frame pool,
    page-locking and each band's host copy and DMA.

    A part of the estimator, not used alone: it reads the estimator's ``_cp``, ``_device``,
    ``_gpu_cfg``, ``width_px``, ``height_px``, ``_copy_stream``, ``_events`` (stage timing) and
    ``_crew``, and owns the staging buffer, the device copy of the frame, the pool and the
    page-locked frame in flight (:meth:`_build_staging` makes them).
    """

    def _build_staging(self) -> None:
        """Pinned staging for the largest frame (4 channels; per-channel views share it), the device
        copy the DMA writes (none with ``gpu.zero_copy``: the kernels read the mapping), and the
        bookkeeping of the buffers a frame is read from in place."""
        cp = self._cp
        frame_bytes = self.height_px * 2 * self.width_px * _MAX_CHANNELS
        self._host_frame_mem, self._host_frame, mapped_ptr = self._pinned(frame_bytes)
        if self._gpu_cfg.zero_copy:
            self._frame_dev_ptr = mapped_ptr
            self._dev_frame = None
        else:
            self._dev_frame = cp.empty(frame_bytes, dtype=cp.uint8)
            self._frame_dev_ptr = int(self._dev_frame.data.ptr)
        self._registered = 0  # caller frame page-locked for the DMA in flight (register_frames)
        # The pinned buffers a frame is read from in place (the staging buffer, frame_pool()'s): host
        # pointer -> where the kernels read the frame (the device copy; zero copy: the buffer's mapping).
        self._pool: FramePool | None = None
        self._pool_mem: list[Any] = []
        self._in_place_ptrs: dict[int, int] = {int(self._host_frame_mem.ptr): self._frame_dev_ptr}
        self._frame_shapes = {self.frame_buffer(c).shape: c for c in (1, 2, 3, 4)}  # shape -> channels
        self._kernel_frame_ptr = self._frame_dev_ptr  # where this frame's kernels read it

    def frame_buffer(self, channels: int = 3) -> np.ndarray:
        """The pinned staging buffer as a writable uint8 ``(H, 2W, channels)`` array (``(H, 2W)`` for 1;
        2 is YUYV, the bytes a UVC camera sends, 3 BGR, 4 BGRA).

        A camera that decodes straight into this array (e.g. ``VideoCapture.read(image=buf)``) and
        passes it to :meth:`estimate` saves the host copy of the frame. Its content is overwritten by
        every :meth:`estimate` of another array.
        """
        if channels not in (1, 2, 3, 4):
            raise ValueError(f"channels must be 1, 2, 3 or 4, got {channels}")
        shape = (self.height_px, 2 * self.width_px) + ((channels,) if channels > 1 else ())
        return self._host_frame[: math.prod(shape)].reshape(shape)

    def frame_pool(self, count: int = 3, channels: int = 3) -> FramePool:
        """``count`` more pinned buffers of the frame's shape (``(H, 2W, channels)``, uint8) for a camera to
        decode into (:mod:`companion.framepool`): a frame in one of them goes to the device with no host
        copy, as from :meth:`frame_buffer`, but the camera may fill the next buffer while this frame is
        processed. Made once; later calls return the same pool (``count`` and ``channels`` of the first).

        Raises:
            ValueError: ``count`` < 1, or ``channels`` not 1, 2, 3 or 4.
        """
        if self._pool is not None:
            return self._pool
        if count < 1:
            raise ValueError(f"count must be >= 1, got {count}")
        shape = self.frame_buffer(channels).shape
        buffers = []
        with self._device:
            for _ in range(count):
                mem, buf, mapped_ptr = self._pinned(math.prod(shape))
                self._pool_mem.append(mem)
                # zero copy: the kernels read the buffer through its mapping; else the DMA reads it
                self._in_place_ptrs[int(mem.ptr)] = mapped_ptr if self._dev_frame is None else self._frame_dev_ptr
                buffers.append(buf.reshape(shape))
        self._pool = FramePool(buffers)
        return self._pool

    def _pinned(self, nbytes: int) -> tuple[Any, np.ndarray, int]:
        """Page-locked host memory for frames (mapped with ``gpu.zero_copy``): the allocation, a uint8
        ``(nbytes,)`` array over it, and its device-side pointer (0 when not mapped)."""
        cp = self._cp
        zero_copy = self._gpu_cfg.zero_copy
        flags = cp.cuda.runtime.hostAllocMapped if zero_copy else cp.cuda.runtime.hostAllocPortable
        mem = cp.cuda.PinnedMemory(nbytes, flags)
        array = np.frombuffer(cp.cuda.PinnedMemoryPointer(mem, 0), dtype=np.uint8, count=nbytes)
        mapped = int(cp.cuda.runtime.pointerGetAttributes(mem.ptr).devicePointer) if zero_copy else 0
        return mem, array, mapped

    def _in_place(self, frame: Any) -> tuple[int, int, int] | None:
        """``(channels, host pointer, where the kernels read it)`` for a frame written into
        :meth:`frame_buffer` or decoded into a :meth:`frame_pool` buffer, as a whole C-contiguous uint8
        frame; else None."""
        if type(frame) is not np.ndarray:
            return None
        ptr = frame.ctypes.data
        kernel_ptr = self._in_place_ptrs.get(ptr)
        if kernel_ptr is None or not frame.flags.c_contiguous or frame.dtype != np.uint8:
            return None
        channels = self._frame_shapes.get(frame.shape)
        return None if channels is None else (channels, ptr, kernel_ptr)

    def _source(self, frame: np.ndarray, channels: int, in_place: tuple[int, int, int] | None) -> FrameSource:
        """How this frame reaches the device: host copy function, DMA source, channel order
        (``in_place``: :meth:`_in_place`'s answer for it)."""
        zero_copy = self._dev_frame is None
        if in_place is not None:
            # written into frame_buffer() or decoded into a frame_pool() buffer: DMA (zero copy: read) it there
            return FrameSource(frame, frame, None, in_place[1], False, zero_copy, in_place[2])
        staging = self.frame_buffer(channels)
        host_ptr = self._host_frame_mem.ptr
        if (
            self._gpu_cfg.register_frames
            and not zero_copy
            and frame.flags.c_contiguous
            and self._register(frame)
        ):
            # The caller's own pages are locked for this frame: DMA straight from them.
            return FrameSource(frame, staging, None, frame.ctypes.data, False, zero_copy, self._frame_dev_ptr)
        if self._gpu_cfg.host_copy_engine == "opencv" and channels in (3, 4):
            import cv2

            code = cv2.COLOR_BGR2RGB if channels == 3 else cv2.COLOR_BGRA2RGBA

            def copy(dst: np.ndarray, src: np.ndarray) -> None:
                out = cv2.cvtColor(src, code, dst=dst)
                if out.__array_interface__["data"][0] != dst.__array_interface__["data"][0]:
                    np.copyto(dst, out)  # cv2 reallocated (not expected for these layouts)

            return FrameSource(frame, staging, copy, host_ptr, True, zero_copy, self._frame_dev_ptr)
        return FrameSource(frame, staging, np.copyto, host_ptr, False, zero_copy, self._frame_dev_ptr)

    def _upload_band(self, src: FrameSource, band: Band, done: Any) -> None:
        """Host-copy band rows into the staging buffer, queue their DMA, record ``done`` after it."""
        cp = self._cp
        a, b = band.src
        copy_stream = self._copy_stream
        row_bytes = src.staging.strides[0]
        if b > a:

            def rows(ra: int, rb: int) -> None:
                if src.copy is not None:
                    src.copy(src.staging[ra:rb], src.frame[ra:rb])
                if self._events:  # stage timing (one band, no crew): h2d_ms is the DMA alone
                    self._events[0].record(copy_stream)
                if not src.zero_copy:
                    off = ra * row_bytes
                    cp.cuda.runtime.memcpyAsync(
                        self._frame_dev_ptr + off, src.dma_ptr + off, (rb - ra) * row_bytes,
                        cp.cuda.runtime.memcpyHostToDevice, copy_stream.ptr,
                    )

            crew = self._crew
            if crew is None or src.copy is None or self._events:
                rows(a, b)
            else:
                edges = [a + ((b - a) * i) // crew.size for i in range(crew.size + 1)]
                crew.run([(lambda ra=ra, rb=rb: rows(ra, rb)) for ra, rb in zip(edges, edges[1:])])
        elif self._events:
            self._events[0].record(copy_stream)
        done.record(copy_stream)

    def _register(self, frame: np.ndarray) -> bool:
        """Page-lock the caller's frame for one DMA (``gpu.register_frames``); False: use staging."""
        cp = self._cp
        try:
            cp.cuda.runtime.hostRegister(frame.ctypes.data, frame.nbytes, 0)
        except cp.cuda.runtime.CUDARuntimeError as err:
            # e.g. part of the range is already registered (by the caller): the staged path works.
            log.debug("could not page-lock the frame (%s); copying it into the staging buffer", err)
            return False
        self._registered = frame.ctypes.data
        return True

    def _unregister(self) -> None:
        if self._registered:
            ptr, self._registered = self._registered, 0
            self._cp.cuda.runtime.hostUnregister(ptr)


class CopyCrew:
    """``size - 1`` persistent threads plus the caller run one job each, in parallel, per frame.

    Started once (no per-frame thread or future objects); NumPy's copy and CuPy's memcpyAsync release
    the GIL, so the copies run on several cores. Each worker makes the estimator's device current once.
    """

    def __init__(self, size: int, device_id: int):
        self.size = size
        self._jobs: list[Callable[[], Any] | None] = [None] * size
        self._errors: list[BaseException | None] = [None] * size
        self._start = [threading.Event() for _ in range(size)]
        self._done = [threading.Event() for _ in range(size)]
        self._stop = False
        self._threads = [
            threading.Thread(target=self._work, args=(i, device_id), name=f"companion-upload-{i}", daemon=True)
            for i in range(1, size)
        ]
        for t in self._threads:
            t.start()

    def _work(self, i: int, device_id: int) -> None:
        import cupy

        cupy.cuda.runtime.setDevice(device_id)
        while True:
            self._start[i].wait()
            self._start[i].clear()
            if self._stop:
                return
            try:
                job = self._jobs[i]
                if job is not None:
                    job()
            except BaseException as err:  # handed to the caller of run()
                self._errors[i] = err
            finally:
                self._done[i].set()

    def run(self, jobs: list[Callable[[], Any]]) -> None:
        """Run ``jobs[0]`` here and ``jobs[i]`` on worker i; return when all are done (re-raising)."""
        for i in range(1, self.size):
            self._jobs[i] = jobs[i]
            self._start[i].set()
        try:
            jobs[0]()
        finally:
            for i in range(1, self.size):
                self._done[i].wait()
                self._done[i].clear()
        for i in range(1, self.size):
            err, self._errors[i] = self._errors[i], None
            if err is not None:
                raise err

    def close(self) -> None:
        self._stop = True
        for i in range(1, self.size):
            self._start[i].set()
        for t in self._threads:
            t.join(timeout=1.0)


@dataclass(frozen=True)
class FrameSource:
    """Where one frame's bytes come from: host copy into ``staging`` (None: no copy), DMA source, and
    where the kernels then read them."""

    frame: np.ndarray
    staging: np.ndarray
    copy: Callable[[np.ndarray, np.ndarray], Any] | None
    dma_ptr: int
    swapped: bool
    zero_copy: bool
    kernel_ptr: int  # where the kernels read the frame (the device copy, or a mapped buffer in place)

