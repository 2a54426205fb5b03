"""Depth refinement look-up table (paper section VI) and the per-region median and release filters.

The LUT maps a computed depth to a true depth piecewise-linearly through measured pairs, clamped to
the table's ends. The median filter outvotes a reading that lasts one frame (a false stereo match
rarely survives two frames; an obstacle does). The release filter keeps an approaching obstacle
instant and smooths a receding one, so a flickering near match does not make the region depth bounce
back to far every other frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from companion.config.core import LutConfig


class DepthLUT:
    """Piecewise-linear map computed depth (m) -> true depth (m).

    Args:
        points_m: ``(computed, true)`` pairs in metres; at least two; both columns strictly
            increasing and positive (finite).

    Raises:
        ValueError: fewer than two points, or a point that is non-positive, non-finite or not
            strictly after its predecessor (the message names the point's index and values).
    """

    def __init__(self, points_m: Sequence[tuple[float, float]]) -> None:
        pts = [tuple(p) for p in points_m]
        if len(pts) < 2:
            raise ValueError(f"a depth LUT needs at least 2 points, got {len(pts)}")
        for i, p in enumerate(pts):
            if len(p) != 2:
                raise ValueError(f"LUT point {i} must be a (computed, true) pair, got {p}")
            c, t = float(p[0]), float(p[1])
            if not (math.isfinite(c) and math.isfinite(t) and c > 0 and t > 0):
                raise ValueError(f"LUT point {i} ({c}, {t}): depths must be finite and positive")
            if i > 0:
                c0, t0 = float(pts[i - 1][0]), float(pts[i - 1][1])
                if not c > c0:
                    raise ValueError(
                        f"LUT point {i} ({c}, {t}): computed depth must be strictly greater than "
                        f"point {i - 1}'s {c0} m"
                    )
                if not t > t0:
                    raise ValueError(
                        f"LUT point {i} ({c}, {t}): true depth must be strictly greater than "
                        f"point {i - 1}'s {t0} m"
                    )
        arr = np.array(pts, dtype=np.float64)
        self._computed = arr[:, 0].copy()
        self._true = arr[:, 1].copy()
        self._computed.flags.writeable = False
        self._true.flags.writeable = False

    @classmethod
    def from_config(cls, cfg: LutConfig) -> DepthLUT:
        """The LUT that ``cfg.points_m`` describes."""
        return cls(cfg.points_m)

    @property
    def computed_m(self) -> np.ndarray:
        """float64 ``(n,)``: the table's computed depths, metres (read-only)."""
        return self._computed

    @property
    def true_m(self) -> np.ndarray:
        """float64 ``(n,)``: the table's true depths, metres (read-only)."""
        return self._true

    def apply(self, depth_m: np.ndarray) -> np.ndarray:
        """Refined depth.

        Args:
            depth_m: depths in metres, any shape (region depths float64 ``(9,)``, or an image).

        Returns:
            Same shape; float32 for float32 input, else float64. Below the first computed depth ->
            the first true depth; above the last (``+inf`` included) -> the last true depth; NaN
            (unknown) stays NaN.
        """
        d = np.asarray(depth_m)
        res = np.interp(d, self._computed, self._true)  # clamps to fp[0] / fp[-1]; NaN -> NaN
        if d.dtype == np.float32:
            return res.astype(np.float32)
        return res

    def __repr__(self) -> str:
        return f"DepthLUT({list(zip(self._computed.tolist(), self._true.tolist()))})"


def median_filter(history_m: Sequence[np.ndarray], new_m: np.ndarray, frames: int) -> np.ndarray:
    """Per-region median of the last ``frames`` frames (``history_m`` then ``new_m``): a reading that
    lasts one frame (a false stereo match, or a near region that drops out to far for a frame) is
    outvoted; an obstacle that appears at once counts one frame later.

    * new NaN (unknown) -> NaN at once: unknown is treated as near and is never delayed;
    * a NaN in the history counts as 0 m (unknown was near then), so it never makes a region farther;
    * fewer than ``frames - 1`` history frames (start-up), or ``frames`` <= 1 -> ``new_m``.

    Args:
        history_m: the previous frames' depths, oldest first (float, each the shape of ``new_m``), metres;
            only the newest ``frames - 1`` are used.
        new_m: float ``(9,)`` (any shape), this frame's depths, metres, NaN = unknown.
        frames: the window, frames (odd, >= 1).

    Returns:
        float64 array of ``new_m``'s shape, metres.

    Raises:
        ValueError: an even ``frames``, or a history array of another shape.
    """
    if frames % 2 == 0:
        raise ValueError(f"frames must be odd, got {frames}")
    new = np.array(new_m, dtype=np.float64)
    if frames <= 1 or len(history_m) < frames - 1:
        return new
    window = [np.asarray(h, dtype=np.float64) for h in list(history_m)[-(frames - 1):]]
    for h in window:
        if h.shape != new.shape:
            raise ValueError(f"history {h.shape} and new_m {new.shape} differ in shape")
    stack = np.stack([*(np.nan_to_num(h, nan=0.0) for h in window), new])
    out = np.sort(stack, axis=0)[frames // 2]  # the median of an odd count; np.median is 5x slower here
    out[np.isnan(new)] = np.nan
    return out


def release_filter(
    previous_m: np.ndarray | None, new_m: np.ndarray, dt_s: float, time_constant_s: float
) -> np.ndarray:
    """Asymmetric per-region low-pass: approach passes at once, release is smoothed.

    Per element (region):

    * new NaN (unknown) -> NaN: unknown is never hidden by memory;
    * no previous (``None``) or previous NaN -> new;
    * new <= previous (obstacle approaching) -> new, immediately;
    * new > previous (receding) -> ``prev + alpha·(new - prev)``, ``alpha = 1 - exp(-dt/τ)``, never
      above ``new``; ``τ = 0`` -> new (pass-through); ``dt = 0`` with ``τ > 0`` -> prev.

    So the output always lies in ``[min(prev, new), new]``: never farther than the newest sample.

    Args:
        previous_m: float ``(9,)`` (any shape) last output, metres, or ``None`` on the first frame.
        new_m: float, same shape, this frame's depths, metres, NaN = unknown.
        dt_s: time since the previous output, seconds (>= 0); passed in, no clocks here.
        time_constant_s: release time constant τ, seconds (>= 0).

    Returns:
        float64 array of ``new_m``'s shape, metres.

    Raises:
        ValueError: negative or non-finite ``dt_s``/``time_constant_s``, or mismatched shapes.
    """
    new = np.array(new_m, dtype=np.float64)
    if not (math.isfinite(dt_s) and dt_s >= 0):
        raise ValueError(f"dt_s must be finite and >= 0, got {dt_s}")
    if not (math.isfinite(time_constant_s) and time_constant_s >= 0):
        raise ValueError(f"time_constant_s must be finite and >= 0, got {time_constant_s}")
    if previous_m is None or time_constant_s == 0:
        return new
    prev = np.asarray(previous_m, dtype=np.float64)
    if prev.shape != new.shape:
        raise ValueError(f"previous_m {prev.shape} and new_m {new.shape} differ in shape")
    alpha = -math.expm1(-dt_s / time_constant_s)  # 1 - exp(-dt/τ), accurate for small dt/τ
    grow = new > prev  # False where either is NaN: NaN new stays NaN, NaN prev takes new
    if alpha > 0:
        with np.errstate(invalid="ignore"):
            step = prev + alpha * (new - prev)
        # Rounding could put prev + 1·(new - prev) a hair above new; inf new gives inf (alpha > 0).
        np.minimum(step, new, out=step)
    else:
        step = prev
    return np.where(grow, step, new)


def fit_lut(
    computed_m: Sequence[float],
    true_m: Sequence[float],
    *,
    extend_to_m: tuple[float, float] | None = (0.2, 40.0),
    decimals: int = 3,
) -> list[tuple[float, float]]:
    """The paper's depth refinement table from measurements: the pipeline's computed depth of a flat
    target at measured true distances.

    1. Captures at the same true distance are pooled: their median computed depth.
    2. The computed depths are made monotone in the true distance (pool-adjacent-violators, weighted
       by the captures pooled): a table whose computed column went back would not be a function.
    3. Points that still share a computed depth are merged (their mean true distance).
    4. With ``extend_to_m = (lo, hi)``, the table is extended to ``lo`` and ``hi`` computed metres by
       the nearest point's ratio true/computed (a scale error, the usual one of a wrong baseline or
       focal length, is a ratio); else depths outside the measured range clamp to its ends.

    Args:
        computed_m, true_m: one pair per capture, metres (finite, > 0).
        extend_to_m: see 4, or None.
        decimals: rounding of the table's values (mm by default).

    Returns:
        ``[(computed, true), ...]``, both strictly increasing: a valid ``lut.points_m``.

    Raises:
        ValueError: mismatched lengths, a non-positive or non-finite depth, or fewer than two
            distinct true distances (the message says which).
    """
    c = np.asarray(computed_m, dtype=np.float64).reshape(-1)
    t = np.asarray(true_m, dtype=np.float64).reshape(-1)
    if c.shape != t.shape:
        raise ValueError(f"{c.size} computed depths but {t.size} true distances")
    for name, a in (("computed", c), ("true", t)):
        bad = ~(np.isfinite(a) & (a > 0))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"{name} depth #{i + 1} is {a[i]}: depths must be finite and positive")
    distances = np.unique(t)
    if distances.size < 2:
        raise ValueError(
            f"at least 2 different true distances are needed, got {distances.size} "
            f"({', '.join(f'{d:g} m' for d in distances)})"
        )
    pooled_c = np.array([np.median(c[t == d]) for d in distances])
    weight = np.array([np.count_nonzero(t == d) for d in distances], dtype=np.float64)
    # Pool adjacent violators: blocks of (value, weight, members).
    blocks: list[list[float]] = []  # [mean computed, weight, first index, last index]
    for i in range(distances.size):
        blocks.append([float(pooled_c[i]), float(weight[i]), i, i])
        while len(blocks) > 1 and blocks[-2][0] >= blocks[-1][0]:
            v2, w2, _, l2 = blocks.pop()
            v1, w1, f1, _ = blocks.pop()
            blocks.append([(v1 * w1 + v2 * w2) / (w1 + w2), w1 + w2, f1, l2])
    points = []
    for value, _, first, last in blocks:
        members = slice(int(first), int(last) + 1)
        points.append((value, float(np.average(distances[members], weights=weight[members]))))
    if extend_to_m is not None:
        lo, hi = extend_to_m
        (c0, t0), (cn, tn) = points[0], points[-1]
        if lo < c0:
            points.insert(0, (lo, lo * t0 / c0))
        if hi > cn:
            points.append((hi, hi * tn / cn))
    table: list[tuple[float, float]] = []
    for pc, pt in points:
        rc, rt = round(pc, decimals), round(pt, decimals)
        if table and (rc <= table[-1][0] or rt <= table[-1][1]):
            continue  # rounding made it equal to its neighbour: one of the two is enough
        table.append((rc, rt))
    if len(table) < 2:
        raise ValueError("the measurements collapse to a single point: the target read the same at every distance")
    return table
