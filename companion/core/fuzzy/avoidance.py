"""The paper's avoidance controller (section VIII): two Mamdani systems over the nine region depths.

:class:`AvoidanceController` compiles, from a :class:`~companion.config.core.ControllerConfig`, a
*main* system (``main_rules``: the centre and the four sides) and a *corner* system (``corner_rules``:
the same idea rotated by 45°). Both take the nine region depths in ``REGION_NAMES`` order, every region
sharing ``cfg.input_terms``, and give ``yaw`` and ``pitch`` in [-1, 1] on a universe of
``cfg.output_resolution`` samples. Placeholders (``{yaw_side}``, ``{pitch_side}``, ``{corner_side}``)
are substituted with ``cfg.substitute`` once, at construction.

Decision logic of :meth:`AvoidanceController.decide` (``near`` is the centre's degree in the input
term ``near``; a rule is *neutral* when all its consequents are ``yaw_neutral_term`` /
``pitch_neutral_term``; a system's *escape strength* is the largest strength of its non-neutral rules):

a. A NaN (unknown) region depth becomes ``cfg.unknown_depth_m`` (near: unknown is never free space);
   depths are clipped to >= 0.
b. Run the main system.
c. Main escape strength >= ``min_escape_strength`` and the defuzzified yaw or pitch at least
   ``min_escape_command`` in magnitude (opposing escapes that cancel, as in front of a flat wall, are
   no escape): use the main outputs. Kind AVOID when near > 0, else CLEAR (only possible with custom rules whose escapes do not require the centre near).
d. Else run the corner system; corner escape strength >= ``min_escape_strength`` (same command
   test): AVOID with the corner outputs ("corner controller" in the reason).
e. Else, if no rule of either system fired for either output: BRAKE ("no rule fired").
f. Else, if near >= ``brake_near_degree``: BRAKE (centre blocked, no escape).
g. Else straight on with the engine's outputs (the main system's, or the corner's if only it fired):
   CLEAR when near == 0 (centre far), otherwise AVOID ("centre partly near, no escape, below the brake
   degree": the speed blend below slows the vehicle). Labelling the partly-near case AVOID rather than
   CLEAR keeps "CLEAR" equivalent to "centre far", so that making any region nearer can never turn a
   non-CLEAR decision into CLEAR.
h. When one output fired and the other did not (e.g. a pure vertical escape), the controller sets the
   unfired one to 0 on purpose: the engine itself reports it as not fired (``None``), never as 0.
i. ``speed_fraction = 1 + (cfg.avoid_speed_fraction - 1)·slow`` for CLEAR and AVOID, 0 for BRAKE, where
   ``slow`` is the largest "near" degree of the centre and the regions in ``cfg.avoid_speed_regions``;
   yaw and pitch are clipped to [-1, 1]; BRAKE gives yaw = pitch = 0.

The local planner (:mod:`companion.core.planner`) takes the :class:`~companion.core.types.Decision` as
one term of its cost (``planner.weight_fuzzy``) and as a brake its safety chain obeys.
"""

from __future__ import annotations

import numpy as np

from companion.core.fuzzy.engine import (
    FuzzySystem,
    InferenceResult,
    InputVariable,
    OutputVariable,
    Rule,
    Term,
)
from companion.config.core import ControllerConfig, RuleConfig
from companion.core.types import N_REGIONS, REGION_NAMES, Decision, DecisionKind
from companion.errors import ConfigError


OUTPUTS: tuple[str, str] = ("yaw", "pitch")


