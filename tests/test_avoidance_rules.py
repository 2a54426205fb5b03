"""The avoidance controller does what the paper's rules say, treats unknown as near, and maps decisions
to setpoints with the right signs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import parse_config
from companion.config.core import ControllerConfig, InputTerm
from companion.core.direct import decision_setpoint
from companion.core.fuzzy import AvoidanceController
from companion.core.types import REGION_INDEX, REGION_NAMES, ZERO_SETPOINT, Decision, DecisionKind

NEAR, FAR = 0.3, 5.0  # metres: fully near (< 0.75) and fully far (> 2.25) with the paper's terms
CFG = parse_config({})
CTL = ControllerConfig()


def depths(default: float = FAR, **regions: float) -> np.ndarray:
    d = np.full(len(REGION_NAMES), default)
    for name, v in regions.items():
        d[REGION_INDEX[name]] = v
    return d


def controller(**cfg: object) -> AvoidanceController:
    return AvoidanceController(ControllerConfig(**cfg))  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def ctl() -> AvoidanceController:
    return controller()


# --------------------------------------------------------------------------------------------------
# The paper's rules


@pytest.mark.parametrize(
    "others", [{}, {"up": NEAR, "down": NEAR}, {"left": NEAR, "right": NEAR, "up_left": NEAR}, {"default": NEAR}]
)
def test_rule1_centre_far_flies_straight(ctl: AvoidanceController, others: dict[str, float]) -> None:
    d = ctl.decide(depths(**{**others, "center": FAR}))  # type: ignore[arg-type]
    assert d.kind is DecisionKind.CLEAR
    assert d.yaw == pytest.approx(0.0, abs=1e-9) and d.pitch == pytest.approx(0.0, abs=1e-9)
    # Full speed unless a speed region (by default the sides) is near.
    sides_near = any(others.get(k, others.get("default", FAR)) < 2.25 for k in CTL.avoid_speed_regions)
    assert d.speed_fraction == pytest.approx(CTL.avoid_speed_fraction if sides_near else 1.0)
    assert "R1" in d.rule_strengths


def test_rule2_blocked_above_goes_down(ctl: AvoidanceController) -> None:
    d = ctl.decide(depths(center=NEAR, up=NEAR, down=FAR))
    assert d.kind is DecisionKind.AVOID and d.pitch < -0.3


def test_rule3_blocked_below_goes_up(ctl: AvoidanceController) -> None:
    d = ctl.decide(depths(center=NEAR, down=NEAR, up=FAR))
    assert d.kind is DecisionKind.AVOID and d.pitch > 0.3


def test_rule4_blocked_right_turns_left(ctl: AvoidanceController) -> None:
    d = ctl.decide(depths(center=NEAR, right=NEAR, left=FAR))
    assert d.kind is DecisionKind.AVOID and d.yaw < -0.3


def test_rule5_blocked_left_turns_right(ctl: AvoidanceController) -> None:
    d = ctl.decide(depths(center=NEAR, left=NEAR, right=FAR))
    assert d.kind is DecisionKind.AVOID and d.yaw > 0.3


@pytest.mark.parametrize(("side", "sign"), [("right", 1.0), ("left", -1.0)])
def test_rule6_preferred_side_when_both_free(side: str, sign: float) -> None:
    d = controller(preferred_yaw_side=side).decide(depths(center=NEAR))
    assert d.kind is DecisionKind.AVOID and sign * d.yaw > 0.3


@pytest.mark.parametrize(("side", "sign"), [("up", 1.0), ("down", -1.0)])
def test_rule7_preferred_vertical_side_when_both_free(side: str, sign: float) -> None:
    d = controller(preferred_pitch_side=side).decide(depths(center=NEAR, left=NEAR, right=NEAR))
    assert d.kind is DecisionKind.AVOID and sign * d.pitch > 0.3
    assert d.yaw == 0.0  # no yaw rule fired: 0 by the controller's choice


@pytest.mark.parametrize("centre_m", [2.0, 1.8, 1.6, 1.5, 1.4])
def test_an_overhead_block_is_gone_under_as_early_as_a_low_wall_is_gone_over(
    ctl: AvoidanceController, centre_m: float
) -> None:
    """An overhead block reads in the up region as near as the centre, while the down region sees under
    it; a low wall is the mirror. Between 0.75 and 2.25 m the up region is partly 'far' too, so at
    weight 1 the preference rule R7 (up) fired as strongly as R2 (down) and cancelled it: no descent
    from 2.25 m in and a brake at 1.5 m, where the low wall climbed from 2 m (PX4 SITL pitch-1 timed
    out in every run r7-r13). R7's weight 0.5 leaves the tie-break to ties."""
    block = ctl.decide(depths(center=centre_m, up=centre_m, up_left=centre_m, up_right=centre_m,
                              left=centre_m, right=centre_m, down=3.0, down_left=3.0, down_right=3.0))
    wall = ctl.decide(depths(center=centre_m, down=centre_m, down_left=centre_m, down_right=centre_m,
                             left=centre_m, right=centre_m, up=6.0, up_left=6.0, up_right=6.0))
    assert block.kind is not DecisionKind.BRAKE and block.pitch < -0.05, block.reason
    assert wall.kind is not DecisionKind.BRAKE and wall.pitch > 0.1, wall.reason
    assert next(r.weight for r in ControllerConfig().main_rules if r.name == "R7") == 0.5


