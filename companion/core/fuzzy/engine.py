"""A small, generic Mamdani fuzzy inference engine in NumPy, compiled once and then vectorised.

Pieces (each also usable on its own):

* Membership functions over float64 arrays: :func:`triangle`, :func:`trapezoid`,
  :func:`left_shoulder`, :func:`right_shoulder`, :func:`gaussian`, and :func:`membership` (by shape
  name). A degenerate edge (``a == b`` of a triangle, ...) is a vertical edge whose top point has
  membership 1, exactly like scikit-fuzzy's ``trimf``/``trapmf``.
* Operators: :func:`fuzzy_and` (``"min"`` | ``"product"``), :func:`fuzzy_or` (``"max"`` |
  ``"probabilistic_sum"``: a + b - ab), :func:`fuzzy_not` (1 - mu), :func:`implicate` (``"min"``:
  clip, ``"product"``: scale).
* :func:`defuzzify` (``"centroid"`` | ``"mean_of_maximum"`` | ``"bisector"``) of a membership
  function sampled on a universe, computed the way ``skfuzzy.defuzz`` computes it: the centroid and
  bisector are those of the piecewise-linear function through the samples, the mean of maximum is the
  mean of the samples at the maximum. An all-zero set gives ``None``, never 0 or NaN.
* :class:`FuzzySystem`: inputs, outputs (sampled universes), weighted rules. The constructor compiles
  the system into parameter arrays and index matrices, so that :meth:`FuzzySystem.infer` is a fixed,
  short sequence of vectorised NumPy calls (tens of microseconds for the avoidance controller).

Inference (Mamdani): fuzzify every (input, term) pair; a rule's strength is the AND (or OR) of its
clauses, a ``not`` clause using 1 - mu, times the rule's weight; each rule shapes its consequent terms
by implication; the shaped sets of one output are aggregated with max and defuzzified. An output whose
rules all have strength 0 did not fire: its value is ``None`` and its ``fired`` flag False.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from companion.config.rules import Antecedent, parse_antecedent
from companion.errors import ConfigError

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

# Inputs are clamped to this magnitude before fuzzification so that +-inf never meets an infinite
# shoulder parameter (inf - inf = NaN); every membership at +-1e300 equals its limit at +-inf.
_BIG = 1e300

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
    return np.clip(np.asarray(x, dtype=np.float64), -_BIG, _BIG)


def triangle(x: np.ndarray | Sequence[float] | float, a: float, b: float, c: float) -> np.ndarray:
    """Triangle: 0 at or below ``a``, 1 at ``b``, 0 at or above ``c`` (``a <= b <= c``).

    Args:
        x: points, any shape, float64.
    Returns:
        float64 array of the shape of ``x``, in [0, 1].
    """
    _check_params("triangle", (a, b, c))
    return _ramps(_as_array(x), a, b, b, c)


def trapezoid(
    x: np.ndarray | Sequence[float] | float, a: float, b: float, c: float, d: float
) -> np.ndarray:
    """Trapezoid: 0 at or below ``a``, rising to 1 at ``b``, 1 up to ``c``, 0 at or above ``d``."""
    _check_params("trapezoid", (a, b, c, d))
    return _ramps(_as_array(x), a, b, c, d)


def left_shoulder(x: np.ndarray | Sequence[float] | float, a: float, b: float) -> np.ndarray:
    """1 up to ``a``, falling linearly to 0 at ``b`` and beyond (``a == b``: a step, 1 at ``a``)."""
    _check_params("left_shoulder", (a, b))
    return _ramps(_as_array(x), -math.inf, -math.inf, a, b)


def right_shoulder(x: np.ndarray | Sequence[float] | float, a: float, b: float) -> np.ndarray:
    """0 up to ``a``, rising linearly to 1 at ``b`` and beyond (``a == b``: a step, 1 at ``a``)."""
    _check_params("right_shoulder", (a, b))
    return _ramps(_as_array(x), a, b, math.inf, math.inf)


def gaussian(x: np.ndarray | Sequence[float] | float, mean: float, sigma: float) -> np.ndarray:
    """exp(-(x - mean)² / (2 sigma²)), as skfuzzy's ``gaussmf`` (``sigma > 0``)."""
    _check_params("gaussian", (mean, sigma))
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
    _check_params(shape, params)
    return fn(x, *params)  # type: ignore[operator]


