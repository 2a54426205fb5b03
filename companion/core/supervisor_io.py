"""What goes into the service's supervisor and what comes out of it (:mod:`companion.core.supervisor`).

The states, the actions the shell carries out on the vehicle link, the operator's requests and their
replies, one step's output, and the timings and limits the supervisor applies. Plain frozen data: no
behaviour, no I/O.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, Union

from companion.core.goal import COURSE, GoalSpec
from companion.core.types import Decision, VelocitySetpoint

if TYPE_CHECKING:
    from companion.config import CompanionConfig
    from companion.config.core import CommandConfig


class State(str, enum.Enum):
    """What the service is doing (health's ``state``)."""

    PASSIVE = "passive"
    ENGAGING = "engaging"
    ENGAGED = "engaged"
    DEGRADED = "degraded"
    FAILSAFE = "failsafe"
    PAUSED = "paused"
    OVERRIDE = "override"
    DISENGAGED = "disengaged"


class Action(str, enum.Enum):
    """What the shell must do on the vehicle link, besides handing over the setpoint."""

    START_OFFBOARD = "start_offboard"  #: request offboard mode (a setpoint has been streamed first)
    HOLD = "hold"  #: leave offboard to Hold (only ever while we own offboard)
    STOP_SETPOINTS = "stop_setpoints"  #: stop streaming (and MAVSDK's re-sending) WITHOUT a mode change


# ---------------------------------------------------------------------------------------------- requests


@dataclass(frozen=True)
class Engage:
    """Operator: take control (enter offboard), flying toward ``goal`` (:mod:`companion.core.goal`;
    default: the heading and line at engagement)."""

    goal: GoalSpec = COURSE


@dataclass(frozen=True)
class Goto:
    """Operator, while engaged: a new goal (:class:`~companion.core.goal.GoalSpec`), from where the
    vehicle is now. Ends a hold of the progress watchdog, a dead end or the goal reached (automatic
    again); refused while not engaged (engage with a goal instead)."""

    goal: GoalSpec


@dataclass(frozen=True)
class Disengage:
    """Operator: give control back (leave offboard to Hold if we are in it)."""


@dataclass(frozen=True)
class Pause:
    """Operator: hover in offboard (zero velocity) until resumed."""


@dataclass(frozen=True)
class Resume:
    """Operator: back to automatic (ends a pause, a hold or an override)."""


@dataclass(frozen=True)
class Override:
    """Operator: fly this for ``duration_s`` seconds, then automatic again.

    Attributes:
        yaw: in [-1, 1] (+ turns right), scaled by ``planner.max_yaw_rate_deg_s`` (at most
            ``envelope.max_yaw_rate_deg_s``).
        pitch: in [-1, 1] (+ climbs), scaled by ``planner.max_vertical_speed_m_s`` (at most
            ``envelope.max_vertical_speed_m_s``).
        speed_fraction: in [0, 1], share of ``planner.cruise_speed_m_s``.
        duration_s: > 0, at most ``service.override_max_duration_s``.
    """

    yaw: float
    pitch: float
    speed_fraction: float
    duration_s: float


@dataclass(frozen=True)
class Shutdown:
    """The service is stopping: leave offboard to Hold if we own it, then stop streaming."""


@dataclass(frozen=True)
class ActionResult:
    """The shell's report of how an :class:`Action` went (``ok`` False with the error's message)."""

    action: Action
    ok: bool
    message: str = ""


Request = Union[Engage, Goto, Disengage, Pause, Resume, Override, Shutdown, ActionResult]


@dataclass(frozen=True)
class Reply:
    """The answer to one operator request (ActionResults get none)."""

    request: Request
    ok: bool
    message: str


class FrameOutcome(Protocol):
    """What the supervisor needs from a frame result (:class:`~companion.core.pipeline.FrameResult`;
    it also reads ``refined``, ``near_blocks`` and ``geometry`` where present)."""

    timestamp_s: float
    decision: Decision


@dataclass(frozen=True)
class StepOutput:
    """What one :meth:`~companion.core.supervisor.Supervisor.step` decided.

    Attributes:
        setpoint: hand this to the vehicle link now; ``None``: hand nothing (not commanding).
        actions: to carry out after the setpoint, in order.
        state: the state after this step.
        reason: one line saying why the service is in this state.
        replies: one per operator request, in order.
        changed: state or reason differ from before the step.
        frame_age_s: age of the newest frame result at ``now_s`` (inf without one), seconds.
    """

    setpoint: VelocitySetpoint | None
    actions: tuple[Action, ...]
    state: State
    reason: str
    replies: tuple[Reply, ...]
    changed: bool
    frame_age_s: float


@dataclass(frozen=True)
class SupervisorConfig:
    """The timing and limits the supervisor applies (seconds unless named otherwise).

    Attributes:
        command: the frame timeouts (``stale_frame_timeout_s``, ``failsafe_timeout_s``) and the
            progress watchdog's step.
        flight: the whole configuration the local stack flies by (``planner``, ``vehicle``,
            ``envelope``, ...); None: the defaults.
    """

    command: CommandConfig
    offboard_prestream_s: float = 0.5
    engage_timeout_s: float = 3.0
    hold_retry_s: float = 2.0
    leave_timeout_s: float = 10.0
    require_armed_to_engage: bool = True
    override_max_duration_s: float = 10.0
    override_respects_brake: bool = True
    autostart: bool = False
    engage_on_offboard_switch: bool = False
    flight: CompanionConfig | None = None

    @classmethod
    def from_config(cls, cfg: CompanionConfig) -> SupervisorConfig:
        v, s = cfg.vehicle, cfg.service
        return cls(
            command=cfg.command,
            offboard_prestream_s=v.offboard_prestream_s,
            engage_timeout_s=v.engage_timeout_s,
            hold_retry_s=v.hold_retry_s,
            leave_timeout_s=v.leave_timeout_s,
            require_armed_to_engage=v.require_armed_to_engage,
            override_max_duration_s=s.override_max_duration_s,
            override_respects_brake=s.override_respects_brake,
            autostart=s.autostart,
            engage_on_offboard_switch=v.engage_on_offboard_switch,
            flight=cfg,
        )
