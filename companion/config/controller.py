"""Config of the Mamdani fuzzy controller: membership functions and rules (``[controller]``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from companion.config._base import StrictModel
from companion.config.rules import parse_antecedent
from companion.config.regions import REGION_NAMES, RegionName

MembershipShape = Literal["triangle", "trapezoid", "left_shoulder", "right_shoulder", "gaussian"]
_SHAPE_ARITY = {"triangle": 3, "trapezoid": 4, "left_shoulder": 2, "right_shoulder": 2, "gaussian": 2}


def _check_shape_params(shape: str, params: tuple[float, ...]) -> None:
    n = _SHAPE_ARITY[shape]
    if len(params) != n:
        raise ValueError(f"{shape} takes {n} parameters, got {len(params)}: {list(params)}")
    if shape == "gaussian":
        if params[1] <= 0:
            raise ValueError(f"gaussian sigma must be > 0, got {params[1]}")
        return
    if any(b < a for a, b in zip(params, params[1:])):
        raise ValueError(f"{shape} parameters must be non-decreasing, got {list(params)}")
    if shape in ("left_shoulder", "right_shoulder") and params[1] <= params[0]:
        raise ValueError(f"{shape} needs a < b, got {list(params)}")


class InputTerm(StrictModel):
    """A membership function over a region depth (metres).

    Shapes: triangle (a, b, c): 0 at a, 1 at b, 0 at c. trapezoid (a, b, c, d). left_shoulder (a, b):
    1 up to a, falling linearly to 0 at b. right_shoulder (a, b): 0 up to a, rising to 1 at b.
    gaussian (mean, sigma).
    """

    shape: MembershipShape = Field(description="Membership function shape.")
    params_m: tuple[float, ...] = Field(description="Shape parameters in metres (see the shape).")

    @model_validator(mode="after")
    def _check(self) -> InputTerm:
        _check_shape_params(self.shape, self.params_m)
        return self


class OutputTerm(StrictModel):
    """A membership function over a normalised output in [-1, 1] (same shapes as :class:`InputTerm`)."""

    shape: MembershipShape = Field(description="Membership function shape.")
    params: tuple[float, ...] = Field(description="Shape parameters, dimensionless, on [-1, 1].")

    @model_validator(mode="after")
    def _check(self) -> OutputTerm:
        _check_shape_params(self.shape, self.params)
        return self


class RuleConfig(StrictModel):
    """One Mamdani rule: ``when`` (a condition over region terms) ``then`` (output terms).

    ``when`` may use the placeholders ``{yaw_side}`` (the preferred horizontal side, a region and yaw
    term: left/right), ``{pitch_side}`` (up/down) and ``{corner_side}`` (the preferred corner, e.g.
    up_right); ``then`` values may use ``{yaw_side}`` and ``{pitch_side}``.
    """

    name: str = Field(min_length=1, max_length=64, description="Short unique name, shown in logs and health.")
    when: str = Field(min_length=1, max_length=500, description="Condition, e.g. 'center is near and up is far'.")
    then: dict[Literal["yaw", "pitch"], str] = Field(
        min_length=1, description="Output -> term, e.g. {yaw = 'left'}."
    )
    weight: float = Field(default=1.0, gt=0.0, le=1.0, description="Rule weight multiplying its strength.")
    doc: str = Field(default="", max_length=1000, description="Why the rule exists (free text).")

    @field_validator("when")
    @classmethod
    def _parse(cls, v: str) -> str:
        parse_antecedent(_substitute_placeholders(v, "right", "up"))
        return v


def _substitute_placeholders(text: str, yaw_side: str, pitch_side: str) -> str:
    return (
        text.replace("{yaw_side}", yaw_side)
        .replace("{pitch_side}", pitch_side)
        .replace("{corner_side}", f"{pitch_side}_{yaw_side}")
    )


def _t(shape: str, *p: float) -> dict:
    return {"shape": shape, "params": p}


def _i(shape: str, *p: float) -> dict:
    return {"shape": shape, "params_m": p}


def _default_input_terms() -> dict[str, InputTerm]:
    # Paper: below 0.75 m is near, above 2.25 m is far, linear between (a 1/3 scale on its 0–3 axis).
    return {
        "near": InputTerm(**_i("left_shoulder", 0.75, 2.25)),
        "far": InputTerm(**_i("right_shoulder", 0.75, 2.25)),
    }


def _default_yaw_terms() -> dict[str, OutputTerm]:
    return {
        "left": OutputTerm(**_t("trapezoid", -1.0, -1.0, -0.6, 0.0)),
        "straight": OutputTerm(**_t("triangle", -0.4, 0.0, 0.4)),
        "right": OutputTerm(**_t("trapezoid", 0.0, 0.6, 1.0, 1.0)),
    }


def _default_pitch_terms() -> dict[str, OutputTerm]:
    return {
        "down": OutputTerm(**_t("trapezoid", -1.0, -1.0, -0.6, 0.0)),
        "level": OutputTerm(**_t("triangle", -0.4, 0.0, 0.4)),
        "up": OutputTerm(**_t("trapezoid", 0.0, 0.6, 1.0, 1.0)),
    }


def _r(name: str, when: str, doc: str, weight: float = 1.0, **then: str) -> RuleConfig:
    return RuleConfig(name=name, when=when, then=then, doc=doc, weight=weight)


def _default_main_rules() -> list[RuleConfig]:
    return [
        _r("R1", "center is far", "Paper rule 1: centre clear, fly straight.", yaw="straight", pitch="level"),
        _r("R2", "center is near and up is near and down is far",
           "Paper rule 2: blocked ahead and above, free below: go down.", pitch="down"),
        _r("R3", "center is near and down is near and up is far",
           "Paper rule 3: blocked ahead and below, free above: go up.", pitch="up"),
        _r("R4", "center is near and right is near and left is far",
           "Paper rule 4: blocked ahead and right, free left: turn left.", yaw="left"),
        _r("R5", "center is near and left is near and right is far",
           "Paper rule 5: blocked ahead and left, free right: turn right.", yaw="right"),
        _r("R6", "center is near and {yaw_side} is far",
           "Paper rule 6 (preferred side): blocked ahead and the preferred side is free: turn to it. "
           "The paper prints 'right is near -> right', which would steer into the obstacle and cancel "
           "rule 4; read as the preference that breaks left/right ties (paper Fig. 9c).",
           yaw="{yaw_side}"),
        _r("R7", "center is near and {pitch_side} is far",
           "Paper rule 7 (preferred vertical): blocked ahead and the preferred vertical side is free: "
           "go that way (same reading as rule 6). Weight 0.5 (not in the paper): a preference breaks "
           "ties and must not cancel the rule that names the free side. An overhead block reads in "
           "the up region as near as the centre, 'near' and 'far' 0.5 each at 1.5 m, so at weight 1 "
           "this rule would fire as strongly as R2 and the two cancel: no descent under the block, a "
           "brake instead. At 0.5 it descends from 2 m, a low wall still climbs, and with both sides "
           "free up still wins at 2/3 of the command.",
           weight=0.5, pitch="{pitch_side}"),
        _r("TIE", "center is near and up is near and down is near and left is far and right is far",
           "Tie rule (paper Fig. 9c): ahead, above and below blocked, both sides free: take the "
           "preferred side so the centroid never collapses to straight.",
           yaw="{yaw_side}"),
        # Not in the paper. The centre region is a cone (0.5 m at 1.5 m) narrower than the vehicle
        # closer in, so an obstacle within reach can sit in a side region while the centre reads far
        # (the paper's Fig. 11 failure): the side rules keep steering away from a near side until it
        # is passed.
        _r("S1", "center is far and left is near and right is far",
           "Side rule (not in the paper): centre clear but something near on the left: veer right.",
           yaw="right"),
        _r("S2", "center is far and right is near and left is far",
           "Side rule (not in the paper): centre clear but something near on the right: veer left.",
           yaw="left"),
        _r("S3", "center is far and up is near and down is far",
           "Side rule (not in the paper): centre clear but something near above: sink.",
           pitch="down"),
        _r("S4", "center is far and down is near and up is far",
           "Side rule (not in the paper): centre clear but something near below: climb.",
           pitch="up"),
    ]


def _default_corner_rules() -> list[RuleConfig]:
    # The main controller rotated by 45°: up -> up_right, right -> down_right, down -> down_left,
    # left -> up_left. Consulted only when the main controller finds no escape.
    return [
        _r("C1", "center is far", "Rotated rule 1: centre clear, fly straight.", yaw="straight", pitch="level"),
        _r("C2", "center is near and up_right is near and down_left is far",
           "Rotated rule 2: blocked up-right, free down-left: go down-left.", yaw="left", pitch="down"),
        _r("C3", "center is near and down_left is near and up_right is far",
           "Rotated rule 3: blocked down-left, free up-right: go up-right.", yaw="right", pitch="up"),
        _r("C4", "center is near and down_right is near and up_left is far",
           "Rotated rule 4: blocked down-right, free up-left: go up-left.", yaw="left", pitch="up"),
        _r("C5", "center is near and up_left is near and down_right is far",
           "Rotated rule 5: blocked up-left, free down-right: go down-right.", yaw="right", pitch="down"),
        _r("C6", "center is near and {corner_side} is far",
           "Rotated preference: blocked ahead and the preferred corner is free: go to it.",
           yaw="{yaw_side}", pitch="{pitch_side}"),
    ]


class ControllerConfig(StrictModel):
    """The Mamdani fuzzy controller: membership functions, operators and the rule bases."""

    and_method: Literal["min", "product"] = Field(default="min", description="Fuzzy AND (t-norm).")
    or_method: Literal["max", "probabilistic_sum"] = Field(default="max", description="Fuzzy OR (s-norm).")
    implication: Literal["min", "product"] = Field(
        default="min", description="How a rule's strength shapes its output set: clip (min) or scale (product)."
    )
    defuzzification: Literal["centroid", "mean_of_maximum", "bisector"] = Field(
        default="centroid", description="Defuzzification of the aggregated (max) output set."
    )
    output_resolution: int = Field(
        default=201, ge=21, le=10001, description="Samples of the output universe [-1, 1]."
    )
    input_terms: dict[str, InputTerm] = Field(
        default_factory=_default_input_terms,
        min_length=1,
        description="Terms over every region depth (metres). Paper: near below 0.75 m, far above 2.25 m.",
    )
    yaw_terms: dict[str, OutputTerm] = Field(
        default_factory=_default_yaw_terms, min_length=1, description="Terms of the yaw output (-1 left, +1 right)."
    )
    pitch_terms: dict[str, OutputTerm] = Field(
        default_factory=_default_pitch_terms, min_length=1, description="Terms of the pitch output (-1 down, +1 up)."
    )
    yaw_neutral_term: str = Field(default="straight", description="The yaw term that means 'no avoidance'.")
    pitch_neutral_term: str = Field(default="level", description="The pitch term that means 'no avoidance'.")
    preferred_yaw_side: Literal["left", "right"] = Field(
        default="right", description="Side taken when both are equally free ({yaw_side} in rules). Paper: right."
    )
    preferred_pitch_side: Literal["up", "down"] = Field(
        default="up", description="Vertical side taken when both are equally free ({pitch_side} in rules)."
    )
    main_rules: list[RuleConfig] = Field(
        default_factory=_default_main_rules, min_length=1, description="The main controller (centre + 4 sides)."
    )
    corner_rules: list[RuleConfig] = Field(
        default_factory=_default_corner_rules,
        description="The 45°-rotated controller over the corners, consulted when the main one finds no escape.",
    )
    unknown_depth_m: float = Field(
        default=0.0,
        ge=0.0,
        le=0.75,
        description="Depth fed to the controller for an unknown region, metres: unknown is treated as near.",
    )
    min_escape_strength: float = Field(
        default=0.2,
        gt=0.0,
        le=1.0,
        description=(
            "Strongest non-neutral rule below this means that controller found no escape (then the "
            "corner controller, then brake). Simulator-tuned: 0.05 crept toward flat faces on escapes "
            "of strength 0.07."
        ),
    )
    min_escape_command: float = Field(
        default=0.05,
        ge=0.0,
        le=1.0,
        description=(
            "An escape whose defuzzified |yaw| and |pitch| are both below this is no escape: opposing "
            "rules of equal strength (a flat wall filling the view) cancel to 'straight'."
        ),
    )
    brake_near_degree: float = Field(
        default=0.5,
        gt=0.0,
        le=1.0,
        description=(
            "With no escape from either controller, brake once the centre is at least this near "
            "(membership of the first input term, 'near')."
        ),
    )

    avoid_speed_fraction: float = Field(
        default=0.1,
        ge=0.0,
        le=1.0,
        description=(
            "The decision's speed share (its speed_fraction: health, the preview, companion process) "
            "while the centre is fully near, as a share of the cruise speed, blended linearly with the "
            "centre's near degree; 1 = the paper's constant speed. The local planner sets the flown "
            "speed itself, from the space seen free ([planner]); this is the fuzzy controller's own "
            "reading of how fast the way ahead allows."
        ),
    )
    avoid_speed_regions: list[RegionName] = Field(
        default=[],
        max_length=9,
        description=(
            "Regions whose 'near' degree also lowers the decision's speed (the largest of them and the "
            "centre's drives the avoid_speed_fraction blend); [] = the centre only (the default)."
        ),
    )

    def substitute(self, text: str) -> str:
        """Replace ``{yaw_side}``, ``{pitch_side}`` and ``{corner_side}`` in a rule's text."""
        return _substitute_placeholders(text, self.preferred_yaw_side, self.preferred_pitch_side)

    @model_validator(mode="after")
    def _check_rules(self) -> ControllerConfig:
        regions = set(REGION_NAMES)
        out_terms = {"yaw": self.yaw_terms, "pitch": self.pitch_terms}
        if self.yaw_neutral_term not in self.yaw_terms:
            raise ValueError(f"yaw_neutral_term {self.yaw_neutral_term!r} is not one of {sorted(self.yaw_terms)}")
        if self.pitch_neutral_term not in self.pitch_terms:
            raise ValueError(
                f"pitch_neutral_term {self.pitch_neutral_term!r} is not one of {sorted(self.pitch_terms)}"
            )
        if "near" not in self.input_terms:
            raise ValueError("input_terms must define 'near' (used for braking and speed)")
        for label, rules in (("main_rules", self.main_rules), ("corner_rules", self.corner_rules)):
            seen: set[str] = set()
            for k, rule in enumerate(rules):
                where = f"{label}.{k} ({rule.name!r})"
                if rule.name in seen:
                    raise ValueError(f"{where}: duplicate rule name")
                seen.add(rule.name)
                ante = parse_antecedent(self.substitute(rule.when))
                for c in ante.clauses:
                    if c.variable not in regions:
                        raise ValueError(
                            f"{where}: unknown region {c.variable!r}; regions are {', '.join(REGION_NAMES)}"
                        )
                    if c.term not in self.input_terms:
                        raise ValueError(f"{where}: unknown term {c.term!r}; terms are {sorted(self.input_terms)}")
                for out, term in rule.then.items():
                    term = self.substitute(term)
                    if term not in out_terms[out]:
                        raise ValueError(f"{where}: {out} has no term {term!r}; terms are {sorted(out_terms[out])}")
        return self
