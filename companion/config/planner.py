"""The local planner's section (``[planner]``): one planner on a local map, a stopping-distance speed
law, one cost function and the safety filters after it (companion/core/planner/, docs/planner.md).

Every clearance derives from ``vehicle.radius_m``; the settings here are physics (braking, latency),
the map's resolution and memory, and the cost's weights.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from companion.config._base import StrictModel


class PlannerConfig(StrictModel):
    """The local planner: how fast, how near, what the map keeps, and how the way is chosen."""

    cruise_speed_m_s: float = Field(
        default=3.0,
        gt=0.0,
        le=20.0,
        description=(
            "Top speed of the local planner where the map shows enough seen-free space ahead to stop "
            "in, m/s; the speed law slows below it wherever the space is shorter."
        ),
    )
    braking_accel_m_s2: float = Field(
        default=2.0,
        gt=0.0,
        le=20.0,
        description=(
            "Deceleration the vehicle is counted on to brake with, m/s²: below the autopilot's "
            "horizontal acceleration limit (PX4 MPC_ACC_HOR 3 m/s²) so that a stop planned at it "
            "is one the vehicle can fly."
        ),
    )
    latency_s: float = Field(
        default=1.0,
        ge=0.0,
        le=3.0,
        description=(
            "Time from a surface entering the camera's view to the vehicle starting to brake for it, "
            "s: a frame period, the pipeline's processing time and the autopilot's velocity "
            "response (a first-order lag follows a falling setpoint its time constant late: PX4 "
            "about 0.85 s). The speed law flies this long at the commanded speed before braking."
        ),
    )
    stop_margin_m: float = Field(
        default=0.3,
        ge=0.0,
        le=5.0,
        description=(
            "Room kept in hand beyond the vehicle's radius, m: the seen-free length left after a "
            "planned stop (the map is inflated by the radius), and the gap to the nearest surface "
            "seen the vehicle is moved back out to beside it: the depth error of stereo at a few "
            "metres and the drift the position estimate shows before it is countered."
        ),
    )
    voxel_m: float = Field(
        default=0.15,
        ge=0.05,
        le=0.5,
        description=(
            "Edge of the local map's cubes, m: finer resolves narrower gaps (a doorway's free band is "
            "its width less twice the inflated radius, quantised to this), coarser costs less."
        ),
    )
    map_range_m: float = Field(
        default=8.0,
        ge=2.0,
        le=30.0,
        description=(
            "Depth out to which a frame's measurements enter the map, m, and the horizon of the "
            "planner's free lengths: stereo's depth error grows with the square of the depth, and "
            "the speed law needs no more than the stopping distance at cruise."
        ),
    )
    block_px: int = Field(
        default=4,
        ge=1,
        le=16,
        description=(
            "The disparity image enters the map as the largest valid disparity (the nearest surface) "
            "of each block of this many pixels square, pixels: one ray per block. The GPU reduces on "
            "the device: a multiple of gpu.disparity_preview_downsample there."
        ),
    )
    block_erode_px: Annotated[int, Field(ge=0, le=4)] | Literal["auto"] = Field(
        default="auto",
        description=(
            "Before the blocks are reduced, each pixel takes the smallest disparity of its row's pixels "
            "within this many pixels (an invalid one the smallest), pixels; 0 = off; auto = 1 with the "
            "semi-global matcher (stereo.backend cpu-sgm, or cupy or reference with matcher sgm), 0 "
            "with any other. A foreground edge smeared onto what is behind it, and a lone too-near "
            "pixel, then give no block its depth, and a true surface loses this many pixels at each "
            "side. A thin upright thing (a fence's bar, a pole) stays: a pixel more than an eighth "
            "nearer than something within twice this many pixels on each side keeps its disparity, as "
            "far as the rows above and below see it too (docs/planner.md). The "
            "semi-global matcher smears depth edges and fills plain walls; StereoBM's sparse map has "
            "few such blocks and would lose near surfaces to it."
        ),
    )
    occupied_memory_s: float = Field(
        default=20.0,
        gt=0.0,
        le=600.0,
        description=(
            "A surface not seen again is forgotten this long after it was last seen, s: the map lives "
            "in the position estimate, which drifts against the world."
        ),
    )
    free_memory_s: float = Field(
        default=6.0,
        gt=0.0,
        le=600.0,
        description=(
            "Space seen free counts as free this long after it was last seen free, s; older space is "
            "unknown again, and unknown is near (the speed law does not fly into it)."
        ),
    )
    yaw_step_deg: float = Field(
        default=5.0,
        ge=2.0,
        le=45.0,
        description=(
            "Spacing of the candidate directions in yaw, degrees (all round the vehicle). A gap whose "
            "free band (its width less twice the inflated radius) is w wide has a candidate through it "
            "only from within w / spacing (radians) of it: 3.4 m for a 0.3 m band at 5°, 1.7 m at 10° "
            "(the vehicle creeps toward such a gap until a line fits). Finer flies narrow gaps sooner "
            "and faster but costs tick time in proportion."
        ),
    )
    max_climb_deg: float = Field(
        default=25.0,
        ge=0.0,
        le=45.0,
        description=(
            "Steepest candidate climb or descent, degrees (five climbs from minus to plus this): within "
            "the camera's vertical half view (about 29° on a ZED at VGA) so that a climb is seen "
            "before it is flown."
        ),
    )
    max_yaw_rate_deg_s: float = Field(
        default=90.0,
        gt=0.0,
        le=360.0,
        description=(
            "Fastest turn toward the chosen direction, deg/s: the camera must sweep slowly enough "
            "for a frame every few degrees (30 fps at 90 deg/s: 3 degrees a frame)."
        ),
    )
    max_vertical_speed_m_s: float = Field(
        default=1.0,
        gt=0.0,
        le=5.0,
        description="Fastest climb or descent the planner commands, m/s.",
    )
    weight_goal: float = Field(
        default=1.0,
        ge=0.0,
        le=100.0,
        description="Cost weight of the turn away from the goal's direction (per half turn).",
    )
    weight_time: float = Field(
        default=1.0,
        ge=0.0,
        le=100.0,
        description=(
            "Cost weight of the time to the goal along a candidate (its free length at the speed law's "
            "speed, then the rest at cruise), per time to fly the map range at cruise: prefers the "
            "way that gets there soonest, round an obstacle rather than crawling at it."
        ),
    )
    weight_clearance: float = Field(
        default=0.5,
        ge=0.0,
        le=100.0,
        description="Cost weight of a short free length (1 at none, 0 at the map range).",
    )
    weight_smooth: float = Field(
        default=0.6,
        ge=0.0,
        le=100.0,
        description=(
            "Cost weight of a change from the last chosen direction (per half turn): keeps a side "
            "once taken, so that a detour does not swing between two equal ways."
        ),
    )
    weight_fuzzy: float = Field(
        default=0.3,
        ge=0.0,
        le=100.0,
        description=(
            "Cost weight of a difference from the direction the fuzzy controller steers to (its "
            "yaw and pitch outputs, per half turn): the paper's reactive controller as a term."
        ),
    )
    weight_visited: float = Field(
        default=0.5,
        ge=0.0,
        le=100.0,
        description=(
            "Cost weight of flying back into places already flown through (per second spent there, "
            "at most 1): the way out of a pocket is not the way in."
        ),
    )
    fuzzy_yaw_deg: float = Field(
        default=45.0,
        ge=0.0,
        le=90.0,
        description=(
            "Turn the fuzzy controller's full yaw output (1) stands for, degrees: the side region's "
            "bearing off the optical axis."
        ),
    )
    look_memory_s: float = Field(
        default=4.0,
        gt=0.0,
        le=60.0,
        description=(
            "A direction the camera looked along within this long, from within a metre of here, "
            "counts as looked at, s: unknown space there is not worth turning to look at again (a "
            "plain wall stays unknown); older, or looked at from elsewhere, unknown space is worth a "
            "look."
        ),
    )
    dead_end_free_m: float = Field(
        default=1.5,
        ge=0.1,
        le=20.0,
        description=(
            "The flight holds where no direction within dead_end_cone_deg of the goal's is free for "
            "this long, every one of them ends at a surface seen, and no way round the surfaces seen "
            "leads on within the cone, m: a closed pocket."
        ),
    )
    dead_end_cone_deg: float = Field(
        default=100.0,
        ge=10.0,
        le=180.0,
        description="Half-angle round the goal's direction a dead end must be closed over, degrees.",
    )
    floor_m: float = Field(
        default=0.5,
        ge=0.0,
        le=100.0,
        description="Lowest altitude above the local origin the planner descends to, m (the ground's margin).",
    )
    ceiling_m: float = Field(
        default=3.0,
        gt=0.0,
        le=500.0,
        description=(
            "Highest altitude above the local origin the planner climbs to, m: a room's ceiling, and "
            "a wall this high is no way over (a closed pocket is held, not climbed out of)."
        ),
    )

    no_progress_distance_m: float = Field(
        default=60.0,
        ge=0.0,
        le=1000.0,
        description=(
            "Progress watchdog, metres flown at cruise (0 = off): the service holds position, paused "
            "with the reason, once the vehicle has not come command.progress_step_m nearer its goal "
            "in the time it takes to fly this far at cruise_speed_m_s (60 m: 20 s at 3 m/s, 86 s at "
            "0.7 m/s). A way round can lead away from the goal and back; it is as long at any cruise, "
            "so the watchdog's time grows as the cruise falls."
        ),
    )

    @property
    def no_progress_timeout_s(self) -> float:
        """The progress watchdog's time, seconds (0 = off): ``no_progress_distance_m`` at cruise."""
        return self.no_progress_distance_m / self.cruise_speed_m_s

    @model_validator(mode="after")
    def _floor_below_ceiling(self) -> PlannerConfig:
        if self.floor_m >= self.ceiling_m:
            raise ValueError(f"floor_m ({self.floor_m}) must be below ceiling_m ({self.ceiling_m})")
        return self
