"""Pacing a frame source: at a fixed rate, or at the times a recording was made.

Both sleep on a stop event, so that closing the source ends a wait at once, and both restart their
schedule rather than burst when the reader has fallen behind (a slow disk, a pause).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

#: A source that far behind its recording's schedule starts the schedule again from now, seconds.
BEHIND_S = 0.5


class RatePacer:
    """Sleeps so that frames come out every ``period_s`` seconds (restarts the grid when it falls
    behind by more than a period)."""

    def __init__(self, period_s: float, clock: Callable[[], float], stop: threading.Event) -> None:
        self.period_s = period_s
        self._clock = clock
        self._stop = stop
        self._next: float | None = None

    def restart(self) -> None:
        """The next frame starts the grid (the source opened again)."""
        self._next = None

    def wait(self) -> None:
        now = self._clock()
        if self._next is None or now - self._next > self.period_s:
            self._next = now  # first frame, or we fell behind by more than a frame: no burst
        delay = self._next - now
        if delay > 0:
            self._stop.wait(delay)
        self._next += self.period_s


class RecordedPacer:
    """Sleeps so that frame ``i``, recorded at ``t_i``, comes out at ``t0 + (t_i - t_0)·unit_s`` on
    ``clock`` (the first frame after :meth:`restart` anchors both); more than :data:`BEHIND_S` late
    anchors again at the late frame.

    Args:
        unit_s: seconds per unit of the recording's times (1e-9 for nanoseconds; the difference of two
            integer times is taken before scaling, so nanosecond stamps keep their precision).
    """

    def __init__(self, clock: Callable[[], float], stop: threading.Event, unit_s: float = 1.0) -> None:
        self._clock = clock
        self._stop = stop
        self.unit_s = unit_s
        self._anchor: tuple[float, float | int] | None = None  # (clock, recorded time)

    def restart(self) -> None:
        """The next frame anchors the schedule (the recording opened or started again)."""
        self._anchor = None

    def wait(self, t: float | int) -> None:
        now = self._clock()
        if self._anchor is None:
            self._anchor = (now, t)
        due = self._anchor[0] + (t - self._anchor[1]) * self.unit_s
        if due > now:
            self._stop.wait(due - now)
        elif now - due > BEHIND_S:
            self._anchor = (now, t)
