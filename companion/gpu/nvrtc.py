"""The GPU estimator's CUDA modules: the kernel sources shipped in ``companion/gpu/kernels`` and their
compilation with NVRTC, once per shape.

Each module is the kernel file with the shape of one configuration prepended as ``#define`` lines
(:mod:`companion.gpu.plan`), so that every loop bound is a compile-time constant. CuPy keeps the
compiled binaries on disk: a second estimator of the same shape loads them instead of compiling.

* ``stereo.cu``: grey, remap, SAD block matching with the region histograms fused in, the preview's
  and the map's blocks;
* ``sgm.cu``: census + semi-global matching, and the near-range check's shrunk pair;
* ``obstacle.cu``: OBSTACLE_DISTANCE's 72 bins from the device disparity.

Importing this module does not import CuPy; :func:`import_cupy` does.
"""

from __future__ import annotations

import importlib.resources
from collections.abc import Sequence
from typing import Any

from companion.errors import BackendError
from companion.gpu.plan import (
    OBSTACLE_THREADS,
    DisparityPlan,
    SgmPlan,
    kernel_defines,
    obstacle_defines,
    sgm_defines,
)

#: NVRTC's options for every module. ``--fmad=false``: the remap's float arithmetic must round exactly
#: like OpenCV's (explicit fmaf only); nothing else in the modules is floating point on the hot path.
NVRTC_OPTIONS = ("--std=c++17", "--fmad=false")


def kernel_source(name: str = "stereo.cu") -> str:
    """The CUDA source of a kernel file (``companion/gpu/kernels/stereo.cu`` or ``sgm.cu``), without the #defines."""
    return (importlib.resources.files("companion.gpu") / "kernels" / name).read_text(encoding="utf-8")


def import_cupy() -> Any:
    """The ``cupy`` module.

    Raises:
        BackendError: CuPy is not installed (``companion[gpu]``).
    """
    try:
        import cupy
    except ImportError as err:  # the caller asked for the GPU explicitly
        raise BackendError(f"the cupy backend needs CuPy ({err}); install companion[gpu]") from None
    return cupy


def compile_module(cp: Any, code: str) -> Any:
    """A CuPy ``RawModule`` of ``code`` with :data:`NVRTC_OPTIONS`."""
    return cp.RawModule(code=code, options=NVRTC_OPTIONS)


def stereo_module(cp: Any, plan: DisparityPlan, row_edges: Sequence[int], col_edges: Sequence[int]) -> Any:
    """``stereo.cu`` for one SAD plan and region layout (the regions' row and column edges, px)."""
    return compile_module(cp, kernel_defines(plan, row_edges, col_edges) + kernel_source())


def sgm_module(
    cp: Any, plan: SgmPlan, pitch_bytes: int, row_edges: Sequence[int], col_edges: Sequence[int]
) -> Any:
    """``sgm.cu`` for one SGM plan, row pitch of the rectified images (bytes) and region layout (px)."""
    return compile_module(cp, sgm_defines(plan, pitch_bytes, row_edges, col_edges) + kernel_source("sgm.cu"))


def obstacle_module(cp: Any) -> Any:
    """``obstacle.cu`` with :data:`~companion.gpu.plan.OBSTACLE_THREADS` threads a block."""
    return compile_module(cp, obstacle_defines(OBSTACLE_THREADS) + kernel_source("obstacle.cu"))