@pytest.mark.parametrize(("side", "sign"), [("right", 1.0), ("left", -1.0)])
def test_tie_rule_takes_the_preferred_side(side: str, sign: float) -> None:
    # Paper Fig. 9c: ahead, above and below blocked, both sides free.
    d = controller(preferred_yaw_side=side).decide(depths(center=NEAR, up=NEAR, down=NEAR, left=FAR, right=FAR))
    assert d.kind is DecisionKind.AVOID
    assert sign * d.yaw > 0.5  # clearly non-zero: the centroid does not collapse to straight
    assert d.pitch == 0.0
    assert "TIE" in d.rule_strengths


@pytest.mark.parametrize(
    ("free", "yaw_sign", "pitch_sign"),
    [("up_right", 1, 1), ("down_left", -1, -1), ("up_left", -1, 1), ("down_right", 1, -1)],
)
def test_corner_controller_when_the_four_sides_are_blocked(free: str, yaw_sign: int, pitch_sign: int) -> None:
    ctl = controller()
    d = ctl.decide(depths(default=NEAR, **{free: FAR}))
    assert d.kind is DecisionKind.AVOID
    assert yaw_sign * d.yaw > 0.3 and pitch_sign * d.pitch > 0.3
    assert "corner" in d.reason


def test_corner_preference_when_all_corners_are_free() -> None:
    d = controller().decide(depths(default=FAR, center=NEAR, up=NEAR, down=NEAR, left=NEAR, right=NEAR))
    assert d.kind is DecisionKind.AVOID and d.yaw > 0.3 and d.pitch > 0.3  # up_right (right, up)
    d = controller(preferred_yaw_side="left", preferred_pitch_side="down").decide(
        depths(default=FAR, center=NEAR, up=NEAR, down=NEAR, left=NEAR, right=NEAR)
    )
    assert d.yaw < -0.3 and d.pitch < -0.3


def test_everything_near_brakes(ctl: AvoidanceController) -> None:
    d = ctl.decide(depths(default=NEAR))
    assert d.kind is DecisionKind.BRAKE and d.reason == "no rule fired"
    assert (d.yaw, d.pitch, d.speed_fraction) == (0.0, 0.0, 0.0)


def test_centre_blocked_without_escape_brakes(ctl: AvoidanceController) -> None:
    d = ctl.decide(depths(default=NEAR, center=1.0))  # near 0.83, far 0.17: only R1/C1 fire
    assert d.kind is DecisionKind.BRAKE and "centre blocked" in d.reason
    assert (d.yaw, d.pitch, d.speed_fraction) == (0.0, 0.0, 0.0)


def test_centre_slightly_near_without_escape_goes_straight_slower() -> None:
    ctl = AvoidanceController(ControllerConfig(avoid_speed_fraction=0.5, avoid_speed_regions=[]))
    d = ctl.decide(depths(default=NEAR, center=1.95))  # near 0.2 < brake_near_degree 0.5
    assert d.kind is DecisionKind.AVOID  # not CLEAR: CLEAR means the centre is far (see module doc)
    assert d.yaw == pytest.approx(0.0, abs=1e-9) and d.pitch == pytest.approx(0.0, abs=1e-9)
    assert d.speed_fraction == pytest.approx(1.0 - 0.5 * 0.2)


def test_speed_fraction_blends_with_centre_near_degree() -> None:
    ctl = AvoidanceController(ControllerConfig(avoid_speed_fraction=0.4))
    assert ctl.decide(depths(center=NEAR)).speed_fraction == pytest.approx(0.4)
    assert ctl.decide(depths(center=1.5)).speed_fraction == pytest.approx(0.7)
    assert ctl.decide(depths()).speed_fraction == 1.0


