"""Config sections of the service shell: camera source, vehicle link, ZeroMQ bus, daemon.

Owned by the daemon work (issue 5). Every field: type, default, bounds, unit in its name, description.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from companion.config._base import StrictModel


class CameraConfig(StrictModel):
    """Where frames come from."""

    source: Literal["sim", "uvc", "replay"] = Field(
        default="sim",
        description="sim: the built-in renderer; uvc: a ZED over UVC (V4L2); replay: a recording.",
    )
    width_px: int = Field(default=672, ge=64, le=4416, description="Width of ONE eye, pixels (ZED: 2208/1920/1280/672).")
    height_px: int = Field(default=376, ge=48, le=1242, description="Height of one eye, pixels (ZED: 1242/1080/720/376).")
    fps_hz: float = Field(default=30.0, gt=0.0, le=120.0, description="Requested frame rate, frames per second.")


class VehicleConfig(StrictModel):
    """The autopilot link."""

    connection: str = Field(
        default="udpin://0.0.0.0:14540",
        min_length=1,
        max_length=200,
        description="MAVSDK connection URL: udpin://0.0.0.0:14540 for SITL, serial:///dev/ttyTHS1:921600 on a Jetson.",
    )
    setpoint_rate_hz: float = Field(
        default=20.0, ge=2.0, le=100.0, description="Rate at which setpoints are streamed, whatever the vision rate, Hz."
    )


class BusConfig(StrictModel):
    """The ZeroMQ control plane."""

    health_endpoint: str = Field(
        default="tcp://127.0.0.1:5560", min_length=1, description="PUB endpoint for health messages."
    )
    control_endpoint: str = Field(
        default="tcp://127.0.0.1:5561", min_length=1, description="ROUTER endpoint for requests."
    )


class ServiceConfig(StrictModel):
    """The daemon itself."""

    autostart: bool = Field(
        default=False, description="Engage without an 'engage' request (for tests and simulation only)."
    )
