"""The CPU census + SGM engine (``stereo.backend = "cpu-sgm"``): the rules of
:mod:`companion.core.disparity.sgm`, bit for bit, compiled with Numba and threaded over rows.

Numba is imported only when the engine is built (:class:`CpuSgmMatcher`); its kernels compile then,
or load from Numba's on-disk cache (:func:`cache_dir`), never at import time.
"""

from __future__ import annotations

import os
from types import ModuleType

from companion.cpu.matcher import CpuSgmMatcher
from companion.errors import BackendError
from companion.jitcache import cache_dir, use_cache_dir

__all__ = ["CpuSgmMatcher", "cache_dir", "load_kernels"]


def load_kernels() -> ModuleType:
    """Import Numba and :mod:`companion.cpu.kernels` with the cache pointed at :func:`cache_dir`
    (the kernels bind their cache location when their module is first imported).

    Raises:
        BackendError: the cache folder cannot be created or written.
    """
    # Numba's OpenMP workers wait for the next frame asleep, not spinning: a spinning worker takes a
    # core from the rest of the pipeline (OpenCV's threads, the service) on a small machine, and made
    # a frame several times slower there. Read when Numba's thread pool starts; the user's choice stays.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    try:
        use_cache_dir()
    except BackendError as err:
        raise BackendError(f"cpu-sgm: {err}", backend="cpu-sgm") from None
    from companion.cpu import kernels

    return kernels
