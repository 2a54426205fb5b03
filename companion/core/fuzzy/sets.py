"""Fuzzy sets over float64 arrays, in NumPy: the pieces of the Mamdani engine, each usable on its own.

* Membership functions: :func:`triangle`, :func:`trapezoid`, :func:`left_shoulder`,
  :func:`right_shoulder`, :func:`gaussian`, and :func:`membership` (by shape name). A degenerate edge
  (``a == b`` of a triangle, ...) is a vertical edge whose top point has membership 1, exactly like
  scikit-fuzzy's ``trimf``/``trapmf``.
* Operators: :func:`fuzzy_and` (``"min"`` | ``"product"``), :func:`fuzzy_or` (``"max"`` |
  ``"probabilistic_sum"``: a + b - ab), :func:`fuzzy_not` (1 - mu), :func:`implicate` (``"min"``:
  clip, ``"product"``: scale).
* :func:`defuzzify` (``"centroid"`` | ``"mean_of_maximum"`` | ``"bisector"``) of a membership
  function sampled on a universe, computed the way ``skfuzzy.defuzz`` computes it: the centroid and
  bisector are those of the piecewise-linear function through the samples, the mean of maximum is the
  mean of the samples at the maximum. An all-zero set gives ``None``, never 0 or NaN.

:class:`~companion.core.fuzzy.engine.FuzzySystem` compiles them into one vectorised inference.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Literal

import numpy as np

Shape = Literal["triangle", "trapezoid", "left_shoulder", "right_shoulder", "gaussian"]
AndMethod = Literal["min", "product"]
OrMethod = Literal["max", "probabilistic_sum"]
ImplicationMethod = Literal["min", "product"]
DefuzzMethod = Literal["centroid", "mean_of_maximum", "bisector"]

SHAPE_ARITY: Mapping[str, int] = {
    "triangle": 3,
    "trapezoid": 4,
    "left_shoulder": 2,
    "right_shoulder": 2,
    "gaussian": 2,
}

#: Inputs are clamped to this magnitude before fuzzification so that +-inf never meets an infinite
#: shoulder parameter (inf - inf = NaN); every membership at +-1e300 equals its limit at +-inf.
BIG = 1e300

# --------------------------------------------------------------------------------------------------
# Membership functions


def _ramps(x: np.ndarray, a: float, b: float, c: float, d: float) -> np.ndarray:
    """Trapezoid (a, b, c, d) with +-inf allowed for a shoulder; vertical edges are 1 at the edge."""
    with np.errstate(invalid="ignore"):
        if a == b:
            left = (x >= a).astype(np.float64)
        else:
            left = (x - a) / (b - a)
        if c == d:
            right = (x <= d).astype(np.float64)
        else:
            right = (d - x) / (d - c)
    return np.clip(np.minimum(left, right), 0.0, 1.0)


def _as_array(x: np.ndarray | Sequence[float] | float) -> np.ndarray:
    return np.clip(np.asarray(x, dtype=np.float64), -BIG, BIG)


def triangle(x: np.ndarray | Sequence[float] | float, a: float, b: float, c: float) -> np.ndarray:
    """Triangle: 0 at or below ``a``, 1 at ``b``, 0 at or above ``c`` (``a <= b <= c``).

    Args:
        x: points, any shape, float64.
    Returns:
        float64 array of the shape of ``x``, in [0, 1].
    """
    check_params("triangle", (a, b, c))
    return _ramps(_as_array(x), a, b, b, c)


def trapezoid(
    x: np.ndarray | Sequence[float] | float, a: float, b: float, c: float, d: float
) -> np.ndarray:
    """Trapezoid: 0 at or below ``a``, rising to 1 at ``b``, 1 up to ``c``, 0 at or above ``d``."""
    check_params("trapezoid", (a, b, c, d))
    return _ramps(_as_array(x), a, b, c, d)


def left_shoulder(x: np.ndarray | Sequence[float] | float, a: float, b: float) -> np.ndarray:
    """1 up to ``a``, falling linearly to 0 at ``b`` and beyond (``a == b``: a step, 1 at ``a``)."""
    check_params("left_shoulder", (a, b))
    return _ramps(_as_array(x), -math.inf, -math.inf, a, b)


def right_shoulder(x: np.ndarray | Sequence[float] | float, a: float, b: float) -> np.ndarray:
    """0 up to ``a``, rising linearly to 1 at ``b`` and beyond (``a == b``: a step, 1 at ``a``)."""
    check_params("right_shoulder", (a, b))
    return _ramps(_as_array(x), a, b, math.inf, math.inf)


def gaussian(x: np.ndarray | Sequence[float] | float, mean: float, sigma: float) -> np.ndarray:
    """exp(-(x - mean)² / (2 sigma²)), as skfuzzy's ``gaussmf`` (``sigma > 0``)."""
    check_params("gaussian", (mean, sigma))
    xx = _as_array(x)
    with np.errstate(over="ignore"):
        return np.exp(-((xx - mean) ** 2) / (2.0 * sigma * sigma))


