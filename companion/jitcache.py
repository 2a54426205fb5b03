"""Where Numba keeps the compiled kernels between processes (the CPU matcher's, the planner's and
its map's), so that a service restart or a simulated flight loads them in under a second instead of
compiling them again (about 10 s for the planner's on a 2-core machine, 1.5 min for the matcher's).

The folder is ``NUMBA_CACHE_DIR`` when set (the systemd unit sets ``/var/cache/companion/numba``),
else ``$XDG_CACHE_HOME/companion/numba`` (``~/.cache`` without it); never next to the installed
source. Kernel modules bind their cache when first imported: a module imported before
:func:`use_cache_dir` compiles in memory for that process.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from companion.errors import BackendError

__all__ = ["cache_dir", "use_cache_dir", "use_cache_dir_or_memory"]


def cache_dir() -> Path:
    """The folder for the compiled kernels (see the module doc); not created here."""
    env = os.environ.get("NUMBA_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "companion" / "numba"


def use_cache_dir() -> Path:
    """Point Numba's cache at :func:`cache_dir` (created if missing) unless it already points
    somewhere; return where it points.

    Raises:
        BackendError: the folder cannot be created or written.
    """
    import numba

    if numba.config.CACHE_DIR:
        return Path(numba.config.CACHE_DIR)
    folder = cache_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise BackendError(
            f"cannot create the compiled kernels' cache folder {folder} ({err.strerror}); "
            "set NUMBA_CACHE_DIR to a writable folder", folder=str(folder)
        ) from None
    if not os.access(folder, os.W_OK):
        raise BackendError(
            f"the compiled kernels' cache folder {folder} is not writable; set NUMBA_CACHE_DIR to a "
            "writable folder", folder=str(folder)
        )
    numba.config.CACHE_DIR = str(folder)
    return folder


def use_cache_dir_or_memory(log: logging.Logger) -> Path | None:
    """:func:`use_cache_dir`, or, where the folder cannot be written, one warning and kernels compiled
    in memory at every start (slower to start, the same kernels); the folder or None."""
    try:
        return use_cache_dir()
    except BackendError as err:
        log.warning("%s: the planner's kernels compile in memory at every start", err)
        return None
