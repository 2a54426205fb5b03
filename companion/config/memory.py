"""Config of the obstacle memory and the out-of-view guard (``[memory]``)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator

from companion.config._base import StrictModel


#: ``push_baseline_m`` is 0 or at least this many ``trust_cell_m`` (a cube's horizontal diagonal is 1.41).
PUSH_BASELINE_MIN_CELLS = 1.5


class MemoryConfig(StrictModel):
    """Obstacle memory: what the camera saw near, kept for a few seconds in the local (NED) frame, so
    that an obstacle the vehicle turned away from or flew past still keeps it away. The camera sees
    only ahead (ZED: ~±44°), and a multicopter drifts with its position estimate's error (PX4 SITL:
    ~0.2 m/s), sideways into what it no longer sees. Not in the paper."""

    duration_s: float = Field(
        default=30.0,
        ge=0.0,
        le=300.0,
        description=(
            "How long a point seen near is remembered after it was last seen, seconds; 0 = off (the "
            "paper). Long enough to outlast a brake, a hold or a turn in place in a dead end (an "
            "obstacle beside the vehicle is out of view the whole time: 17 s in one simulated dead "
            "end), short because the memory lives in the vehicle's position estimate, which drifts "
            "against the world."
        ),
    )
    max_depth_m: float = Field(
        default=2.5,
        gt=0.0,
        le=10.0,
        description=(
            "Only cells nearer than this are remembered, metres. Far enough that a wall 1 m to the "
            "side is remembered: the leftmost num_disparities columns are never matched, so a side "
            "wall first shows at ~32° off the heading, 1.6 times its lateral distance ahead."
        ),
    )
    map_depth_m: float = Field(
        default=5.0,
        gt=0.0,
        le=20.0,
        description=(
            "Cells out to this depth are remembered too, metres, for the detour layer's map only "
            "([detour]: which way round is shorter); only points seen nearer than max_depth_m guard "
            "the vehicle or keep course hold from a side. At most max_depth_m means no map beyond it."
        ),
    )
    grid_rows: int = Field(default=6, ge=1, le=64, description="Rows of the image's memory cells.")
    grid_cols: int = Field(
        default=24,
        ge=1,
        le=128,
        description=(
            "Columns of the image's memory cells: each cell gives at most one remembered point per "
            "frame, at its robust nearest depth, on the ray of the block that depth came from."
        ),
    )
    block_px: int = Field(
        default=4,
        ge=1,
        le=16,
        description=(
            "The disparity image is first reduced to the largest valid disparity of each block of this "
            "many pixels square (the GPU does this on the device: it must be a multiple of "
            "gpu.disparity_preview_downsample there), then cells are reduced from blocks."
        ),
    )
    block_erode_px: Annotated[int, Field(ge=0, le=4)] | Literal["auto"] = Field(
        default="auto",
        description=(
            "Before the blocks are reduced, each pixel takes the smallest disparity of its row's pixels "
            "within this many pixels (an invalid one the smallest), pixels; 0 = off; auto = 1 with the "
            "semi-global matcher (stereo.backend cupy or reference, matcher sgm), 0 with any other. A "
            "lone too-near pixel or a foreground edge smeared onto what is behind it then gives no "
            "block its depth; a true surface loses this many pixels at each side. The semi-global "
            "matcher smears depth edges and fills plain walls, so it halves its too-near blocks; "
            "StereoBM's sparse map has few, and loses near surfaces to it, so auto leaves it off there."
        ),
    )
    robust_percentile_pct: float = Field(
        default=25.0,
        ge=0.0,
        le=100.0,
        description=(
            "A cell's disparity is the k-th largest of its blocks' with k = max(1, ceil(pct/100 · "
            "valid blocks)): something near must fill this share of a cell to be remembered. Each "
            "block is already its nearest pixel, so a small patch of false matches fills many blocks; "
            "at 5 % a weak-texture patch matched wrong for 2 frames of 3 was remembered and pushed a "
            "simulated vehicle into a pillar."
        ),
    )
    min_valid_fraction: float = Field(
        default=0.1,
        ge=0.0,
        le=1.0,
        description=(
            "A cell with fewer valid blocks than this fraction gives no point (unknown ahead is the "
            "regions' business: the controller treats it as near)."
        ),
    )
    confirm_frames: int = Field(
        default=3,
        ge=1,
        le=9,
        description=(
            "A cell's depth is the median of its last this many frames, odd, a cell seen nothing in "
            "counting as far: a false match that lasts one frame is not remembered."
        ),
    )
    map_clear_after_frames: int = Field(
        default=3,
        ge=0,
        le=100,
        description=(
            "A remembered point that this many frames in a row see well past (map_clear_depth_ratio) "
            "leaves the detour layer's map until it is seen again, frames; 0 = never. Only measured "
            "blocks judge: a plain wall the matcher leaves unmatched, a point out of view or nearer "
            "than the rig can see stays. It still guards the vehicle (a point the position drift "
            "moved is seen past too) until guard_clear_after_s. A door's jambs smeared into "
            "its opening closed the door on the map."
        ),
    )
    guard_clear_after_s: float = Field(
        default=4.0,
        ge=0.0,
        le=60.0,
        description=(
            "A remembered point that the camera sees well past for this long in a row (as for "
            "map_clear_after_frames, which must be on, with the detour layer: they judge the points) no "
            "longer guards the vehicle, keeps course hold from a side or bounds a gap until it is seen "
            "again, seconds; 0 = never. Each frame that sees past counts the time since the frame "
            "before it, at most 0.2 s, so that a camera stall is not time spent seeing past. Far longer "
            "than map_clear_after_frames: a point the position drift moved off its surface is seen past "
            "too, and forgetting it within a couple of seconds lets a drifting vehicle into the "
            "surface; a false match kept guarding for longer stops the vehicle in open space. Seconds, "
            "not frames, so that it means the same at any camera rate."
        ),
    )
    map_clear_depth_ratio: float = Field(
        default=1.3,
        gt=1.0,
        le=10.0,
        description=(
            "A frame sees past a remembered point when every valid block within 2 blocks of its ray "
            "measures at least this many times the point's depth (a ratio: stereo depth error grows "
            "with depth)."
        ),
    )
    guard_distance_m: float = Field(
        default=0.6,
        gt=0.0,
        le=5.0,
        description=(
            "A remembered point out of the camera's view (or nearer than it can see) this near to the "
            "vehicle's centre, horizontally, pushes the vehicle away (and stops its motion toward it when "
            "on its path, keep_out_m), metres. Default: the 0.25 m vehicle plus 0.35 m, below the 0.66 m a centred vehicle has "
            "to either side of a 0.82 m doorway gap."
        ),
    )
    keep_out_m: float = Field(
        default=0.35,
        gt=0.0,
        le=5.0,
        description=(
            "A guarding point within this of the path ahead (the line of the commanded velocity) stops "
            "the motion toward it, metres: the 0.25 m vehicle plus 0.1 m. Points farther from the path "
            "only push, so that passing between two pillars is not stalled."
        ),
    )
    guard_gain_per_s: float = Field(
        default=1.5,
        ge=0.0,
        le=10.0,
        description=(
            "The push away: this gain times how far inside guard_distance_m the point is, per second "
            "(m/s per metre); 0 = only stop the motion toward it. Only points seen from two places "
            "push (push_baseline_m): "
            "a push moves the vehicle where the camera does not see, and a false point seen once "
            "pushed a simulated vehicle into a pillar out of view; every guarding point stops the "
            "motion toward it."
        ),
    )
    max_guard_speed_m_s: float = Field(
        default=0.5, ge=0.0, le=2.0, description="The largest speed the push commands, m/s."
    )
    guard_damping_fraction: float = Field(
        default=0.0,
        ge=0.0,
        le=2.0,
        description=(
            "The push away from a point drops by this fraction of the speed the vehicle already moves "
            "away from it (its measured velocity; never below zero), dimensionless; 0 = off. Between "
            "two points on opposite sides the push alone is a spring, and the autopilot's lag (~0.85 s "
            "with PX4) makes a strong push ring between a wall and a box until it touches. Damping "
            "stops that ringing, but costs stiffness where the position drifts unseen (the estimate "
            "says the vehicle moves away)."
        ),
    )
    counter_velocity_fraction: float = Field(
        default=0.5,
        ge=0.0,
        le=2.0,
        description=(
            "While the vehicle is still moving toward a guarding point on the path it actually flies "
            "(its velocity lags the setpoint: ~0.85 s with PX4), the setpoint moves away from it at "
            "this fraction of that closing speed (with the push, at most max_guard_speed_m_s), so the "
            "lag does not carry it in (0 = only stop commanding toward it). Dimensionless. Without it a "
            "vehicle pushed off one jamb of a narrow doorway slides on into the other; 1 shoves the "
            "vehicle sideways, where the camera does not see either."
        ),
    )
    hold_clear_m: float = Field(
        default=1.0,
        ge=0.0,
        le=5.0,
        description=(
            "Course hold neither turns nor slides toward a side with a remembered point within this of "
            "the vehicle, horizontally, and not more than keep_out_m behind it, metres (0 = off): an "
            "obstacle just passed is beside it, out of view, and turning back toward the line right "
            "after a box would swing the vehicle into the box's rear corner."
        ),
    )
    gap_centering_gain_per_s: float = Field(
        default=1.0,
        ge=0.0,
        le=10.0,
        description=(
            "Gap centering: with remembered points on both sides of the vehicle, abreast or up to "
            "gap_lookahead_m ahead, less than gap_max_width_m apart sideways (a doorway, two pillars), "
            "a CLEAR decision flies sideways toward the middle between the nearest of each side at this "
            "speed per metre off it, 1/s, instead of the line hold's sideways step (0 = off). It raises "
            "the clearance through doorways from a few centimetres to a few tenths of a metre. Only "
            "points seen from two places push_baseline_m apart bound a gap: a false near point would "
            "make a false gap."
        ),
    )
    max_gap_centering_speed_m_s: float = Field(
        default=0.3, ge=0.0, le=2.0, description="Gap centering: the largest sideways speed it commands, m/s."
    )
    gap_max_width_m: float = Field(
        default=2.0,
        gt=0.0,
        le=10.0,
        description=(
            "Gap centering: only a gap narrower than this (sideways, between the nearest remembered "
            "points left and right) is centred in, metres; wider ones leave room for course hold."
        ),
    )
    gap_lookahead_m: float = Field(
        default=1.5,
        gt=0.0,
        le=10.0,
        description=(
            "Gap centering: points up to this far ahead of the vehicle (and abreast, down to keep_out_m "
            "behind) count as its sides, metres: far enough to line up with a doorway before its "
            "jambs leave the view, near enough not to centre on what lies beyond a turn."
        ),
    )
    path_slow_time_s: float = Field(
        default=0.0,
        ge=0.0,
        le=10.0,
        description=(
            "Slow down for what lies in the vehicle's path: on CLEAR and AVOID decisions the forward "
            "speed is at most (how far it can fly straight on before a trusted remembered point comes "
            "within path_half_width_m of its centre, less path_stop_m) / this, seconds; 0 = off (the "
            "default). About the autopilot's velocity lag plus a frame: PX4 follows a setpoint ~0.85 s "
            "late. The centre region is a fixed angle wide, so near the vehicle what it will hit sits "
            "in a side region (the paper's Fig. 11), where a CLEAR decision does not look. Points the "
            "camera now sees past do not count."
        ),
    )
    path_stop_m: float = Field(
        default=0.2,
        ge=0.0,
        le=5.0,
        description=(
            "Slowing for the path: the speed reaches 0 this far short of where a point would come "
            "within path_half_width_m, metres."
        ),
    )
    path_half_width_m: float = Field(
        default=0.3,
        gt=0.0,
        le=5.0,
        description=(
            "Slowing for the path: a point less than this from the vehicle's centre line, sideways, "
            "is in its path, and the vehicle may come no nearer to it than this, metres (the 0.25 m "
            "vehicle plus 0.05 m). A wall alongside, farther sideways, does not slow it."
        ),
    )
    path_range_m: float = Field(
        default=2.0,
        gt=0.0,
        le=10.0,
        description="Slowing for the path: points farther than this, horizontally, do not count, metres.",
    )
    gap_pass_clearance_m: float = Field(
        default=0.35,
        ge=0.0,
        le=2.0,
        description=(
            "Gap centering: the vehicle flies on into a gap only while its centre stays this far from "
            "the nearest bounding point on either side, metres (0 = off: it flies on while it centres): "
            "off the middle by more than half the gap's width less this, the forward speed falls to 0 "
            "over gap_lineup_ramp_m while the sideways slide lines it up (at least "
            "gap_lineup_min_slack_m off the middle always counts as lined up, so that a gap the map has "
            "narrowed still lets a centred vehicle through). The vehicle's 0.25 m plus 0.1 m: a vehicle "
            "arriving at a door well off its middle at cruise hits the jamb before the centering has "
            "slid it across."
        ),
    )
    gap_lineup_ramp_m: float = Field(
        default=0.1,
        gt=0.0,
        le=2.0,
        description=(
            "Gap centering: beyond the lined-up band (gap_pass_clearance_m), the forward speed falls "
            "from full to 0 over this much more offset from the gap's middle, metres."
        ),
    )
    gap_lineup_min_slack_m: float = Field(
        default=0.05,
        ge=0.0,
        le=1.0,
        description=(
            "Gap centering: this far off the gap's middle always counts as lined up, metres, however "
            "narrow the map makes the gap (stereo smears a jamb's edge inward, into the opening)."
        ),
    )
    clearance_below_m: float = Field(
        default=0.0,
        ge=0.0,
        le=3.0,
        description=(
            "Keep at least this much height between the vehicle's centre and the highest point "
            "remembered below it (seen within duration_s, not seen past since, within keep_out_m "
            "horizontally, above command.min_altitude_m over the take-off point, so not the ground): "
            "nearer, every setpoint climbs at 2/s times the shortfall (at most "
            "command.max_altitude_hold_speed_m_s) while the up region is open, metres; 0 = off (the "
            "default). The camera cannot see what is under the vehicle, and an autopilot sags while it "
            "brakes or turns hard, a few tenths of a metre over a low wall's top."
        ),
    )
    height_band_m: float = Field(
        default=0.4,
        gt=0.0,
        le=5.0,
        description=(
            "Only points within this much of the vehicle's altitude guard it, metres (the ground and "
            "what is overhead are the regions' business)."
        ),
    )

    trust_cell_m: float = Field(
        default=0.3,
        gt=0.0,
        le=2.0,
        description=(
            "Trust is kept per cube of this side, metres: a point is trusted when its cube has been "
            "seen as trust_baseline_m or trust_persist_s say."
        ),
    )
    trust_baseline_m: float = Field(
        default=0.3,
        ge=0.0,
        le=10.0,
        description=(
            "A remembered point is trusted once its cube has been seen from two camera positions at "
            "least this far apart, metres (0 = from any two frames). Only trusted points open or close "
            "a detour's direction (to push or bound a gap, push_baseline_m): a false match moves with "
            "the view where a surface does not, and a false point the vehicle could fly through would "
            "make a false gap."
        ),
    )
    push_baseline_m: float = Field(
        default=0.5,
        ge=0.0,
        le=10.0,
        description=(
            "Only a point whose trust_cell_m cube has been seen from two camera positions at least this "
            "far apart pushes the vehicle away (guard_gain_per_s) or bounds a gap to centre in, metres; "
            "0 = every trusted point does. A false match that follows the vehicle (StereoBM's alias on "
            "a fence's bars, a smudge on the lens) lands in one cube only while the vehicle moves less "
            "than about the cube's diagonal, and persists; trusted by persistence alone, it would push "
            "the vehicle into the wall across from it. At least trust_cell_m × 1.5 (a cube's horizontal "
            "diagonal, and a little)."
        ),
    )
    trust_persist_s: float = Field(
        default=0.6,
        ge=0.0,
        le=60.0,
        description=(
            "...or once it has been seen in trust_min_frames frames spanning at least this long, "
            "seconds (a vehicle turning in place sees from one position)."
        ),
    )
    trust_min_frames: int = Field(
        default=4,
        ge=1,
        le=100,
        description="Frames its cube must be seen in to be trusted by persistence (trust_persist_s).",
    )

    @model_validator(mode="after")
    def _push_beyond_a_cube(self) -> MemoryConfig:
        if 0.0 < self.push_baseline_m < PUSH_BASELINE_MIN_CELLS * self.trust_cell_m:
            raise ValueError(
                f"push_baseline_m ({self.push_baseline_m} m) must be 0 or at least "
                f"{PUSH_BASELINE_MIN_CELLS * self.trust_cell_m:g} m ({PUSH_BASELINE_MIN_CELLS} × trust_cell_m): "
                f"a false match that follows the vehicle stays in one cube while the vehicle moves up to "
                f"the cube's diagonal, and would push"
            )
        return self

    @field_validator("confirm_frames")
    @classmethod
    def _odd_confirm(cls, v: int) -> int:
        if v % 2 == 0:
            raise ValueError(f"confirm_frames must be odd, got {v}")
        return v
