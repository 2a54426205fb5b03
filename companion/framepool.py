"""Frame buffers a camera decodes into, lent one frame at a time.

The GPU backend reads a frame fastest from its own page-locked (pinned) host memory: the DMA, or on a
Jetson the kernels themselves, read it in place, with no host copy (5.5 MB per 1280×720 frame). So the
estimator offers a few such buffers (:meth:`CupyRegionEstimator.frame_pool
<companion.gpu.estimator.CupyRegionEstimator.frame_pool>`) and the camera decodes each frame into one
(:class:`~companion.service.camera_v4l2.UvcCamera`).

A buffer may be written again only when nothing holds the frame any more: the pipeline may still be
reading it, a preview or a recording may hold it. So a buffer is lent as a fresh array over a
``memoryview`` of it: NumPy makes every view derived from the lent array (a reshape, one eye's slice)
hold that array itself (a view of a plain ndarray view would hold the buffer's owner instead), so the
buffer comes back to the pool when the lent array and every view of it are gone
(``weakref.finalize``), whatever thread drops the last one. When every buffer is out, :meth:`FramePool.acquire` says so (None)
and the camera decodes into memory of its own, as without a pool: nothing waits.
"""

from __future__ import annotations

import threading
import weakref
from collections import deque
from collections.abc import Sequence

import numpy as np


class FramePool:
    """A fixed set of equal frame buffers, lent out one at a time. Thread-safe.

    Args:
        buffers: the buffers (uint8 arrays of one shape, C-contiguous); the pool owns them from now on.
    """

    def __init__(self, buffers: Sequence[np.ndarray]) -> None:
        if not buffers:
            raise ValueError("a frame pool needs at least one buffer")
        shapes = {b.shape for b in buffers}
        if len(shapes) != 1 or any(b.dtype != np.uint8 or not b.flags.c_contiguous for b in buffers):
            raise ValueError(f"frame pool buffers must be C-contiguous uint8 arrays of one shape, got {sorted(shapes)}")
        self._buffers = list(buffers)
        self._flat = [b.reshape(-1) for b in self._buffers]  # 1-D views: what each lease's memoryview covers
        self._free: deque[int] = deque(range(len(buffers)))
        self._lock = threading.Lock()
        self._lent = 0
        self._misses = 0

    @property
    def shape(self) -> tuple[int, ...]:
        """The buffers' shape, e.g. ``(H, 2W, 3)``."""
        return tuple(self._buffers[0].shape)

    def acquire(self) -> np.ndarray | None:
        """A free buffer as a new writable view (back in the pool once it and every view of it are
        gone), or None when every buffer is out."""
        with self._lock:
            if not self._free:
                self._misses += 1
                return None
            i = self._free.popleft()
            self._lent += 1
        lease = np.frombuffer(memoryview(self._flat[i]), dtype=np.uint8)  # a fresh base for every view of it
        weakref.finalize(lease, self._release, i)
        return lease.reshape(self._buffers[i].shape)

    def _release(self, i: int) -> None:
        with self._lock:
            self._free.append(i)

    def stats(self) -> dict[str, int]:
        """``size``, ``free`` now, ``lent`` and ``misses`` (none free when asked) so far."""
        with self._lock:
            return {"size": len(self._buffers), "free": len(self._free), "lent": self._lent, "misses": self._misses}


class FrameBuffers:
    """Where a camera gets its buffers: the current pool, or none (it allocates, as without one).

    The service swaps :attr:`pool` when it builds a new estimator (a frame decoded into the old pool's
    buffer is still a valid frame: the new estimator copies it). Thread-safe: the capture thread asks,
    the pipeline thread swaps.
    """

    def __init__(self) -> None:
        self.pool: FramePool | None = None

    def acquire(self, shape: tuple[int, ...]) -> np.ndarray | None:
        """A buffer of ``shape`` from the current pool, or None (no pool, another shape, none free)."""
        pool = self.pool
        if pool is None or pool.shape != tuple(shape):
            return None
        return pool.acquire()