def _check_params(shape: str, params: Sequence[float]) -> None:
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


def _trapezoid_params(shape: str, params: Sequence[float]) -> tuple[float, float, float, float]:
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


def _centroid_weights(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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


def _bisector_from_cum(x: np.ndarray, y: np.ndarray, cum: np.ndarray, total: float) -> float:
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
        wm, wa = _centroid_weights(x)
        area = float(wa @ y)
        return float(wm @ y) / area if area > 0.0 else None
    if method == "mean_of_maximum":
        top = y.max()
        return float(np.mean(x[y == top])) if top > 0.0 else None
    if method == "bisector":
        cum = np.cumsum(0.5 * np.diff(x) * (y[:-1] + y[1:]))
        total = float(cum[-1])
        return _bisector_from_cum(x, y, cum, total) if total > 0.0 else None
    raise ValueError(f"unknown defuzzification {method!r}; use centroid, mean_of_maximum or bisector")


# --------------------------------------------------------------------------------------------------
# System description


@dataclass(frozen=True)
class Term:
    """A named membership function ``shape(params)``."""

    name: str
    shape: Shape
    params: tuple[float, ...]


@dataclass(frozen=True)
class InputVariable:
    """A crisp input and its terms."""

    name: str
    terms: tuple[Term, ...]


@dataclass(frozen=True)
class OutputVariable:
    """An output, its terms, and the sampled universe ``linspace(low, high, resolution)``."""

    name: str
    terms: tuple[Term, ...]
    low: float = -1.0
    high: float = 1.0
    resolution: int = 201


@dataclass(frozen=True)
class Rule:
    """``if antecedent then output is term, ...`` with a weight in (0, 1] multiplying its strength.

    ``antecedent`` is a parsed :class:`~companion.config.rules.Antecedent` or its text.
    """

    name: str
    antecedent: Antecedent | str
    consequents: Mapping[str, str]
    weight: float = 1.0


@dataclass(frozen=True, slots=True)
class InferenceResult:
    """The outcome of one :meth:`FuzzySystem.infer`.

    Attributes:
        values: output name -> crisp value, or ``None`` where no rule fired for that output.
        fired: output name -> whether any of its rules had a strength > 0 (computed as: its aggregated
            set is not all zero, which is the same thing because every output term is checked at
            compile time to be non-zero somewhere on the universe).
        strengths: float64 ``(n_rules,)``, each rule's firing strength (after its weight), in
            :attr:`FuzzySystem.rule_names` order.
        memberships: float64 ``(n_atoms,)``, the degree of every (input, term) pair, indexed by
            :meth:`FuzzySystem.atom`.
        aggregated: float64 ``(n_outputs, N)``, each output's aggregated set on its universe.
    """

    values: dict[str, float | None]
    fired: dict[str, bool]
    strengths: np.ndarray
    memberships: np.ndarray
    aggregated: np.ndarray = field(repr=False)


class FuzzySystem:
    """A compiled Mamdani system.

    Args:
        inputs: the crisp inputs, in the order :meth:`infer` takes them.
        outputs: the outputs. All outputs must share one universe (low, high, resolution).
        rules: the rules; every clause must name an input and one of its terms, every consequent an
            output and one of its terms.
        and_method, or_method, implication, defuzzification: the operators (see the module doc).

    Raises:
        ConfigError: an unknown variable or term, bad parameters, an output term that is zero on the
            whole sampled universe (it could never fire visibly), or mismatched output universes.
    """

    def __init__(
        self,
        inputs: Sequence[InputVariable],
        outputs: Sequence[OutputVariable],
        rules: Sequence[Rule],
        *,
        and_method: AndMethod = "min",
        or_method: OrMethod = "max",
        implication: ImplicationMethod = "min",
        defuzzification: DefuzzMethod = "centroid",
    ) -> None:
        if and_method not in ("min", "product"):
            raise ConfigError(f"unknown and_method {and_method!r}")
        if or_method not in ("max", "probabilistic_sum"):
            raise ConfigError(f"unknown or_method {or_method!r}")
        if implication not in ("min", "product"):
            raise ConfigError(f"unknown implication {implication!r}")
        if defuzzification not in ("centroid", "mean_of_maximum", "bisector"):
            raise ConfigError(f"unknown defuzzification {defuzzification!r}")
        if not inputs or not outputs:
            raise ConfigError("a fuzzy system needs at least one input and one output")
        self.and_method: AndMethod = and_method
        self.or_method: OrMethod = or_method
        self.implication: ImplicationMethod = implication
        self.defuzzification: DefuzzMethod = defuzzification
        self.input_names: tuple[str, ...] = tuple(v.name for v in inputs)
        self.output_names: tuple[str, ...] = tuple(o.name for o in outputs)
        self.rule_names: tuple[str, ...] = tuple(r.name for r in rules)
        for label, names in (("input", self.input_names), ("output", self.output_names), ("rule", self.rule_names)):
            dup = {n for n in names if names.count(n) > 1}
            if dup:
                raise ConfigError(f"duplicate {label} name(s): {sorted(dup)}")
        self._compile_inputs(inputs)
        self._compile_outputs(outputs)
        self._compile_rules(rules)

    # ---------------------------------------------------------------------------------- compile

    def _compile_inputs(self, inputs: Sequence[InputVariable]) -> None:
        # Atoms = (input, term) pairs, piecewise-linear ones first, then gaussians, so that
        # fuzzification is one pass per family over parameter arrays.
        lin: list[tuple[int, str, tuple[float, float, float, float]]] = []
        gau: list[tuple[int, str, tuple[float, float]]] = []
        for vi, var in enumerate(inputs):
            if not var.terms:
                raise ConfigError(f"input {var.name!r} has no terms")
            names = [t.name for t in var.terms]
            if len(set(names)) != len(names):
                raise ConfigError(f"input {var.name!r} has duplicate term names: {names}")
            for t in var.terms:
                try:
                    _check_params(t.shape, t.params)
                except ValueError as err:
                    raise ConfigError(f"input {var.name!r} term {t.name!r}: {err}") from None
                if t.shape == "gaussian":
                    gau.append((vi, t.name, (float(t.params[0]), float(t.params[1]))))
                else:
                    lin.append((vi, t.name, _trapezoid_params(t.shape, t.params)))
        self._atom_index: dict[tuple[str, str], int] = {}
        order = [(vi, tn) for vi, tn, _ in lin] + [(vi, tn) for vi, tn, _ in gau]
        for k, (vi, tn) in enumerate(order):
            self._atom_index[(self.input_names[vi], tn)] = k
        self._n_atoms = len(order)
        self._n_lin = len(lin)
        lin_var = np.array([vi for vi, _, _ in lin], dtype=np.intp)
        p = np.array([q for _, _, q in lin], dtype=np.float64).reshape(-1, 4)
        a, b, c, d = p[:, 0], p[:, 1], p[:, 2], p[:, 3]
        # Both ramps in one pass over 2·M values: rows [left | right] = (x - [a | d]) / [b - a | c - d],
        # i.e. left (x - a)/(b - a) and right (d - x)/(d - c) (negating numerator and denominator is
        # exact). A shoulder's infinite side is a ramp that is +inf everywhere (x is finite there), a
        # vertical edge (a == b or c == d, finite) is a step that is 1 at the edge.
        self._lin_var2 = np.concatenate((lin_var, lin_var))
        self._lin_off = np.concatenate((a, d))
        with np.errstate(invalid="ignore"):
            left_den = np.where((b > a) & np.isfinite(b - a), b - a, 1.0)
            right_den = np.where((d > c) & np.isfinite(d - c), c - d, -1.0)
        self._lin_den = np.concatenate((left_den, right_den))
        self._lin_deg = np.concatenate(((a == b) & np.isfinite(a), (c == d) & np.isfinite(d)))
        self._lin_step_ge = np.concatenate((np.ones(len(a), bool), np.zeros(len(d), bool)))
        self._any_deg = bool(self._lin_deg.any())
        self._gau_var = np.array([vi for vi, _, _ in gau], dtype=np.intp)
        g = np.array([q for _, _, q in gau], dtype=np.float64).reshape(-1, 2)
        self._gau_mean = g[:, 0].copy()
        self._gau_inv2s2 = 1.0 / (2.0 * g[:, 1] ** 2)
        self._n_inputs = len(inputs)

    def _compile_outputs(self, outputs: Sequence[OutputVariable]) -> None:
        u0 = (outputs[0].low, outputs[0].high, outputs[0].resolution)
        for o in outputs:
            if (o.low, o.high, o.resolution) != u0:
                raise ConfigError(
                    f"outputs must share one universe: {o.name!r} has {(o.low, o.high, o.resolution)}, "
                    f"{outputs[0].name!r} has {u0}"
                )
            if not (math.isfinite(o.low) and math.isfinite(o.high) and o.high > o.low and o.resolution >= 2):
                raise ConfigError(f"output {o.name!r}: bad universe {(o.low, o.high, o.resolution)}")
        self.universe: np.ndarray = np.linspace(u0[0], u0[1], int(u0[2]))
        self.universe.setflags(write=False)
        self._term_curves: dict[tuple[str, str], np.ndarray] = {}
        for o in outputs:
            if not o.terms:
                raise ConfigError(f"output {o.name!r} has no terms")
            for t in o.terms:
                if (o.name, t.name) in self._term_curves:
                    raise ConfigError(f"output {o.name!r} has a duplicate term {t.name!r}")
                try:
                    curve = membership(t.shape, t.params, self.universe)
                except ValueError as err:
                    raise ConfigError(f"output {o.name!r} term {t.name!r}: {err}") from None
                if not curve.max() > 0.0:
                    raise ConfigError(
                        f"output {o.name!r} term {t.name!r} ({t.shape} {list(t.params)}) is zero on every "
                        f"sample of [{o.low}, {o.high}]: it could never show when its rules fire"
                    )
                curve.setflags(write=False)
                self._term_curves[(o.name, t.name)] = curve
        wm, wa = _centroid_weights(self.universe)
        self._w_centroid = np.stack([wm, wa], axis=1)  # (N, 2): agg @ this -> (moment, area)
        self._half_dx = 0.5 * np.diff(self.universe)

    def _compile_rules(self, rules: Sequence[Rule]) -> None:
        n_rules = len(rules)
        self._n_rules = n_rules
        parsed: list[Antecedent] = []
        for r in rules:
            try:
                ante = parse_antecedent(r.antecedent) if isinstance(r.antecedent, str) else r.antecedent
            except ValueError as err:
                raise ConfigError(f"rule {r.name!r}: {err}") from None
            for cl in ante.clauses:
                if (cl.variable, cl.term) not in self._atom_index:
                    if cl.variable not in self.input_names:
                        raise ConfigError(f"rule {r.name!r}: unknown input {cl.variable!r}")
                    raise ConfigError(f"rule {r.name!r}: input {cl.variable!r} has no term {cl.term!r}")
            if not r.consequents:
                raise ConfigError(f"rule {r.name!r} has no consequent")
            for out, term in r.consequents.items():
                if (out, term) not in self._term_curves:
                    if out not in self.output_names:
                        raise ConfigError(f"rule {r.name!r}: unknown output {out!r}")
                    raise ConfigError(f"rule {r.name!r}: output {out!r} has no term {term!r}")
            if not (0.0 < r.weight <= 1.0):
                raise ConfigError(f"rule {r.name!r}: weight must be in (0, 1], got {r.weight}")
            parsed.append(ante)
        m = self._n_atoms
        # ext = [mu (M), (1 - mu (M) only if some clause is negated), 1 (AND's neutral), 0 (OR's
        # neutral)]; the clause index matrix is padded with the neutral element of its rule's connective.
        self._any_not = any(cl.negated for ante in parsed for cl in ante.clauses)
        base = 2 * m if self._any_not else m
        pad_one, pad_zero = base, base + 1
        k = max((len(a.clauses) for a in parsed), default=1)
        idx = np.full((n_rules, k), pad_one, dtype=np.intp)
        is_or = np.zeros(n_rules, dtype=bool)
        for ri, ante in enumerate(parsed):
            is_or[ri] = ante.connective == "or" and len(ante.clauses) > 1
            idx[ri, :] = pad_zero if is_or[ri] else pad_one
            for ci, cl in enumerate(ante.clauses):
                at = self._atom_index[(cl.variable, cl.term)]
                idx[ri, ci] = at + m if cl.negated else at
        self._clause_idx = idx
        self._is_or = is_or
        self._any_or = bool(is_or.any())
        self._all_or = bool(is_or.all()) and n_rules > 0
        self._pads = np.array([1.0, 0.0])
        self._weights = np.array([r.weight for r in rules], dtype=np.float64)
        self._weighted = bool((self._weights != 1.0).any())
        self.parsed_antecedents: tuple[Antecedent, ...] = tuple(parsed)
        self.rule_consequents: tuple[dict[str, str], ...] = tuple(dict(r.consequents) for r in rules)

        # (rule, output) pairs laid out as (n_outputs, P, N): output o's rules, padded to P rows with
        # all-zero curves (zero under both implications), so that aggregation is one max over axis 1.
        self._output_rules: dict[str, tuple[int, ...]] = {
            out: tuple(ri for ri, r in enumerate(rules) if out in r.consequents) for out in self.output_names
        }
        n_pairs = max((len(v) for v in self._output_rules.values()), default=0)
        n_pairs = max(n_pairs, 1)
        n_samples = len(self.universe)
        self._pair_rule = np.zeros((len(self.output_names), n_pairs), dtype=np.intp)
        self._curves = np.zeros((len(self.output_names), n_pairs, n_samples))
        for o, out in enumerate(self.output_names):
            for j, ri in enumerate(self._output_rules[out]):
                self._pair_rule[o, j] = ri
                self._curves[o, j] = self._term_curves[(out, rules[ri].consequents[out])]

    # ---------------------------------------------------------------------------------- queries

    @property
    def n_inputs(self) -> int:
        return self._n_inputs

    def atom(self, variable: str, term: str) -> int:
        """Index of (input, term) in :attr:`InferenceResult.memberships`."""
        try:
            return self._atom_index[(variable, term)]
        except KeyError:
            raise KeyError(f"input {variable!r} has no term {term!r}") from None

    def output_rules(self, output: str) -> tuple[int, ...]:
        """Indices of the rules that name ``output`` in their consequent."""
        return self._output_rules[output]

    def term_curve(self, output: str, term: str) -> np.ndarray:
        """The sampled curve of an output term, float64 ``(N,)`` on :attr:`universe` (read-only)."""
        return self._term_curves[(output, term)]

    # ---------------------------------------------------------------------------------- inference

    def fuzzify(self, x: np.ndarray) -> np.ndarray:
        """Degrees of every (input, term) pair, float64 ``(n_atoms,)`` (see :meth:`atom`).

        Args:
            x: float64 ``(n_inputs,)`` crisp inputs, in :attr:`input_names` order; +-inf allowed.

        Raises:
            ValueError: wrong shape, or a NaN input (the caller decides what unknown means).
        """
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (self._n_inputs,):
            raise ValueError(f"expected {self._n_inputs} inputs {self.input_names}, got shape {x.shape}")
        if not np.logical_and.reduce(np.isfinite(x)):  # rare: find NaN, clamp +-inf (inf - inf = NaN)
            bad = [n for n, v in zip(self.input_names, x.tolist()) if math.isnan(v)]
            if bad:
                raise ValueError(f"NaN input(s) {bad}: replace unknown inputs before inference")
            x = np.minimum(np.maximum(x, -_BIG), _BIG)
        n = self._n_lin
        xl = x[self._lin_var2]
        r = (xl - self._lin_off) / self._lin_den  # (2M,): left ramps then right ramps
        if self._any_deg:
            step = np.where(self._lin_step_ge, xl >= self._lin_off, xl <= self._lin_off)
            r = np.where(self._lin_deg, step, r)
        mu = np.minimum(r[:n], r[n:])
        np.minimum(mu, 1.0, out=mu)
        np.maximum(mu, 0.0, out=mu)
        if len(self._gau_var):
            dg = x[self._gau_var] - self._gau_mean
            with np.errstate(over="ignore"):  # far from the mean: exp(-inf) = 0 is the right answer
                mu = np.concatenate((mu, np.exp(-(dg * dg) * self._gau_inv2s2)))
        return mu

    def rule_strengths(self, mu: np.ndarray) -> np.ndarray:
        """Firing strength of every rule (after weights), float64 ``(n_rules,)``, from :meth:`fuzzify`."""
        if self._n_rules == 0:
            return np.zeros(0)
        ext = np.concatenate((mu, 1.0 - mu, self._pads) if self._any_not else (mu, self._pads))
        v = ext[self._clause_idx]  # (R, K)
        if self._all_or:
            s = self._reduce_or(v)
        else:
            s = np.minimum.reduce(v, axis=1) if self.and_method == "min" else np.multiply.reduce(v, axis=1)
            if self._any_or:
                s = np.where(self._is_or, self._reduce_or(v), s)
        if self._weighted:
            s = s * self._weights
        return s

    def _reduce_or(self, v: np.ndarray) -> np.ndarray:
        if self.or_method == "max":
            return np.maximum.reduce(v, axis=1)
        # a ⊕ b ⊕ c ... = 1 - (1-a)(1-b)(1-c)...: the probabilistic sum folded over the clauses.
        return 1.0 - np.multiply.reduce(1.0 - v, axis=1)

    def infer(self, x: np.ndarray) -> InferenceResult:
        """One Mamdani inference.

        Args:
            x: float64 ``(n_inputs,)`` crisp inputs in :attr:`input_names` order (no NaN).

        Returns:
            :class:`InferenceResult`; an output whose rules all have strength 0 has value ``None`` and
            ``fired`` False.
        """
        mu = self.fuzzify(x)
        s = self.rule_strengths(mu)
        n_out = len(self.output_names)
        if self._n_rules == 0:
            agg = np.zeros((n_out, len(self.universe)))
        else:
            act = s[self._pair_rule][:, :, None]  # (O, P, 1)
            shaped = np.minimum(self._curves, act) if self.implication == "min" else self._curves * act
            agg = np.maximum.reduce(shaped, axis=1)  # (O, N)
        values: dict[str, float | None] = {}
        fired: dict[str, bool] = {}
        method = self.defuzzification
        if method == "centroid":
            ma = (agg @ self._w_centroid).tolist()  # [[moment, area], ...]
            for name, (mom, area) in zip(self.output_names, ma):
                ok = area > 0.0
                fired[name] = ok
                values[name] = mom / area if ok else None
        elif method == "mean_of_maximum":
            top = np.maximum.reduce(agg, axis=1)
            mask = agg == top[:, None]
            means = ((mask @ self.universe) / mask.sum(axis=1)).tolist()
            for name, t, mv in zip(self.output_names, top.tolist(), means):
                ok = t > 0.0
                fired[name] = ok
                values[name] = mv if ok else None
        else:
            seg = (agg[:, :-1] + agg[:, 1:]) * self._half_dx
            cum = np.cumsum(seg, axis=1)
            totals = cum[:, -1].tolist()
            for o, (name, total) in enumerate(zip(self.output_names, totals)):
                ok = total > 0.0
                fired[name] = ok
                values[name] = _bisector_from_cum(self.universe, agg[o], cum[o], total) if ok else None
        return InferenceResult(values=values, fired=fired, strengths=s, memberships=mu, aggregated=agg)