def membership(shape: str, params: Sequence[float], x: np.ndarray | Sequence[float] | float) -> np.ndarray:
    """Evaluate the membership function ``shape(params)`` at ``x`` (float64, same shape as ``x``)."""
    fn = {
        "triangle": triangle,
        "trapezoid": trapezoid,
        "left_shoulder": left_shoulder,
        "right_shoulder": right_shoulder,
        "gaussian": gaussian,
    }.get(shape)
    if fn is None:
        raise ValueError(f"unknown membership shape {shape!r}; shapes are {', '.join(SHAPE_ARITY)}")
    check_params(shape, params)
    return fn(x, *params)  # type: ignore[operator]


def check_params(shape: str, params: Sequence[float]) -> None:
    """Refuse parameters ``shape`` cannot take: their count, a non-finite value, a sigma <= 0 or
    decreasing breakpoints.

    Raises:
        ValueError: naming the shape and what is wrong.
    """
    n = SHAPE_ARITY.get(shape)
    if n is None:
        raise ValueError(f"unknown membership shape {shape!r}; shapes are {', '.join(SHAPE_ARITY)}")
    if len(params) != n:
        raise ValueError(f"{shape} takes {n} parameters, got {len(params)}: {list(params)}")
    if not all(math.isfinite(p) for p in params):
        raise ValueError(f"{shape} parameters must be finite, got {list(params)}")
    if shape == "gaussian":
        if params[1] <= 0:
            raise ValueError(f"gaussian sigma must be > 0, got {params[1]}")
        return
    if any(q < p for p, q in zip(params, params[1:])):
        raise ValueError(f"{shape} parameters must be non-decreasing, got {list(params)}")


def trapezoid_params(shape: str, params: Sequence[float]) -> tuple[float, float, float, float]:
    """(a, b, c, d) of the trapezoid equal to a piecewise-linear shape (shoulders use +-inf)."""
    p = [float(v) for v in params]
    if shape == "triangle":
        return p[0], p[1], p[1], p[2]
    if shape == "trapezoid":
        return p[0], p[1], p[2], p[3]
    if shape == "left_shoulder":
        return -math.inf, -math.inf, p[0], p[1]
    if shape == "right_shoulder":
        return p[0], p[1], math.inf, math.inf
    raise ValueError(f"{shape} is not piecewise linear")


# --------------------------------------------------------------------------------------------------
# Operators


def fuzzy_and(a: np.ndarray | float, b: np.ndarray | float, method: AndMethod = "min") -> np.ndarray:
    """T-norm: ``min(a, b)`` or ``a·b`` (element-wise, float64)."""
    if method == "min":
        return np.minimum(a, b)
    if method == "product":
        return np.multiply(a, b)
    raise ValueError(f"unknown AND method {method!r}; use 'min' or 'product'")


def fuzzy_or(a: np.ndarray | float, b: np.ndarray | float, method: OrMethod = "max") -> np.ndarray:
    """S-norm: ``max(a, b)`` or the probabilistic sum ``a + b - a·b`` (element-wise, float64)."""
    if method == "max":
        return np.maximum(a, b)
    if method == "probabilistic_sum":
        a_ = np.asarray(a, dtype=np.float64)
        return a_ + b - a_ * b
    raise ValueError(f"unknown OR method {method!r}; use 'max' or 'probabilistic_sum'")


def fuzzy_not(a: np.ndarray | float) -> np.ndarray:
    """Complement ``1 - a`` (float64)."""
    return 1.0 - np.asarray(a, dtype=np.float64)


