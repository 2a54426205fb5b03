"""Config of the nine regions and their robust minimum (``[regions]``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from companion.config._base import StrictModel

#: The nine regions, row-major over the image (up row first, left column first).
REGION_NAMES: tuple[str, ...] = (
    "up_left",
    "up",
    "up_right",
    "left",
    "center",
    "right",
    "down_left",
    "down",
    "down_right",
)

#: A region's name (the same names, in the same order, as :data:`REGION_NAMES`).
RegionName = Literal["up_left", "up", "up_right", "left", "center", "right", "down_left", "down", "down_right"]


class RegionsConfig(StrictModel):
    """The nine regions and how each is reduced to one depth."""

    safe_window_width_m: float = Field(
        default=0.5,
        gt=0.05,
        le=10.0,
        description="Width of the safe window around the vehicle that defines the centre region, metres.",
    )
    safe_window_height_m: float = Field(
        default=0.5,
        gt=0.05,
        le=10.0,
        description="Height of the safe window that defines the centre region, metres.",
    )
    reference_distance_m: float = Field(
        default=1.5,
        gt=0.1,
        le=50.0,
        description=(
            "Distance at which the safe window is projected through the rectified focal length to size "
            "the centre region, metres (paper: 0.5 m at 1.5 m ≈ 150 px at f ≈ 450 px)."
        ),
    )
    robust_percentile_pct: float = Field(
        default=2.0,
        ge=0.0,
        le=50.0,
        description=(
            "Region depth = this low percentile of the region's valid depths, percent: the k-th "
            "nearest valid pixel with k = max(1, ceil(pct/100 · n_valid)). 0 = the raw minimum (the "
            "paper's choice, which one false match turns into a phantom obstacle)."
        ),
    )
    min_valid_fraction: float = Field(
        default=0.10,
        gt=0.0,
        le=1.0,
        description=(
            "A region with a smaller share of valid depth pixels than this is unknown, and the "
            "controller treats unknown as near."
        ),
    )
    max_depth_m: float = Field(
        default=20.0,
        gt=1.0,
        le=1000.0,
        description="Region depths beyond this (including matches at disparity 0) are reported as this, metres.",
    )
