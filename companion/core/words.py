"""A decision in a pilot's words: what the vehicle does and why, in one plain sentence.

The controller's own reason (which rule or controller decided, memberships) is for tuning; a pilot
reads "obstacle 0.4 m ahead, turning right". This is the one place that turns a decision into those
words, from what it did (kind, yaw, pitch, speed) and what was seen (the region depths), never from
the controller's reason text, so a new planner's reasons need no new words here. Used by ``demo``,
``watch``, the view and the health message (``decision.words``).

Pure: numbers in, a string out.
"""

from __future__ import annotations

import math
from typing import Any

from companion.core.types import REGION_NAMES

#: |yaw| or |pitch| below this is "straight on" in words (the outputs are in [-1, 1]).
TURN_WORDS_THRESHOLD = 0.05

_CENTRE = REGION_NAMES.index("center")


def _ahead_m(depth_m: Any) -> float | None:
    """The centre region's depth, metres (None: unknown or not given)."""
    if depth_m is None:
        return None
    try:
        d = float(depth_m[_CENTRE]) if not isinstance(depth_m, dict) else depth_m.get("center")
    except (IndexError, TypeError, ValueError):
        return None
    return d if d is not None and math.isfinite(d) else None


def _metres(d: float) -> str:
    return f"{d:.1f} m" if d < 10.0 else f"{d:.0f} m"


def decision_words(
    kind: Any, yaw: float, pitch: float, depth_m: Any = None, speed_fraction: float | None = None
) -> str:
    """One plain sentence for a decision.

    Args:
        kind: a :class:`~companion.core.types.DecisionKind` or its value ("clear", "avoid", "brake").
        yaw, pitch: the decision's outputs in [-1, 1] (positive: right, up).
        depth_m: the region depths, float ``(9,)`` in ``REGION_NAMES`` order (NaN unknown) or a name ->
            metres (None unknown) mapping; None: not known.
        speed_fraction: share of the cruise speed in [0, 1], if known.

    Returns:
        e.g. "obstacle 0.4 m ahead, turning right", "clear ahead (4.2 m)", "stopping: obstacle 0.6 m
        ahead and no way round".
    """
    k = str(getattr(kind, "value", kind)).lower()
    ahead = _ahead_m(depth_m)
    if k == "brake":
        if ahead is None and depth_m is not None:
            return "stopping: cannot see ahead (too little texture or light to measure)"
        if ahead is None:
            return "stopping: no way round"
        return f"stopping: obstacle {_metres(ahead)} ahead and no way round"
    moves = []
    if yaw >= TURN_WORDS_THRESHOLD:
        moves.append("turning right")
    elif yaw <= -TURN_WORDS_THRESHOLD:
        moves.append("turning left")
    if pitch >= TURN_WORDS_THRESHOLD:
        moves.append("climbing")
    elif pitch <= -TURN_WORDS_THRESHOLD:
        moves.append("descending")
    if k == "clear":  # clear, yet steering: the controller's side rules, a descent back from a climb
        return "clear ahead" + (f" ({_metres(ahead)})" if ahead is not None else "") + (f", {' and '.join(moves)}" if moves else "")
    if not moves:
        moves.append("straight on")
    if speed_fraction is not None and speed_fraction < 0.99:
        moves.append("slowing")
    seen = f"obstacle {_metres(ahead)} ahead" if ahead is not None else "cannot see ahead clearly"
    return f"{seen}, {' and '.join(moves[:2])}" + (", slowing" if "slowing" in moves[2:] else "")


#: A control reply's error prefixes as the config module writes them, and the words a pilot reads.
_ERROR_PREFIXES = (
    ("patch: invalid config: ", "the change was refused (nothing changed): "),
    ("patch: rig check: error: ", "the change was refused (nothing changed): the rig cannot work with it: "),
    ("patch: ", "the change was refused (nothing changed): "),
)


def error_words(message: str) -> str:
    """A control reply's error message in plain words ("patch: invalid config: X" -> "the change was
    refused (nothing changed): X"); other messages as they are."""
    for prefix, words in _ERROR_PREFIXES:
        if message.startswith(prefix):
            return words + message[len(prefix):]
    return message