def build_system(cfg: ControllerConfig, rules: list[RuleConfig]) -> FuzzySystem:
    """Compile one rule base of ``cfg`` into a :class:`FuzzySystem` (inputs: the nine regions in
    ``REGION_NAMES`` order, metres; outputs: ``yaw`` and ``pitch`` on [-1, 1])."""
    in_terms = tuple(Term(name, t.shape, tuple(t.params_m)) for name, t in cfg.input_terms.items())
    inputs = [InputVariable(name, in_terms) for name in REGION_NAMES]
    outputs = [
        OutputVariable(
            out,
            tuple(Term(name, t.shape, tuple(t.params)) for name, t in terms.items()),
            low=-1.0,
            high=1.0,
            resolution=cfg.output_resolution,
        )
        for out, terms in (("yaw", cfg.yaw_terms), ("pitch", cfg.pitch_terms))
    ]
    compiled = [
        Rule(
            name=r.name,
            antecedent=cfg.substitute(r.when),
            consequents={out: cfg.substitute(term) for out, term in r.then.items()},
            weight=r.weight,
        )
        for r in rules
    ]
    return FuzzySystem(
        inputs,
        outputs,
        compiled,
        and_method=cfg.and_method,
        or_method=cfg.or_method,
        implication=cfg.implication,
        defuzzification=cfg.defuzzification,
    )


class _Compiled:
    """A system plus what the decision logic needs about its rules, precomputed."""

    __slots__ = ("system", "names", "keys", "escape_idx", "has_rules")

    def __init__(self, system: FuzzySystem, neutral: dict[str, str], key_prefix: str, taken: set[str]) -> None:
        self.system = system
        self.names = system.rule_names
        # Keys in Decision.rule_strengths: the rule name, prefixed where it clashes with the other base.
        self.keys = tuple(f"{key_prefix}{n}" if n in taken else n for n in self.names)
        self.escape_idx = tuple(
            i
            for i, then in enumerate(system.rule_consequents)
            if any(term != neutral[out] for out, term in then.items())
        )
        self.has_rules = len(self.names) > 0


def _escape(strengths: list[float], escape_idx: tuple[int, ...]) -> tuple[float, int]:
    """(largest strength among the non-neutral rules, its index; -1 if none)."""
    best, best_i = 0.0, -1
    for i in escape_idx:
        if strengths[i] > best:
            best, best_i = strengths[i], i
    return best, best_i


def _clip1(v: float | None) -> float:
    # An unfired output is 0 by the controller's choice (see module doc, h).
    if v is None:
        return 0.0
    return min(1.0, max(-1.0, v))