def test_a_near_side_slows_the_vehicle_like_a_near_centre() -> None:
    # With the sides listed, a box passing beside the vehicle (centre clear, left at 1.5 m: near degree
    # 0.5) slows it as much as the same box ahead would.
    sides = AvoidanceController(
        ControllerConfig(avoid_speed_fraction=0.4, avoid_speed_regions=["left", "right"])
    )
    d = sides.decide(depths(left=1.5))
    assert d.kind is DecisionKind.CLEAR and d.yaw > 0.0  # steers away (side rule S1)
    assert d.speed_fraction == pytest.approx(0.7)
    assert sides.decide(depths(right=NEAR)).speed_fraction == pytest.approx(0.4)
    assert sides.decide(depths(up=NEAR)).speed_fraction == 1.0  # not listed
    # The default (and the paper's): the centre only.
    centre_only = AvoidanceController(ControllerConfig(avoid_speed_fraction=0.4))
    assert centre_only.decide(depths(left=1.5)).speed_fraction == 1.0


# --------------------------------------------------------------------------------------------------
# Unknown regions are near, never far


def test_unknown_centre_is_not_clear(ctl: AvoidanceController) -> None:
    d = ctl.decide(depths(center=math.nan))
    assert d.kind is DecisionKind.AVOID
    assert ctl.decide(depths(default=math.nan)).kind is DecisionKind.BRAKE


def test_unknown_side_is_not_an_escape(ctl: AvoidanceController) -> None:
    d = ctl.decide(depths(center=NEAR, left=math.nan, right=FAR))
    assert d.yaw > 0.3  # like left near
    d = ctl.decide(depths(center=NEAR, right=math.nan, left=FAR))
    assert d.yaw < -0.3  # like right near, although right is the preferred side
    d = ctl.decide(depths(center=NEAR, up=math.nan, down=math.nan, left=math.nan, right=math.nan,
                          up_left=math.nan, up_right=math.nan, down_left=math.nan, down_right=math.nan))
    assert d.kind is DecisionKind.BRAKE


def test_bad_shape_is_rejected(ctl: AvoidanceController) -> None:
    with pytest.raises(ValueError, match="9 region depths"):
        ctl.decide(np.zeros(8))


# --------------------------------------------------------------------------------------------------
# The configuration is really used


def test_membership_breakpoints_change_the_decision() -> None:
    d = depths(center=2.0)
    assert controller().decide(d).kind is DecisionKind.AVOID  # near(2.0) = 1/6 with 0.75..2.25
    tight = {"near": InputTerm(shape="left_shoulder", params_m=(0.5, 1.5)),
             "far": InputTerm(shape="right_shoulder", params_m=(0.5, 1.5))}
    assert controller(input_terms=tight).decide(d).kind is DecisionKind.CLEAR


def test_operators_and_defuzzifier_are_used() -> None:
    d = depths(center=1.2, left=1.0, right=2.0, up=1.4, down=2.1)
    yaws = {
        (a, i, m): controller(and_method=a, implication=i, defuzzification=m).decide(d).yaw
        for a in ("min", "product") for i in ("min", "product") for m in ("centroid", "mean_of_maximum", "bisector")
    }
    assert len({round(v, 9) for v in yaws.values()}) > 6
    assert all(v > 0 for v in yaws.values())  # left nearer than right: turn right


# --------------------------------------------------------------------------------------------------
# Properties

_any_depth = st.one_of(
    st.floats(0.0, 4.0), st.floats(allow_nan=True, allow_infinity=True), st.just(math.nan)
)
_near = st.one_of(st.floats(0.0, 0.75), st.just(math.nan))
_far = st.floats(2.25, 50.0)

_CONTROLLERS = {
    "default": controller(),
    "left_down": controller(preferred_yaw_side="left", preferred_pitch_side="down"),
    "product": controller(and_method="product", or_method="probabilistic_sum", implication="product"),
    "mom": controller(defuzzification="mean_of_maximum"),
    "bisector": controller(defuzzification="bisector"),
}
_ctl_names = st.sampled_from(sorted(_CONTROLLERS))


def _finite_decision(d: Decision) -> None:
    assert math.isfinite(d.yaw) and -1.0 <= d.yaw <= 1.0
    assert math.isfinite(d.pitch) and -1.0 <= d.pitch <= 1.0
    assert math.isfinite(d.speed_fraction) and 0.0 <= d.speed_fraction <= 1.0
    assert all(math.isfinite(v) and 0.0 < v <= 1.0 for v in d.rule_strengths.values())
    if d.kind is DecisionKind.BRAKE:
        assert (d.yaw, d.pitch, d.speed_fraction) == (0.0, 0.0, 0.0)


@settings(max_examples=150, deadline=None)
@given(_ctl_names, st.lists(_any_depth, min_size=9, max_size=9))
def test_outputs_always_finite_and_bounded(name: str, values: list[float]) -> None:
    _finite_decision(_CONTROLLERS[name].decide(np.array(values)))


