"""The two seams between the pure core and the outside world: where frames come from, where setpoints go.

The daemon uses a real ZED (:class:`CameraSource` over UVC) and PX4 (:class:`VehicleLink` over MAVSDK);
the simulator implements the same two interfaces with the renderer and a vehicle model, so the code path
it scores is the product's own.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:  # annotations only: the seams sit below the core that fills them
    from companion.core.types import VelocitySetpoint


@dataclass(frozen=True)
class Frame:
    """One capture.

    Attributes:
        image: uint8 (H, 2W, 3) BGR side-by-side frame (left eye first); from a UVC camera with
            ``camera.pixels = "luma"``, its (H, 2W, 2) YUYV bytes (Y0 U Y1 V: ``[..., 0]`` is the grey).
        timestamp_s: capture time on the monotonic clock of the process that consumes it, seconds
            (the simulator uses simulated time).
        seq: capture sequence number, increasing by 1 per frame the source produced (a gap means
            frames were dropped before they reached the consumer).
    """

    image: np.ndarray
    timestamp_s: float
    seq: int


@runtime_checkable
class CameraSource(Protocol):
    """A blocking frame source. ``read`` runs in the capture thread, never on the event loop."""

    name: str

    @property
    def eye_size_px(self) -> tuple[int, int]:
        """(width, height) of one eye, pixels."""
        ...

    def open(self) -> None:
        """Open the device or file. Raises :class:`~companion.errors.CameraError`."""
        ...

    def read(self) -> Frame:
        """Block until the next frame. Raises :class:`~companion.errors.CameraError` when the source is
        gone (unplugged, end of a recording); the caller decides whether to reopen."""
        ...

    def close(self) -> None:
        """Release the device. Safe to call twice."""
        ...


@dataclass(frozen=True)
class VehicleState:
    """What the service knows about the vehicle.

    Attributes:
        connected: the autopilot's heartbeat is being received.
        armed: motors armed.
        flight_mode: the autopilot's flight mode name: PX4's as MAVSDK reports it (e.g. "OFFBOARD",
            "HOLD", "POSCTL"), ArduPilot's by its own mode number (e.g. "GUIDED", "LOITER", "BRAKE").
        in_offboard: the autopilot is in the mode the service commands it in: PX4's OFFBOARD,
            ArduCopter's GUIDED.
        position_ned_m: float (3,) local position north, east, down in metres, or None if unknown.
        attitude_rad: float (3,) roll, pitch, yaw in radians (yaw from north, positive clockwise), or None.
        timestamp_s: when this state was last updated, on the consumer's clock, seconds.
        position_timestamp_s: when ``position_ned_m`` was last received, on the consumer's clock,
            seconds (None before the first).
        velocity_ned_m_s: float (3,) velocity north, east, down in m/s, from the same report as
            ``position_ned_m``, or None if unknown.
        autopilot: which autopilot the link flies: "px4", "ardupilot", or "unknown" before its
            heartbeat.
    """

    connected: bool = False
    armed: bool = False
    flight_mode: str = "UNKNOWN"
    in_offboard: bool = False
    position_ned_m: np.ndarray | None = None
    attitude_rad: np.ndarray | None = None
    timestamp_s: float = 0.0
    position_timestamp_s: float | None = None
    velocity_ned_m_s: np.ndarray | None = None
    autopilot: str = "unknown"


@runtime_checkable
class VehicleLink(Protocol):
    """The autopilot, as the service commands it: body-frame velocity + yaw-rate setpoints in offboard."""

    async def connect(self, timeout_s: float) -> None:
        """Connect and wait for the autopilot. Raises :class:`~companion.errors.VehicleError`."""
        ...

    async def send_setpoint(self, setpoint: VelocitySetpoint) -> None:
        """Hand one setpoint to the autopilot link (called at the setpoint rate)."""
        ...

    async def start_offboard(self) -> None:
        """Enter offboard mode (a setpoint must have been sent first). Raises VehicleError if refused."""
        ...

    async def hold(self) -> None:
        """Leave offboard for Hold (PX4 AUTO.LOITER, ArduCopter LOITER). Raises VehicleError if refused."""
        ...

    async def stop_setpoints(self) -> None:
        """Stop streaming setpoints WITHOUT any mode change (the link must not re-send the last one).

        Called after the pilot or PX4 left offboard (a mode change then would fight the pilot) and after
        our own Hold took. MAVSDK's ``offboard.stop()`` is NOT this: it also commands Hold. The next
        ``send_setpoint`` starts streaming again."""
        ...

    def state(self) -> VehicleState:
        """The latest known vehicle state (non-blocking)."""
        ...

    async def close(self) -> None:
        """Stop streaming and release the link. Safe to call twice."""
        ...
