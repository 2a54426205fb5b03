"""Config of the OBSTACLE_DISTANCE reduction and of when it is sent (``[obstacle_distance]``).

The depth the pipeline computes is reduced to MAVLink's OBSTACLE_DISTANCE (72 bins of 5°, body frame)
and sent to the autopilot, whose own collision prevention (PX4's ``CP_DIST`` in Position mode,
ArduPilot's proximity library with ``PRX1_TYPE`` = MAVLink) then stops the vehicle in manual modes too.
The reduction is :mod:`companion.core.obstacle`; the sending is the vehicle link's.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from companion.config._base import StrictModel


class ObstacleDistanceConfig(StrictModel):
    """OBSTACLE_DISTANCE from the depth image: the reduction and when it is sent."""

    send: Literal["always", "engaged", "off"] = Field(
        default="always",
        description=(
            "always: one OBSTACLE_DISTANCE per processed frame whether or not the service is engaged (the "
            "autopilot's collision prevention protects manual flight too); engaged: only while the service "
            "commands the vehicle; off: never, and the reduction is not computed."
        ),
    )
    band_half_height_m: float = Field(
        default=0.4,
        gt=0.05,
        le=5.0,
        description=(
            "Only points within this height above or below the camera count (the vehicle's own height "
            "band: the ground and what passes overhead are not obstacles to a level flight), metres."
        ),
    )
    robust_percentile_pct: float = Field(
        default=2.0,
        ge=0.0,
        le=50.0,
        description=(
            "A bin's distance = this low percentile of its in-band points' horizontal distances, percent "
            "(the k-th nearest, k = max(1, ceil(pct/100 · n))): one false match is no obstacle."
        ),
    )
    min_points: int = Field(
        default=20,
        ge=1,
        le=100000,
        description=(
            "A bin with fewer in-band points than this reports no obstacle (max_distance + 1 cm): far "
            "away, the band is only a few image rows high."
        ),
    )
    min_valid_fraction: float = Field(
        default=0.02,
        ge=0.0,
        le=1.0,
        description=(
            "A bin whose columns have a smaller share of valid disparities than this (over all rows) is "
            "unknown (UINT16_MAX): the camera sees nothing it can match there, e.g. a blank wall."
        ),
    )
    max_distance_m: float = Field(
        default=12.0,
        gt=0.5,
        le=600.0,
        description=(
            "OBSTACLE_DISTANCE's max_distance: points farther than this are no obstacle, metres (the "
            "nearest, min_distance, is the rig's: f·B / (stereo.num_disparities - 1))."
        ),
    )