@settings(max_examples=100, deadline=None)
@given(_ctl_names, st.lists(_any_depth, min_size=9, max_size=9), _near, _near, _far,
       st.sampled_from(["left", "right", "up", "down"]))
def test_steers_away_from_the_nearer_side(
    name: str, values: list[float], centre: float, near: float, far: float, side: str
) -> None:
    opposite = {"left": "right", "right": "left", "up": "down", "down": "up"}[side]
    d = np.array(values)
    d[REGION_INDEX["center"]] = centre
    d[REGION_INDEX[side]] = near
    d[REGION_INDEX[opposite]] = far
    dec = _CONTROLLERS[name].decide(d)
    assert dec.kind is DecisionKind.AVOID
    if side == "left":
        assert dec.yaw > 0
    elif side == "right":
        assert dec.yaw < 0
    elif side == "up":
        assert dec.pitch < 0
    else:
        assert dec.pitch > 0


@settings(max_examples=150, deadline=None)
@given(_ctl_names, st.lists(st.one_of(st.floats(0.0, 6.0), st.just(math.nan)), min_size=9, max_size=9),
       st.integers(0, 8), st.floats(0.0, 1.0), st.booleans())
def test_a_nearer_region_never_makes_it_clear(
    name: str, values: list[float], region: int, shrink: float, unknown: bool
) -> None:
    ctl = _CONTROLLERS[name]
    before = np.array(values)
    after = before.copy()
    if unknown:
        after[region] = math.nan  # unknown counts as near: never farther than a known depth
    elif not math.isnan(before[region]):
        after[region] = before[region] * shrink
    if ctl.decide(before).kind is not DecisionKind.CLEAR:
        assert ctl.decide(after).kind is not DecisionKind.CLEAR


# --------------------------------------------------------------------------------------------------
# Setpoints


def _decision(kind: DecisionKind = DecisionKind.AVOID, yaw: float = 0.5, pitch: float = 0.5,
              speed: float = 0.8) -> Decision:
    return Decision(kind=kind, yaw=yaw, pitch=pitch, speed_fraction=speed, reason="test")


def test_setpoint_signs_and_scales() -> None:
    """A decision flown directly (the offline tools' setpoint) scales by the planner's limits."""
    cfg = parse_config({"planner": {"cruise_speed_m_s": 2.0, "max_yaw_rate_deg_s": 40.0, "max_vertical_speed_m_s": 0.6}})
    sp = decision_setpoint(_decision(yaw=0.5, pitch=0.5), cfg)
    assert sp.forward_m_s == pytest.approx(1.6)
    assert sp.yaw_rate_deg_s == pytest.approx(20.0)  # positive yaw = turn right = positive rate
    assert sp.down_m_s == pytest.approx(-0.3)  # pitch up = climb = negative down
    assert sp.right_m_s == 0.0
    sp = decision_setpoint(_decision(yaw=-1.0, pitch=-1.0, speed=1.0), cfg)
    assert (sp.forward_m_s, sp.yaw_rate_deg_s, sp.down_m_s) == pytest.approx((2.0, -40.0, 0.6))


def test_setpoint_zero_when_braking_or_not_finite() -> None:
    assert decision_setpoint(_decision(DecisionKind.BRAKE, 0.0, 0.0, 0.0), CFG) == ZERO_SETPOINT
    assert decision_setpoint(_decision(yaw=math.nan), CFG).is_zero
    assert decision_setpoint(_decision(speed=math.inf), CFG).is_zero


def test_setpoint_from_a_real_decision(ctl: AvoidanceController) -> None:
    sp = decision_setpoint(ctl.decide(depths(center=NEAR, left=NEAR, up=NEAR)), CFG)
    assert sp.yaw_rate_deg_s > 0 and sp.down_m_s > 0 and sp.forward_m_s > 0  # right and down
    assert decision_setpoint(ctl.decide(depths(default=NEAR)), CFG).is_zero


@pytest.mark.parametrize("wall_m", [0.9, 1.2, 1.4])
def test_flat_wall_filling_the_view_brakes_instead_of_flying_straight(ctl: AvoidanceController, wall_m: float) -> None:
    # Every region at the same depth: left/right and up/down escapes fire with equal strength and
    # cancel to yaw = pitch = 0. That is no escape, so once the centre is near enough: brake.
    d = ctl.decide(np.full(9, wall_m))
    assert d.kind is DecisionKind.BRAKE, d


def test_flat_wall_far_enough_slows_but_does_not_brake(ctl: AvoidanceController) -> None:
    d = ctl.decide(np.full(9, 2.0))  # centre near degree 0.17 < brake_near_degree 0.5
    assert d.kind is DecisionKind.AVOID
    assert abs(d.yaw) < 1e-9 and abs(d.pitch) < 1e-9