def implicate(
    curve: np.ndarray, strength: float | np.ndarray, method: ImplicationMethod = "min"
) -> np.ndarray:
    """Shape a consequent's sampled curve by a rule strength: clip (``min``) or scale (``product``)."""
    if method == "min":
        return np.minimum(curve, strength)
    if method == "product":
        return np.multiply(curve, strength)
    raise ValueError(f"unknown implication {method!r}; use 'min' or 'product'")


# --------------------------------------------------------------------------------------------------
# Defuzzification


def centroid_weights(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Node weights (moment, area), float64 ``(N,)``: moment = w_m·y and area = w_a·y are the first
    moment and area of the piecewise-linear function through (x, y), summed segment by segment as
    skfuzzy's ``centroid`` does (its rectangle and triangle cases are special cases of the trapezoid)."""
    x1, x2 = x[:-1], x[1:]
    dx = x2 - x1
    wm = np.zeros_like(x)
    wa = np.zeros_like(x)
    # Segment moment·area = dx²/3·(y2 + y1/2) + x1·dx/2·(y1 + y2).
    wm[:-1] += dx * dx / 6.0 + x1 * dx / 2.0
    wm[1:] += dx * dx / 3.0 + x1 * dx / 2.0
    wa[:-1] += dx / 2.0
    wa[1:] += dx / 2.0
    return wm, wa


def _bisector_in_segment(x1: float, x2: float, y1: float, y2: float, sub: float) -> float:
    """The point u in [x1, x2] where the area under the segment from x1 reaches ``sub``.

    Solves y1·t + m·t²/2 = sub (t = u - x1, m = slope) in the cancellation-free form
    t = 2·sub / (y1 + sqrt(y1² + 2·m·sub)), which also covers skfuzzy's rectangle (m = 0) and
    triangle (y1 = 0) cases.
    """
    m = (y2 - y1) / (x2 - x1)
    root = math.sqrt(max(y1 * y1 + 2.0 * m * sub, 0.0))
    den = y1 + root
    if den <= 0.0:
        return x1
    return min(max(x1 + 2.0 * sub / den, x1), x2)


def bisector_from_cum(x: np.ndarray, y: np.ndarray, cum: np.ndarray, total: float) -> float:
    """The bisector of the set ``y`` sampled on ``x`` (float64 ``(N,)`` each), given ``cum``, the
    cumulative area of its ``N - 1`` trapezoid segments, and ``total`` > 0, their sum."""
    half = total / 2.0
    i = int(np.searchsorted(cum, half, side="left"))  # first segment with cumulative area >= half
    i = min(i, len(cum) - 1)
    before = float(cum[i - 1]) if i > 0 else 0.0
    return _bisector_in_segment(float(x[i]), float(x[i + 1]), float(y[i]), float(y[i + 1]), half - before)


def defuzzify(x: np.ndarray, mfx: np.ndarray, method: DefuzzMethod = "centroid") -> float | None:
    """Defuzzify the set sampled as ``mfx`` on the universe ``x``.

    Args:
        x: float64 ``(N,)``, strictly increasing, N >= 2.
        mfx: float64 ``(N,)``, memberships in [0, 1].
        method: ``centroid`` (of the piecewise-linear function through the samples), ``mean_of_maximum``
            (mean of the samples at the maximum), ``bisector`` (the point halving the area under the
            piecewise-linear function).

    Returns:
        The crisp value, or ``None`` when the set is empty (all zero): nothing fired.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(mfx, dtype=np.float64)
    if x.ndim != 1 or x.shape != y.shape or len(x) < 2:
        raise ValueError(f"x and mfx must be 1-d of one length >= 2, got {x.shape} and {y.shape}")
    if np.isnan(y).any():
        raise ValueError("mfx contains NaN")
    if method == "centroid":
        wm, wa = centroid_weights(x)
        area = float(wa @ y)
        return float(wm @ y) / area if area > 0.0 else None
    if method == "mean_of_maximum":
        top = y.max()
        return float(np.mean(x[y == top])) if top > 0.0 else None
    if method == "bisector":
        cum = np.cumsum(0.5 * np.diff(x) * (y[:-1] + y[1:]))
        total = float(cum[-1])
        return bisector_from_cum(x, y, cum, total) if total > 0.0 else None
    raise ValueError(f"unknown defuzzification {method!r}; use centroid, mean_of_maximum or bisector")

