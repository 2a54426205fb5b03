"""Log back-off: report a condition that repeats (no autopilot yet, a camera that will not open) at
once, then less and less often, so that a log read hours later is not a wall of the same line.

Time is passed in (``now_s``, seconds on any monotonic clock); nothing here reads a clock.
"""

from __future__ import annotations

import math


class LogBackoff:
    """Which occurrences of a repeating condition to log.

    The first occurrence is due at once; after each logged one the next is due ``interval_s`` later,
    and the interval doubles from ``first_interval_s`` up to ``max_interval_s``. Occurrences between
    two logged ones are counted (:attr:`suppressed`), so the next line can say how many there were.
    :meth:`reset` starts over (the condition ended).

    Args:
        first_interval_s: the wait after the first logged occurrence, seconds (> 0).
        max_interval_s: the longest wait between two logged occurrences, seconds (>= first).
    """

    def __init__(self, first_interval_s: float = 10.0, max_interval_s: float = 600.0) -> None:
        if not (first_interval_s > 0 and math.isfinite(first_interval_s)):
            raise ValueError(f"first_interval_s must be > 0, got {first_interval_s}")
        if not max_interval_s >= first_interval_s:
            raise ValueError(f"max_interval_s ({max_interval_s}) must be >= first_interval_s ({first_interval_s})")
        self.first_interval_s = float(first_interval_s)
        self.max_interval_s = float(max_interval_s)
        self.reset()

    def reset(self) -> None:
        """Forget the condition: the next occurrence is logged at once."""
        self._next_s: float | None = None
        self._since_s: float | None = None
        self.interval_s = self.first_interval_s
        self.suppressed = 0
        self.occurrences = 0

    def due(self, now_s: float) -> bool:
        """Record an occurrence at ``now_s``; True when it should be logged (then :attr:`interval_s` is
        the wait until the next logged one and :attr:`suppressed` the count skipped before this one,
        until the next call)."""
        self.occurrences += 1
        if self._since_s is None:
            self._since_s = now_s
        if self._next_s is None:
            self._next_s = now_s + self.interval_s
            self._skipped = 0
            return True
        if now_s >= self._next_s:
            self.interval_s = min(self.max_interval_s, 2.0 * self.interval_s)
            self._next_s = now_s + self.interval_s
            self.suppressed = self._skipped
            self._skipped = 0
            return True
        self._skipped += 1
        return False

    def elapsed_s(self, now_s: float) -> float:
        """Seconds since the first occurrence (0 before it)."""
        return 0.0 if self._since_s is None else max(0.0, now_s - self._since_s)
