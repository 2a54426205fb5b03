"""The CPU census + SGM engine (``stereo.backend = "cpu-sgm"``): the rules of
:mod:`companion.core.disparity.sgm`, bit for bit, compiled with Numba and threaded over rows.

Numba is imported only when the engine is built (:class:`CpuSgmMatcher`); its kernels compile then,
or load from Numba's on-disk cache (:func:`cache_dir`), never at import time.
"""

from __future__ import annotations

import os
from pathlib import Path
from types import ModuleType

from companion.cpu.matcher import CpuSgmMatcher
from companion.errors import BackendError

__all__ = ["CpuSgmMatcher", "cache_dir", "load_kernels"]


def cache_dir() -> Path:
    """Where the compiled kernels are cached: ``NUMBA_CACHE_DIR`` when set (the systemd unit sets
    ``/var/cache/companion/numba``), else ``$XDG_CACHE_HOME/companion/numba`` (``~/.cache`` without
    it); never next to the installed source."""
    env = os.environ.get("NUMBA_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "companion" / "numba"


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
    import numba

    if not numba.config.CACHE_DIR:
        folder = cache_dir()
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise BackendError(
                f"cpu-sgm: cannot create the compiled kernels' cache folder {folder} ({err.strerror}); "
                "set NUMBA_CACHE_DIR to a writable folder",
                backend="cpu-sgm",
            ) from None
        if not os.access(folder, os.W_OK):
            raise BackendError(
                f"cpu-sgm: the compiled kernels' cache folder {folder} is not writable; set NUMBA_CACHE_DIR "
                "to a writable folder",
                backend="cpu-sgm",
            )
        numba.config.CACHE_DIR = str(folder)
    from companion.cpu import kernels

    return kernels
