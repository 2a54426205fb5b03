"""What the service's supervisor remembers between steps (:mod:`companion.core.supervisor`): mutable,
owned by one :class:`~companion.core.supervisor.Supervisor`, never shared."""

from __future__ import annotations

from dataclasses import dataclass, field

from companion.core.goal import COURSE, GoalSpec
from companion.core.supervisor_io import Action, Override, State


@dataclass
class Engaging:
    """An engage under way: streaming since ``since_s``, offboard asked for at ``start_sent_s``."""

    since_s: float
    mode_at_request: str
    start_sent_s: float | None = None
    start_pending: bool = False


@dataclass
class Leaving:
    """Leaving offboard to Hold since ``since_s``, because of ``what``."""

    since_s: float
    what: str  # why we leave, e.g. "operator disengage"
    start_sent_s: float | None  # an offboard start we asked for that may still take effect
    start_pending: bool
    last_hold_s: float | None = None
    holds: int = 0


@dataclass
class Memory:
    """Everything the supervisor remembers between steps (mutable, private)."""

    state: State = State.PASSIVE
    reason: str = "started passive: waiting for an engage request"
    activity: State = State.ENGAGED  # engaged / paused / override, while commanding
    streaming: bool = False  # we have handed setpoints and not stopped the stream since
    ready: bool = False  # streaming zero while passive so that a pilot's offboard switch is accepted
    by_switch: bool = False  # the current engagement came from the pilot's offboard switch
    owns_offboard: bool = False  # the vehicle is in offboard because we put it there
    engaging: Engaging | None = None
    leaving: Leaving | None = None
    override: Override | None = None
    override_until_s: float = 0.0
    autostart_pending: bool = False
    shutting_down: bool = False
    stalled: bool = False  # paused by the progress watchdog, a dead end or the goal reached (not by the operator)
    stall_reason: str = ""  # why, as it was when it stalled (the watchdog's clock is reset right after)
    goal: GoalSpec = COURSE  # the goal of the engage under way (applied when offboard is confirmed)
    actions: list[Action] = field(default_factory=list)
