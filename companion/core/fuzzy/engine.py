"""A small, generic Mamdani fuzzy inference engine in NumPy, compiled once and then vectorised.

:class:`FuzzySystem`: inputs, outputs (sampled universes), weighted rules. The constructor compiles
the system into parameter arrays and index matrices, so that :meth:`FuzzySystem.infer` is a fixed,
short sequence of vectorised NumPy calls (tens of microseconds for the avoidance controller). The
membership functions, operators and defuzzifiers it compiles are those of
:mod:`companion.core.fuzzy.sets`.

Inference (Mamdani): fuzzify every (input, term) pair; a rule's strength is the AND (or OR) of its
clauses, a ``not`` clause using 1 - mu, times the rule's weight; each rule shapes its consequent terms
by implication; the shaped sets of one output are aggregated with max and defuzzified. An output whose
rules all have strength 0 did not fire: its value is ``None`` and its ``fired`` flag False.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from companion.config.rules import Antecedent, parse_antecedent
from companion.core.fuzzy.sets import (
    BIG,
    AndMethod,
    DefuzzMethod,
    ImplicationMethod,
    OrMethod,
    Shape,
    bisector_from_cum,
    centroid_weights,
    check_params,
    membership,
    trapezoid_params,
)
from companion.errors import ConfigError


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
                    check_params(t.shape, t.params)
                except ValueError as err:
                    raise ConfigError(f"input {var.name!r} term {t.name!r}: {err}") from None
                if t.shape == "gaussian":
                    gau.append((vi, t.name, (float(t.params[0]), float(t.params[1]))))
                else:
                    lin.append((vi, t.name, trapezoid_params(t.shape, t.params)))
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
        wm, wa = centroid_weights(self.universe)
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
            x = np.minimum(np.maximum(x, -BIG), BIG)
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
                values[name] = bisector_from_cum(self.universe, agg[o], cum[o], total) if ok else None
        return InferenceResult(values=values, fired=fired, strengths=s, memberships=mu, aggregated=agg)
