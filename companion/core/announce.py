"""What the pilot sees on the ground station: the service's heartbeat state and its STATUSTEXT lines.

Pure: no clock, no MAVLink. The daemon feeds :class:`Announcer` every supervisor step (the time, the
state and reason, the newest decision, the camera's health) and sends what it returns; the vehicle link
turns it into HEARTBEAT and STATUSTEXT messages.

* **Heartbeat state** (MAV_STATE): standby while passive, engaging or disengaged; active while the
  service commands the vehicle; critical in failsafe, while degraded (stale frames: zero velocity) and
  while the camera is lost.
* **STATUSTEXT** on every change of state, on each new brake (a BRAKE decision after a non-BRAKE one
  while engaged), each new pause, and when the camera is lost or back, each at most
  :data:`MAX_TEXT_CHARS` characters ("companion: " included), with a MAV_SEVERITY that QGroundControl
  shows (WARNING and worse pop up).
* **Rate limit**: a token bucket (``burst`` lines, refilled at one per ``min_interval_s``). A line that
  finds the bucket empty is not dropped but kept as *pending*, replaced by any newer one, and sent
  when a token is back: a flickering decision costs the link at most one line per interval, and the
  last word always reaches the pilot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

#: STATUSTEXT's payload is 50 characters (longer texts are chunked, which QGC shows oddly): every
#: line here fits in one.
MAX_TEXT_CHARS = 50
PREFIX = "companion: "

# MAV_SEVERITY
EMERGENCY, ALERT, CRITICAL, ERROR, WARNING, NOTICE, INFO, DEBUG = range(8)
# MAV_STATE
MAV_STATE_BOOT, MAV_STATE_STANDBY, MAV_STATE_ACTIVE, MAV_STATE_CRITICAL = 1, 3, 4, 5

_COMMANDING = ("engaged", "paused", "override")


def heartbeat_state(state: str, camera_ok: bool, frames_ok: bool = True) -> int:
    """The MAV_STATE of the service's heartbeat for supervisor state ``state`` (its value, e.g.
    ``"engaged"``), the camera's health and whether the pipeline delivers frames."""
    if state in ("failsafe", "degraded") or not camera_ok or not frames_ok:
        return MAV_STATE_CRITICAL
    if state in _COMMANDING:
        return MAV_STATE_ACTIVE
    return MAV_STATE_STANDBY


def fit(text: str) -> str:
    """``text`` cut to :data:`MAX_TEXT_CHARS` characters, ASCII only (the field is a char array)."""
    text = text.encode("ascii", "replace").decode("ascii")
    return text if len(text) <= MAX_TEXT_CHARS else text[: MAX_TEXT_CHARS - 1] + "~"


def _metres(x: float | None) -> str:
    return "?" if x is None or not math.isfinite(x) else f"{x:.1f}"


def state_text(state: str, reason: str) -> tuple[int, str]:
    """(severity, line) for entering supervisor state ``state`` with its ``reason``."""
    r = reason.lower()
    if state == "engaged":
        return NOTICE, fit(PREFIX + "engaged")
    if state == "engaging":
        if "offboard switch" in r:
            return NOTICE, fit(PREFIX + "engaging (offboard switch)")
        return INFO, fit(PREFIX + "engaging")
    if state == "paused":
        if "no progress" in r:
            secs = _first_number_after(reason, "for ")
            return WARNING, fit(PREFIX + (f"no progress {secs} s, holding" if secs else "no progress, holding"))
        return NOTICE, fit(PREFIX + "paused, holding")
    if state == "override":
        return NOTICE, fit(PREFIX + "manual override")
    if state == "degraded":
        if "camera lost" in r:
            return ERROR, fit(PREFIX + "camera lost, holding")
        return WARNING, fit(PREFIX + "frames stale, holding")
    if state == "failsafe":
        if "link lost" in r:
            return CRITICAL, fit(PREFIX + "vehicle link lost, stopped")
        return CRITICAL, fit(PREFIX + "failsafe: no frames, Hold")
    if state == "disengaged":
        if "left offboard for" in r:
            mode = reason.split("left OFFBOARD for ", 1)[-1].split(" ", 1)[0] if "left OFFBOARD for " in reason else ""
            return NOTICE, fit(PREFIX + (f"released, pilot in {mode}" if mode else "released to the pilot"))
        if "pilot changed the mode" in r:
            return NOTICE, fit(PREFIX + "engage cancelled by pilot")
        if "refused" in r or "not confirmed" in r or "not engaging" in r:
            return WARNING, fit(PREFIX + "engage failed")
        if "shutdown" in r:
            return NOTICE, fit(PREFIX + "shutting down")
        return NOTICE, fit(PREFIX + "disengaged")
    if state == "passive":
        return INFO, fit(PREFIX + "standby")
    return INFO, fit(PREFIX + state)


