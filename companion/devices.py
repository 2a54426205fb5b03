"""What this machine offers the disparity backends: a CUDA device through CuPy."""

from __future__ import annotations

import importlib.util
import logging

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
