"""What the pilot reads (companion.core.announce): the STATUSTEXT wording for every state the supervisor
can say, its 50-character limit, the rate limit, and the heartbeat's MAV_STATE."""

from __future__ import annotations

import pytest

from companion.core.announce import (
    CRITICAL,
    ERROR,
    MAV_STATE_ACTIVE,
    MAV_STATE_CRITICAL,
    MAV_STATE_STANDBY,
    NOTICE,
    WARNING,
    Announcer,
    TextLimiter,
    brake_text,
    heartbeat_state,
    state_text,
)

# Every reason line the supervisor gives, with what the pilot should read.
REASONS = [
    ("engaged", "engaged: avoiding obstacles", "companion: engaged"),
    ("engaging", "engage requested: streaming zero setpoints before requesting offboard", "companion: engaging"),
    ("paused", "no progress along the course for 20 s (less than 0.5 m: command.no_progress_timeout_s, "
     "progress_step_m): holding position; resume to try again, or take over", "companion: no progress 20 s, holding"),
    ("paused", "paused by the operator: zero velocity in offboard", "companion: paused, holding"),
    ("override", "manual override (automatic again when it expires)", "companion: manual override"),
    ("degraded", "camera lost (reconnecting): zero velocity", "companion: camera lost, holding"),
    ("degraded", "frames stale (newest older than 0.5 s): zero velocity", "companion: frames stale, holding"),
    ("failsafe", "newest frame 5.1 s old (> failsafe_timeout_s 5 s): leaving offboard to Hold",
     "companion: failsafe: no frames, Hold"),
    ("failsafe", "vehicle link lost while commanding: setpoints stopped so that the autopilot's own failsafe acts",
     "companion: vehicle link lost, stopped"),
    ("disengaged", "vehicle left OFFBOARD for POSCTL while engaged (pilot or autopilot failsafe); not commanding, "
     "not re-engaging", "companion: released, pilot in POSCTL"),
    ("disengaged", "operator disengage: leaving offboard to Hold", "companion: disengaged"),
    ("disengaged", "offboard start refused: DENIED", "companion: engage failed"),
    ("disengaged", "pilot changed the mode to ALTCTL during engage; not engaging", "companion: engage cancelled by pilot"),
    ("disengaged", "shutdown: leaving offboard to Hold", "companion: shutting down"),
    ("passive", "started passive: waiting for an engage request", "companion: standby"),
]


@pytest.mark.parametrize(("state", "reason", "text"), REASONS)
def test_every_state_has_a_short_line(state: str, reason: str, text: str) -> None:
    severity, line = state_text(state, reason)
    assert line == text and len(line) <= 50 and line.isascii()
    assert 0 <= severity <= 7


def test_the_issues_examples() -> None:
    assert brake_text(0.6) == (WARNING, "companion: brake, obstacle 0.6 m ahead")
    assert brake_text(None)[1] == "companion: brake, way ahead unknown"
    assert state_text("degraded", "camera lost (reconnecting): zero velocity")[0] == ERROR
    assert state_text("failsafe", "newest frame 5.1 s old")[0] == CRITICAL
    assert state_text("engaged", "engaged: avoiding obstacles")[0] == NOTICE


def test_heartbeat_state_follows_the_service() -> None:
    assert heartbeat_state("passive", True) == MAV_STATE_STANDBY
    assert heartbeat_state("disengaged", True) == MAV_STATE_STANDBY
    assert heartbeat_state("engaging", True) == MAV_STATE_STANDBY
    for s in ("engaged", "paused", "override"):
        assert heartbeat_state(s, True) == MAV_STATE_ACTIVE
    assert heartbeat_state("failsafe", True) == MAV_STATE_CRITICAL
    assert heartbeat_state("degraded", True) == MAV_STATE_CRITICAL
    assert heartbeat_state("passive", False) == MAV_STATE_CRITICAL  # camera lost


def test_limiter_lets_a_burst_through_then_one_per_interval_and_keeps_the_last_word() -> None:
    lim = TextLimiter(min_interval_s=1.0, burst=3)
    sent = []
    for i in range(10):  # a flood at t=0
        sent += lim.offer(0.0, NOTICE, f"line {i}")
    assert [t for _, t in sent] == ["line 0", "line 1", "line 2"]
    assert lim.pending == (NOTICE, "line 9") and lim.suppressed == 6
    assert lim.due(0.5) == []
    assert lim.due(1.0) == [(NOTICE, "line 9")]
    assert lim.due(5.0) == []


def test_a_flickering_brake_costs_at_most_one_line_per_interval() -> None:
    ann = Announcer(TextLimiter(min_interval_s=1.0, burst=2))
    lines = ann.step(0.0, "engaged", "engaged: avoiding obstacles", "clear", 5.0, True)
    assert lines == [(NOTICE, "companion: engaged")]
    out = []
    t = 0.0
    for i in range(200):  # brake / clear alternating at 20 Hz for 10 s
        t += 0.05
        out += [(t, line) for line in ann.step(t, "engaged", "engaged: avoiding obstacles", "brake" if i % 2 else "clear", 0.6, True)]
    assert 9 <= len(out) <= 12, out  # one burst token left, then one per second
    assert all(text == "companion: brake, obstacle 0.6 m ahead" for _, (_, text) in out)
    times = [tt for tt, _ in out]
    assert all(b - a >= 0.95 for a, b in zip(times[1:], times[2:]))  # 20 Hz steps: within one step of 1 s


def test_announcer_says_state_changes_new_pauses_and_the_camera() -> None:
    ann = Announcer(TextLimiter(min_interval_s=0.0, burst=10))
    assert ann.step(0.0, "passive", "started passive", None, None, True) == []  # the start is not news
    assert ann.step(0.1, "passive", "started passive", None, None, False) == [(ERROR, "companion: camera lost")]
    assert ann.step(0.2, "passive", "started passive", None, None, True) == [(NOTICE, "companion: camera back")]
    assert ann.step(0.3, "engaging", "engage requested", None, None, True)[0][1] == "companion: engaging"
    assert ann.step(0.4, "engaged", "engaged: avoiding obstacles", "brake", 0.64, True) == [
        (NOTICE, "companion: engaged"),
        (WARNING, "companion: brake, obstacle 0.6 m ahead"),
    ]
    assert ann.step(0.5, "engaged", "engaged: avoiding obstacles", "brake", 0.5, True) == []  # the same brake
    stall = "no progress along the course for 20 s (less than 0.5 m): holding position"
    assert ann.step(0.6, "paused", stall, "brake", 0.5, True) == [(WARNING, "companion: no progress 20 s, holding")]
    assert ann.step(0.7, "paused", stall, "brake", 0.5, True) == []
    assert ann.step(0.8, "degraded", "camera lost (reconnecting): zero velocity", None, None, False) == [
        (ERROR, "companion: camera lost, holding")
    ]


def test_a_stalled_pipeline_is_said_and_makes_the_heartbeat_critical() -> None:
    ann = Announcer(TextLimiter(min_interval_s=0.0, burst=10))
    ann.step(0.0, "passive", "started passive", None, None, True)
    assert ann.step(0.1, "passive", "started passive", None, None, True, frames_ok=False) == [
        (ERROR, "companion: pipeline stalled")
    ]
    assert ann.step(0.2, "passive", "started passive", None, None, True, frames_ok=True) == [
        (NOTICE, "companion: pipeline back")
    ]
    assert heartbeat_state("passive", True, frames_ok=False) == MAV_STATE_CRITICAL