class AvoidanceController:
    """The main + corner fuzzy controller of one configuration (build a new one for a new config).

    Args:
        cfg: the fuzzy controller's configuration.

    Raises:
        ConfigError: a rule base that cannot be compiled (e.g. an output term zero on every sample).
    """

    def __init__(self, cfg: ControllerConfig) -> None:
        self.cfg = cfg
        neutral = {"yaw": cfg.yaw_neutral_term, "pitch": cfg.pitch_neutral_term}
        try:
            self.main_system = build_system(cfg, cfg.main_rules)
            self.corner_system = build_system(cfg, cfg.corner_rules)
        except ConfigError as err:
            raise ConfigError(f"controller: {err}") from None
        self._main = _Compiled(self.main_system, neutral, "", set())
        self._corner = _Compiled(self.corner_system, neutral, "corner:", set(self._main.names))
        self._near_c = self.main_system.atom("center", "near")
        self._speed_atoms = [self.main_system.atom(region, "near") for region in cfg.avoid_speed_regions]
        self._unknown = float(cfg.unknown_depth_m)
        self._min_escape = float(cfg.min_escape_strength)
        self._min_command = float(cfg.min_escape_command)
        self._brake_near = float(cfg.brake_near_degree)
        self._avoid_speed = float(cfg.avoid_speed_fraction)

    def prepare(self, depth_m: np.ndarray) -> np.ndarray:
        """Depths as fed to the systems: float64 ``(9,)``, NaN -> ``unknown_depth_m``, clipped to >= 0."""
        d = np.asarray(depth_m, dtype=np.float64)
        if d.shape != (N_REGIONS,):
            raise ValueError(f"expected {N_REGIONS} region depths {REGION_NAMES}, got shape {d.shape}")
        if self._unknown == 0.0:
            return np.fmax(d, 0.0)  # fmax picks 0.0 over NaN: unknown -> 0 m and clip in one call
        return np.maximum(np.where(np.isnan(d), self._unknown, d), 0.0)

    def decide(self, depth_m: np.ndarray) -> Decision:
        """Decide for one frame.

        Args:
            depth_m: float64 ``(9,)`` region depths in metres, ``REGION_NAMES`` order, NaN = unknown.

        Returns:
            The :class:`~companion.core.types.Decision` (see the module doc for the logic).
        """
        d = self.prepare(depth_m)
        main = self.main_system.infer(d)
        near = float(main.memberships[self._near_c])
        # The speed blend follows the nearest of the centre and cfg.avoid_speed_regions (none by
        # default; the sides slow the vehicle while a box passes beside it).
        slow = max([near, *(float(main.memberships[a]) for a in self._speed_atoms)])
        s_main = main.strengths.tolist()
        strengths = {k: v for k, v in zip(self._main.keys, s_main) if v > 0.0}
        esc, esc_i = _escape(s_main, self._main.escape_idx)
        if esc >= self._min_escape and self._commands(main):
            if near > 0.0:
                return self._steer(
                    DecisionKind.AVOID, main, slow, f"main controller: escape by {self._main.names[esc_i]} "
                    f"({esc:.2f}), centre near {near:.2f}", strengths
                )
            return self._steer(DecisionKind.CLEAR, main, slow, "centre clear", strengths)

        corner: InferenceResult | None = None
        if self._corner.has_rules:
            corner = self.corner_system.infer(d)
            s_corner = corner.strengths.tolist()
            strengths.update((k, v) for k, v in zip(self._corner.keys, s_corner) if v > 0.0)
            c_esc, c_i = _escape(s_corner, self._corner.escape_idx)
            if c_esc >= self._min_escape and self._commands(corner):
                return self._steer(
                    DecisionKind.AVOID, corner, slow, f"corner controller: escape by {self._corner.names[c_i]} "
                    f"({c_esc:.2f}); main controller found none (best {esc:.2f})", strengths
                )

        main_fired = any(main.fired.values())
        corner_fired = corner is not None and any(corner.fired.values())
        if not main_fired and not corner_fired:
            return Decision(DecisionKind.BRAKE, 0.0, 0.0, 0.0, "no rule fired", strengths)
        if near >= self._brake_near:
            return Decision(
                DecisionKind.BRAKE, 0.0, 0.0, 0.0,
                f"centre blocked (near {near:.2f} >= {self._brake_near:.2f}), no escape from the main or "
                "corner controller", strengths,
            )
        source = main if main_fired or corner is None else corner
        if near == 0.0:
            return self._steer(DecisionKind.CLEAR, source, slow, "centre clear", strengths)
        return self._steer(
            DecisionKind.AVOID, source, slow,
            f"centre partly near ({near:.2f} < brake {self._brake_near:.2f}), no escape: straight on, slowing",
            strengths,
        )

    def _commands(self, res: InferenceResult) -> bool:
        """True when the outputs really steer: opposing escapes of equal strength (a flat wall filling
        the view) defuzzify to ~0, and flying on "straight" then would fly into the wall."""
        return max(abs(_clip1(res.values["yaw"])), abs(_clip1(res.values["pitch"]))) >= self._min_command

    def _steer(
        self, kind: DecisionKind, res: InferenceResult, slow: float, reason: str, strengths: dict[str, float]
    ) -> Decision:
        speed = 1.0 + (self._avoid_speed - 1.0) * slow
        return Decision(
            kind=kind,
            yaw=_clip1(res.values["yaw"]),
            pitch=_clip1(res.values["pitch"]),
            speed_fraction=min(1.0, max(0.0, speed)),
            reason=reason,
            rule_strengths=strengths,
        )
