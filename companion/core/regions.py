"""The nine-region layout and the robust per-region minimum depth (paper section VII).

**Layout.** The centre region is the safe window (``safe_window_width_m × safe_window_height_m``)
projected at ``reference_distance_m`` through the rectified focal length: ``width_px =
round(f·w/z)``, ``height_px = round(f·h/z)`` (round half up), centred on the principal point
``(cx, cy)``: the first column is ``round(cx - (width_px - 1) / 2)`` (pixel centres are at integer
coordinates, so a span ``[c0, c0 + n)`` is centred on ``c0 + (n - 1) / 2``). The other eight regions
are the bands around it (paper Fig. 5). Clamping, so that every region keeps at least one row and one
column: the size is clamped to ``[1, size - 2]`` and then the start to ``[1, size - 1 - n]``. So a
window larger than the image becomes the image less a one-pixel margin on each side, and a window
pushed off-centre by the principal point is slid back inside; :attr:`RegionLayout.clamped` says
when either happened. An image smaller than 3×3 cannot hold nine regions (ValueError).

**Robust minimum** (:func:`reduce_regions`). Per region, with ``n_valid`` the number of non-NaN
depths and ``area`` its pixel count:

* ``valid_fraction = n_valid / area``;
* if ``valid_fraction < min_valid_fraction`` the region is unknown (NaN);
* else ``k = max(1, ceil(robust_percentile_pct · n_valid / 100))`` (float64, product first) and the
  region depth is the **k-th smallest valid depth** (``k = 1``, e.g. at 0 %, is the raw minimum, the
  paper's choice), then ``min(value, max_depth_m)`` (so ``+inf`` reports ``max_depth_m``).

It is an order statistic, not an interpolated percentile, on purpose: the GPU path computes the same
value from a per-region histogram of integer disparities (the k-th *largest* valid disparity gives
the k-th smallest depth, because ``z = f·B/d`` is decreasing), and an order statistic is exactly
reproducible that way where an interpolated percentile is not. :func:`reduce_regions_from_disparity`
is that formulation on the CPU; on a disparity image and its :func:`~companion.core.depth.disparity_to_depth`
the two functions return identical results.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.config.core import RegionsConfig
from companion.core.geometry import StereoGeometry
from companion.core.types import N_REGIONS, REGION_NAMES, RegionDepths


def _round_half_up(x: float) -> int:
    return int(math.floor(x + 0.5))


@dataclass(frozen=True)
class RegionLayout:
    """Where the nine regions are in an image.

    Attributes:
        row_edges: int64 ``(4,)``, pixel rows ``0 = e0 < e1 < e2 < e3 = height``; region row band
            ``k`` is ``[e_k, e_{k+1})`` (0 = up, 1 = middle, 2 = down). Read-only.
        col_edges: int64 ``(4,)``, same for columns (0 = left, 1 = middle, 2 = right). Read-only.
        clamped: True when the centre region had to be shrunk or moved to fit (see module doc).
    """

    row_edges: np.ndarray
    col_edges: np.ndarray
    clamped: bool = False

    def __post_init__(self) -> None:
        rows = np.array(self.row_edges, dtype=np.int64).reshape(-1)
        cols = np.array(self.col_edges, dtype=np.int64).reshape(-1)
        for label, e in (("row_edges", rows), ("col_edges", cols)):
            if e.shape != (4,) or e[0] != 0 or not np.all(np.diff(e) > 0):
                raise ValueError(
                    f"{label} must be 4 strictly increasing ints starting at 0, got {e.tolist()}"
                )
        rows.flags.writeable = False
        cols.flags.writeable = False
        object.__setattr__(self, "row_edges", rows)
        object.__setattr__(self, "col_edges", cols)

    @property
    def height_px(self) -> int:
        return int(self.row_edges[3])

    @property
    def width_px(self) -> int:
        return int(self.col_edges[3])

    @property
    def area_px(self) -> np.ndarray:
        """int64 ``(9,)``: pixel count of each region in :data:`REGION_NAMES` order."""
        return np.outer(np.diff(self.row_edges), np.diff(self.col_edges)).reshape(N_REGIONS)

    def region_slices(self, i: int) -> tuple[slice, slice]:
        """``(rows, cols)`` slices of region ``i`` (index into :data:`REGION_NAMES`, row-major)."""
        if not 0 <= i < N_REGIONS:
            raise IndexError(f"region index {i} out of range 0..{N_REGIONS - 1}")
        rk, ck = divmod(i, 3)
        re, ce = self.row_edges, self.col_edges
        return slice(int(re[rk]), int(re[rk + 1])), slice(int(ce[ck]), int(ce[ck + 1]))

    def region_slices_by_name(self, name: str) -> tuple[slice, slice]:
        """``(rows, cols)`` slices of the region called ``name`` (one of :data:`REGION_NAMES`)."""
        return self.region_slices(REGION_NAMES.index(name))


def _centre_span(size: int, extent_px: float, centre_px: float) -> tuple[int, int, bool]:
    """Start and end ``[a, b)`` of the centre band along one axis, clamped to leave ≥ 1 px each side."""
    n = _round_half_up(extent_px)
    n_c = min(max(n, 1), size - 2)
    a = _round_half_up(centre_px - (n_c - 1) / 2.0)
    a_c = min(max(a, 1), size - 1 - n_c)
    return a_c, a_c + n_c, (n_c != n or a_c != a)


def region_layout(geometry: StereoGeometry, cfg: RegionsConfig) -> RegionLayout:
    """The nine regions for a rectified rig (centre = projected safe window; see module doc).

    For ``f = 450 px`` and the defaults (0.5 m at 1.5 m) the centre region is 150×150 px.

    Raises:
        ValueError: the image is smaller than 3×3 px.
    """
    w, h = geometry.width_px, geometry.height_px
    if w < 3 or h < 3:
        raise ValueError(f"image {w}x{h} px is too small for 3x3 regions (need at least 3x3)")
    f, z = geometry.focal_px, cfg.reference_distance_m
    c0, c1, cc = _centre_span(w, f * cfg.safe_window_width_m / z, geometry.cx_px)
    r0, r1, rc = _centre_span(h, f * cfg.safe_window_height_m / z, geometry.cy_px)
    return RegionLayout(
        row_edges=np.array([0, r0, r1, h]), col_edges=np.array([0, c0, c1, w]), clamped=cc or rc
    )


def _check_image(img: np.ndarray, layout: RegionLayout, what: str) -> None:
    if img.ndim != 2 or img.shape != (layout.height_px, layout.width_px):
        raise ValueError(
            f"{what} image {img.shape} does not match the region layout "
            f"({layout.height_px}, {layout.width_px})"
        )


def _rank(pct: float, n_valid: int) -> int:
    # Product first: pct·n is exact for the usual percentages, so an exact multiple of 100 divides exactly.
    return max(1, math.ceil(pct * n_valid / 100.0))


def _result(out: RegionDepths | None) -> RegionDepths:
    if out is None:
        return RegionDepths(depth_m=np.empty(N_REGIONS), valid_fraction=np.empty(N_REGIONS))
    for label, a in (("depth_m", out.depth_m), ("valid_fraction", out.valid_fraction)):
        if a.shape != (N_REGIONS,) or a.dtype != np.float64:
            raise ValueError(f"out.{label} must be float64 ({N_REGIONS},), got {a.dtype} {a.shape}")
    return out


def reduce_regions(
    depth: np.ndarray, layout: RegionLayout, cfg: RegionsConfig, out: RegionDepths | None = None
) -> RegionDepths:
    """Robust per-region minimum depth (the k-th smallest valid depth; see module doc).

    Args:
        depth: float32 ``(H, W)`` depth, metres; NaN = invalid, ``+inf`` = valid at disparity 0.
        layout: the region layout for this image size.
        cfg: percentile, minimum valid share, max depth.
        out: optional preallocated result whose two float64 ``(9,)`` arrays are overwritten and
            which is returned (so it aliases the previous frame's result).

    Returns:
        :class:`RegionDepths`: ``depth_m`` float64 ``(9,)`` metres (NaN unknown, at most
        ``max_depth_m``), ``valid_fraction`` float64 ``(9,)`` in [0, 1].
    """
    depth = np.asarray(depth)
    _check_image(depth, layout, "depth")
    res = _result(out)
    areas = layout.area_px
    for i in range(N_REGIONS):
        rs, cs = layout.region_slices(i)
        # One copy per region; NaN sorts after every number (+inf included) in np.partition, so the
        # first n_valid entries after partitioning are exactly the valid depths.
        vals = depth[rs, cs].flatten()  # always a copy: partitioned in place below
        n_valid = int(vals.size - np.count_nonzero(np.isnan(vals)))
        res.valid_fraction[i] = n_valid / int(areas[i])
        if n_valid == 0 or res.valid_fraction[i] < cfg.min_valid_fraction:
            res.depth_m[i] = np.nan
            continue
        k = _rank(cfg.robust_percentile_pct, n_valid)
        if k == 1:
            v = float(np.nanmin(vals)) if n_valid < vals.size else float(vals.min())
        else:
            vals.partition(k - 1)
            v = float(vals[k - 1])
        res.depth_m[i] = min(v, cfg.max_depth_m)
    return res


def reduce_regions_from_disparity(
    disparity: np.ndarray,
    layout: RegionLayout,
    cfg: RegionsConfig,
    focal_baseline_px_m: float,
    out: RegionDepths | None = None,
) -> RegionDepths:
    """:func:`reduce_regions` computed from disparity: the k-th *largest* valid disparity per region.

    Valid disparities are the non-NaN, non-negative ones (exactly the pixels whose depth from
    :func:`~companion.core.depth.disparity_to_depth` is not NaN). The chosen disparity ``d`` becomes
    ``f·B/d`` in float32 like ``disparity_to_depth`` (``d == 0`` -> ``+inf``), then
    ``min(z, max_depth_m)``; so the result equals ``reduce_regions(disparity_to_depth(disparity))``
    for a float32 disparity image.

    Args:
        disparity: float32 ``(H, W)`` px, NaN = invalid.
        layout, cfg, out: as for :func:`reduce_regions`.
        focal_baseline_px_m: ``f·B``, pixel·metres.
    """
    disparity = np.asarray(disparity)
    _check_image(disparity, layout, "disparity")
    fb = np.float32(focal_baseline_px_m)
    if not (np.isfinite(fb) and fb > 0):
        raise ValueError(f"focal_baseline_px_m must be finite and > 0, got {focal_baseline_px_m}")
    res = _result(out)
    areas = layout.area_px
    for i in range(N_REGIONS):
        rs, cs = layout.region_slices(i)
        vals = disparity[rs, cs].flatten()  # always a copy: partitioned in place below
        n_nan = int(np.count_nonzero(np.isnan(vals)))
        n_neg = int(np.count_nonzero(vals < 0))
        n_valid = vals.size - n_nan - n_neg
        res.valid_fraction[i] = n_valid / int(areas[i])
        if n_valid == 0 or res.valid_fraction[i] < cfg.min_valid_fraction:
            res.depth_m[i] = np.nan
            continue
        k = _rank(cfg.robust_percentile_pct, n_valid)
        # Ascending order is: negatives, valid (n_valid), NaN; the k-th largest valid sits at
        # index n_neg + n_valid - k.
        j = n_neg + n_valid - k
        if k == 1 and n_nan == 0:
            d = vals.max()
        else:
            vals.partition(j)
            d = vals[j]
        with np.errstate(divide="ignore"):
            z = np.float32(np.inf) if d == 0 else np.float32(fb / np.float32(d))
        res.depth_m[i] = min(float(z), cfg.max_depth_m)
    return res