def _first_number_after(text: str, marker: str) -> str | None:
    """The number right after ``marker`` in ``text`` (e.g. "20" in "... for 20 s ..."), or None."""
    i = text.find(marker)
    if i < 0:
        return None
    word = text[i + len(marker) :].split(" ", 1)[0]
    try:
        float(word)
    except ValueError:
        return None
    return word


def brake_text(distance_m: float | None) -> tuple[int, str]:
    """(severity, line) for a new brake with the obstacle ``distance_m`` ahead (None: unknown)."""
    if distance_m is None or not math.isfinite(distance_m):
        return WARNING, fit(PREFIX + "brake, way ahead unknown")
    return WARNING, fit(PREFIX + f"brake, obstacle {_metres(distance_m)} m ahead")


@dataclass
class TextLimiter:
    """The STATUSTEXT rate limit (see the module doc). Times are the caller's monotonic seconds.

    Args:
        min_interval_s: one token per this long, seconds.
        burst: tokens when full (lines that may go out back to back).
    """

    min_interval_s: float = 1.0
    burst: int = 3
    _tokens: float = field(default=-1.0, repr=False)
    _t_s: float | None = field(default=None, repr=False)
    pending: tuple[int, str] | None = None
    suppressed: int = 0  # lines replaced while pending (never sent)

    def _refill(self, now_s: float) -> None:
        if self._t_s is None:
            self._tokens = float(self.burst)
        else:
            rate = 1.0 / self.min_interval_s if self.min_interval_s > 0 else math.inf
            self._tokens = min(float(self.burst), self._tokens + max(0.0, now_s - self._t_s) * rate)
        self._t_s = now_s

    def offer(self, now_s: float, severity: int, text: str) -> list[tuple[int, str]]:
        """A new line at ``now_s``: returns what may be sent now (the pending one first, if any)."""
        if self.pending is not None:
            self.suppressed += 1
        self.pending = (severity, text)
        return self.due(now_s)

    def due(self, now_s: float) -> list[tuple[int, str]]:
        """The pending line if a token is there now (call it every step), else nothing."""
        self._refill(now_s)
        if self.pending is None or self._tokens < 1.0:
            return []
        self._tokens -= 1.0
        line, self.pending = self.pending, None
        return [line]


@dataclass
class Announcer:
    """Decides, step by step, which STATUSTEXT lines to send and the heartbeat's state.

    Args:
        limiter: the rate limit.
    """

    limiter: TextLimiter = field(default_factory=TextLimiter)
    _state: str | None = None
    _braking: bool = False
    _camera_ok: bool = True
    _frames_ok: bool = True
    _stalled: bool = False

    def step(
        self,
        now_s: float,
        state: str,
        reason: str,
        decision_kind: str | None,
        ahead_m: float | None,
        camera_ok: bool,
        frames_ok: bool = True,
    ) -> list[tuple[int, str]]:
        """The lines to send now, as (MAV_SEVERITY, text).

        Args:
            now_s: the caller's monotonic time, seconds.
            state: the supervisor's state value (``"engaged"``, ...); ``reason`` its reason line.
            decision_kind: the newest frame's decision (``"clear"``, ``"avoid"``, ``"brake"``) or None.
            ahead_m: the distance ahead the brake is about (the centre region's), metres, or None.
            camera_ok: whether the camera delivers frames.
            frames_ok: whether the pipeline delivers results (the newest is not older than the
                caller's limit): a stalled or failing pipeline with the camera still streaming.
        """
        lines: list[tuple[int, str]] = []
        if camera_ok != self._camera_ok:
            self._camera_ok = camera_ok
            if state not in ("degraded", "failsafe"):  # those say it themselves
                lines += [(ERROR, fit(PREFIX + "camera lost")) if not camera_ok else (NOTICE, fit(PREFIX + "camera back"))]
        if frames_ok != self._frames_ok:
            self._frames_ok = frames_ok
            if camera_ok and state not in ("degraded", "failsafe"):
                lines += [(ERROR, fit(PREFIX + "pipeline stalled")) if not frames_ok else (NOTICE, fit(PREFIX + "pipeline back"))]
        if state != self._state:
            first = self._state is None
            self._state = state
            if not (first and state == "passive"):
                lines.append(state_text(state, reason))
            self._braking = False
            self._stalled = state == "paused" and "no progress" in reason.lower()
        elif state == "paused":
            stalled = "no progress" in reason.lower()
            if stalled and not self._stalled:
                lines.append(state_text(state, reason))
            self._stalled = stalled
        braking = state == "engaged" and decision_kind == "brake"
        if braking and not self._braking:
            lines.append(brake_text(ahead_m))
        self._braking = braking
        out: list[tuple[int, str]] = []
        for sev, text in lines:
            out += self.limiter.offer(now_s, sev, text)
        out += self.limiter.due(now_s)
        return out
