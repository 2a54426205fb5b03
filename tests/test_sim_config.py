"""The simulator's config section and the paper-faithful profile."""

from __future__ import annotations

from pathlib import Path

import pytest

from companion.config import CompanionConfig, load_config, parse_config
from companion.errors import ConfigError

PAPER = Path(__file__).resolve().parent.parent / "config" / "paper.toml"


def test_paper_profile_is_the_papers_controller() -> None:
    cfg = load_config(PAPER)
    default = CompanionConfig()
    assert [r.name for r in cfg.controller.main_rules] == ["R1", "R2", "R3", "R4", "R5", "R6", "R7", "TIE"]
    assert cfg.controller.avoid_speed_fraction == 1.0  # constant speed
    # The fuzzy controller's steering dominates the local planner's cost: its weight outweighs all
    # the others together.
    p = cfg.planner
    others = p.weight_goal + p.weight_time + p.weight_clearance + p.weight_smooth + p.weight_visited
    assert p.weight_fuzzy > 10.0 * others and default.planner.weight_fuzzy < default.planner.weight_goal
    assert p.no_progress_distance_m == 0.0  # no watchdog: the paper's controller only avoids
    assert cfg.lut.release_time_constant_s == 0.0
    # The paper's values are the same in both.
    assert cfg.controller.input_terms == default.controller.input_terms
    assert cfg.regions == default.regions
    paper_rules = [r for r in default.controller.main_rules if not r.name.startswith("S")]
    assert [(r.name, r.when, r.then) for r in cfg.controller.main_rules] == [(r.name, r.when, r.then) for r in paper_rules]
    # The paper weighs every rule alike; the defaults weigh its preference R7 at 0.5 (a tie-break
    # that must not cancel R2: test_avoidance_rules).
    assert all(r.weight == 1.0 for r in cfg.controller.main_rules)
    assert {r.name: r.weight for r in paper_rules if r.weight != 1.0} == {"R7": 0.5}


def test_defaults_add_side_rules_and_a_speed_blend() -> None:
    cfg = CompanionConfig()
    assert [r.name for r in cfg.controller.main_rules][-4:] == ["S1", "S2", "S3", "S4"]
    assert cfg.controller.avoid_speed_fraction < 1.0


@pytest.mark.parametrize(
    ("patch", "field"),
    [
        ({"sim": {"exposure_gain_range": [1.2, 0.8]}}, "exposure_gain_range"),
        ({"sim": {"physics_rate_hz": 30.0, "camera_rate_hz": 60.0}}, "physics_rate_hz"),
        ({"sim": {"collision_radius_m": 0.0}}, "sim.collision_radius_m"),
        ({"sim": {"eye_width_px": 10}}, "sim.eye_width_px"),
    ],
)
def test_sim_section_is_validated(patch: dict, field: str) -> None:
    with pytest.raises(ConfigError, match=field):
        parse_config(patch)
