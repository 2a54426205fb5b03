"""A decision in a pilot's words: plain sentences from what the vehicle does and what it sees; the
controller's reasons (rule ids, memberships) only with --verbose."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.core.types import REGION_NAMES, DecisionKind
from companion.core.words import decision_words


def _depths(centre: float) -> np.ndarray:
    d = np.full(9, 5.0)
    d[REGION_NAMES.index("center")] = centre
    return d


@pytest.mark.parametrize(
    "kind, yaw, pitch, centre, speed, words",
    [
        (DecisionKind.AVOID, 0.6, 0.0, 0.42, None, "obstacle 0.4 m ahead, turning right"),
        (DecisionKind.AVOID, -0.6, 0.3, 1.2, None, "obstacle 1.2 m ahead, turning left and climbing"),
        (DecisionKind.AVOID, 0.0, 0.0, 1.5, 0.5, "obstacle 1.5 m ahead, straight on and slowing"),
        ("avoid", 0.0, -0.4, math.nan, None, "cannot see ahead clearly, descending"),
        (DecisionKind.CLEAR, 0.0, 0.0, 4.21, 1.0, "clear ahead (4.2 m)"),
        (DecisionKind.BRAKE, 0.0, 0.0, 0.6, 0.0, "stopping: obstacle 0.6 m ahead and no way round"),
        (DecisionKind.BRAKE, 0.0, 0.0, math.nan, 0.0, "stopping: cannot see ahead (too little texture or light to measure)"),
    ],
)
def test_decisions_in_plain_words(kind, yaw, pitch, centre, speed, words) -> None:
    assert decision_words(kind, yaw, pitch, _depths(centre), speed) == words


def test_words_from_a_health_message_s_regions() -> None:
    regions = {name: 3.0 for name in REGION_NAMES} | {"center": 0.8}
    assert decision_words("avoid", 0.5, 0.0, regions) == "obstacle 0.8 m ahead, turning right"


def test_no_rule_ids_nor_memberships_in_the_words() -> None:
    for kind in DecisionKind:
        text = decision_words(kind, 0.3, -0.2, _depths(0.9), 0.7)
        assert "R2" not in text and "<" not in text and "controller" not in text


def test_demo_speaks_plain_words(tmp_path, capsys) -> None:
    from companion.cli import main

    assert main(["demo", "--out", str(tmp_path / "a")]) == 0
    plain = capsys.readouterr().out
    assert "what it does" in plain and "escape by" not in plain and "main controller" not in plain
    assert "clear ahead" in plain


def test_watch_shows_the_words_and_the_reason_only_with_verbose() -> None:
    from companion.service.client import render_health

    h = {"decision": {"kind": "avoid", "reason": "main controller: escape by R2 (0.80), centre near 0.60",
                      "words": "obstacle 0.9 m ahead, turning right"}, "yaw": 0.5, "pitch": 0.0}
    assert "turning right" in render_health(h) and "R2" not in render_health(h)
    assert "escape by R2" in render_health(h, verbose=True)


def test_a_refused_change_reads_as_one_plain_sentence() -> None:
    from companion.core.words import error_words

    assert error_words("patch: invalid config: planner.cruise_speed_m_s: Input should be greater than or equal to 0 (got -1)") == (
        "the change was refused (nothing changed): planner.cruise_speed_m_s: Input should be greater than or equal to 0 (got -1)"
    )
    assert error_words("engage refused: vehicle is disarmed (the service never arms it)") == (
        "engage refused: vehicle is disarmed (the service never arms it)"
    )
