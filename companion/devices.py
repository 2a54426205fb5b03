"""What this machine offers the disparity backends: a CUDA device through CuPy, Numba, CPU cores."""

from __future__ import annotations

import importlib.util
import logging
import os

log = logging.getLogger(__name__)


def cuda_available() -> bool:
    """True when CuPy imports and sees at least one CUDA device."""
    if importlib.util.find_spec("cupy") is None:
        return False
    try:
        import cupy

        return cupy.cuda.runtime.getDeviceCount() > 0
    except Exception as err:  # CuPy raises several types when the driver or runtime is missing
        log.debug("CuPy present but no usable CUDA device: %s", err)
        return False


def numba_available() -> bool:
    """True when Numba (the cpu-sgm backend's compiler) is installed; nothing is imported."""
    return importlib.util.find_spec("numba") is not None


def cpu_cores() -> int:
    """CPU cores this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1
