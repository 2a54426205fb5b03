"""Config of the detour layer (``[detour]``): a way round an obstacle the reactive controller cannot pass."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from companion.config._base import StrictModel


class DetourConfig(StrictModel):
    """The detour layer, above the fuzzy controller (:mod:`companion.core.detour`). When the way ahead
    stays blocked (the controller brakes), or the vehicle gets no nearer its goal, it turns in place to
    look around (filling the obstacle memory), picks from the memory's trusted points the free
    direction that best leads toward the goal (a polar histogram of the vehicle's surroundings, as
    VFH+ and PX4-Avoidance's local planner do), flies that way and hands back to course hold once the
    goal direction is free. No free direction toward the goal: a hold, reported as a dead end. The
    fuzzy controller stays the reactive layer: a detour only turns the vehicle and slows it, never
    flies it where the controller would not. Not in the paper."""

    trigger_after_s: float = Field(
        default=0.8,
        ge=0.0,
        le=30.0,
        description=(
            "Start a detour once the controller has braked (the way ahead blocked, no escape) this long "
            "without a break, seconds; 0 = the detour layer is off (the reactive controller and course "
            "hold alone). Short, since a pilot calls a vehicle stopped for 3 s held."
        ),
    )
    trigger_no_progress_s: float = Field(
        default=10.0,
        ge=0.0,
        le=600.0,
        description=(
            "Also start a detour when the vehicle has got no command.progress_step_m nearer its goal "
            "for this long (circling in front of a box: the avoidance steers round it, course hold "
            "back into it), seconds; 0 = only on a brake. Once per stall: the progress watchdog "
            "(command.no_progress_timeout_s) still ends a detour that gets nowhere."
        ),
    )
    trigger_away_deg: float = Field(
        default=110.0,
        ge=0.0,
        le=180.0,
        description=(
            "Also start a detour when the controller, steering round something, has turned the vehicle "
            "this many degrees away from the goal direction (it circles in front of a box), degrees; "
            "0 = off."
        ),
    )
    trigger_on_regress: bool = Field(
        default=True,
        description=(
            "Also start a detour as soon as the vehicle has flown command.regress_distance_m back from "
            "the nearest it has been to its goal, before the progress watchdog's regress hold "
            "(command.regress_timeout_s later): once per stall, as for trigger_no_progress_s. Avoiding "
            "along a wall can turn the vehicle away from the goal and fly it back; a detour then finds "
            "the way round before the watchdog holds."
        ),
    )
    passing_away_deg: float = Field(
        default=60.0,
        ge=0.0,
        le=180.0,
        description=(
            "No detour under way, facing at least this many degrees away from the goal direction on a "
            "decision that is no brake (the controller steering along a wall, across a door's mouth, "
            "round a fence's end), look at the map in passing: the goal direction free, or an opening "
            "to line up with it, hands back there as a detour's choice would, degrees; 0 = off. Flying "
            "across a door's mouth parallel to the wall, the side rules keep turning the vehicle along "
            "it, so course hold alone would never turn it in."
        ),
    )
    passing_interval_s: float = Field(
        default=0.5,
        gt=0.0,
        le=60.0,
        description="The passing look (passing_away_deg) looks at the map at most this often, seconds.",
    )
    passing_spacing_m: float = Field(
        default=1.0,
        ge=0.0,
        le=100.0,
        description=(
            "After a passing look has handed back, the next one waits until the vehicle is this far "
            "from where it was, metres: turned to a goal direction the controller turns it away from "
            "again, it does not turn back and forth on the spot."
        ),
    )
    passing_turn_back: bool = Field(
        default=True,
        description=(
            "The passing look (passing_away_deg) with the goal direction closed: when the side the "
            "vehicle heads along opens no way to the goal within lookahead_m and the other side does "
            "(and has a free direction), begin a detour round that side there, rather than follow a "
            "fence into a pocket that a wall closes."
        ),
    )
    scan_half_angle_deg: float = Field(
        default=90.0,
        ge=0.0,
        le=180.0,
        description=(
            "The look round: turn in place to this many degrees either side of the goal direction, so "
            "that the camera (about ±45°) fills the memory out to scan_half_angle_deg + 45° round the "
            "goal, degrees. It first turns to the side the memory does not favour and ends facing the "
            "one it does. No look round when the way round is already in view, or seen "
            "(no_look_round_step_m)."
        ),
    )
    no_look_round_step_m: float = Field(
        default=1.5,
        ge=0.0,
        le=10.0,
        description=(
            "No look round when the memory already shows, on the side it favours, a sideways step "
            "of at most this many metres (square to the goal direction) after which the way to the "
            "goal is free: the end of a box seen on the approach. The detour chooses at once and "
            "turns to face each direction before it flies it. Metres; 0 = always look round. Keep "
            "it within what the camera saw beside the obstacle on the way in (about the brake "
            "distance): farther out the map has not looked, so unseen space reads free (the detour "
            "course's wall: steps of 2-3 m that were not there)."
        ),
    )
    turn_rate_deg_s: float = Field(
        default=50.0,
        gt=0.0,
        le=360.0,
        description=(
            "Yaw rate of the look round and of a detour's turns in place, deg/s (within "
            "envelope.max_yaw_rate_deg_s): slow enough that each direction stays in view for the "
            "memory to trust what it saw there (memory.trust_persist_s)."
        ),
    )
    scan_timeout_s: float = Field(
        default=15.0,
        gt=0.0,
        le=120.0,
        description="A look round ends after this long, wherever it has got to, seconds.",
    )
    max_angle_deg: float = Field(
        default=100.0,
        ge=10.0,
        le=180.0,
        description=(
            "Only directions within this many degrees of the goal direction count as leading toward "
            "it; none free: a dead end. Above 90 allows a little back-tracking round a corner."
        ),
    )
    cone_from_start: bool | Literal["auto"] = Field(
        default="auto",
        description=(
            "Directions within max_angle_deg of the goal direction as it was when the detour began "
            "count as leading toward the goal too (false: only of the goal direction now; auto: true "
            "with the semi-global matcher, as memory.block_erode_px). Flying along a wall toward its "
            "end, the bearing to a goal point turns away from the way the vehicle flies, and the "
            "directions left within max_angle_deg of it close in on the wall; the start's direction "
            "keeps the opening ahead. With StereoBM's sparse map it sends detours down the wrong side, "
            "so auto leaves it off there."
        ),
    )
    cone_from_start_max_m: float = Field(
        default=4.0,
        gt=0.0,
        le=50.0,
        description=(
            "With cone_from_start, the start's directions count only while the vehicle is within this "
            "far (horizontally) of where the detour began, metres; farther, only those within "
            "max_angle_deg of the goal direction now, so a side with no opening can end as a dead end "
            "and the detour switch sides (unbounded, a wall's own direction stays within the start's "
            "cone and the vehicle follows it on and on)."
        ),
    )
    either_side_within_deg: float = Field(
        default=15.0,
        ge=0.0,
        le=90.0,
        description=(
            "A detour keeps to the side of the goal direction it chose, but a free direction within "
            "this many degrees of the goal direction may be taken on either side, degrees (0 = only the "
            "side chosen). Flying along a wall, an opening just past the goal direction is the way "
            "through, not a switch of sides."
        ),
    )
    sector_deg: float = Field(
        default=5.0,
        ge=1.0,
        le=30.0,
        description="Angular resolution of the polar histogram of directions, degrees.",
    )
    radius_m: float = Field(
        default=2.5,
        gt=0.5,
        le=20.0,
        description=(
            "The goal direction counts as free, and a detour hands back to course hold, when its path "
            "keeps clearance_m from every trusted remembered point this far (or all the way to a "
            "nearer goal point), metres."
        ),
    )
    min_free_m: float = Field(
        default=1.5,
        gt=0.0,
        le=20.0,
        description=(
            "A detour's direction must keep clearance_m from every trusted point for at least this "
            "far, metres; no such direction within max_angle_deg of the goal: a dead end (a hold, "
            "reported). A corridor leaves no straight 2.5 m path round a box, but a bend of them."
        ),
    )
    clearance_m: float = Field(
        default=0.55,
        gt=0.0,
        le=5.0,
        description=(
            "A free direction's path keeps at least this far from every trusted point, metres: the "
            "0.25 m vehicle plus 0.3 m. A gap must be twice this wide to be chosen."
        ),
    )
    squeeze_clearance_m: float = Field(
        default=0.4,
        gt=0.0,
        le=5.0,
        description=(
            "Along a detour, on the side chosen, when no direction keeps clearance_m (an opening just "
            "wide enough, seen with its jambs' depth noise), one keeping this much still goes on, and "
            "the goal direction keeping this much is enough to hand back, and after a look round an "
            "opening the map closes at both ends whose path keeps this much chooses its side "
            "(lookahead_m), metres: the 0.25 m vehicle plus 0.15 m (the controller and the guard "
            "still act)."
        ),
    )
    line_up_max_m: float = Field(
        default=0.5,
        ge=0.0,
        le=2.0,
        description=(
            "Lining up with an opening: when the goal direction is not free from where the vehicle is, "
            "but the path parallel to it is (with line_up_clearance_m) from an opening's middle at most "
            "this far to one side (free offsets with points on both sides within twice this: a door, "
            "not a box's free side), the vehicle slides there, facing the goal, and hands back, metres "
            "(0 = off). At a door just wide enough, the map's jambs, smeared inward, leave no free "
            "direction from anywhere but its middle."
        ),
    )
    line_up_clearance_m: float = Field(
        default=0.3,
        gt=0.0,
        le=5.0,
        description=(
            "Lining up with an opening: the parallel path, and the slide to it, keep at least this "
            "far from every trusted point, metres: the 0.25 m vehicle plus 0.05 m. After the "
            "hand-back, course hold's gap centering, the guard and the controller's brake act on "
            "the way through."
        ),
    )
    preferred_clearance_m: float = Field(
        default=0.8,
        gt=0.0,
        le=5.0,
        description=(
            "Directions that pass nearer than this to a trusted point cost extra (prefer_clear_cost_deg), "
            "metres, so that a detour along a wall keeps off it."
        ),
    )
    prefer_clear_cost_deg: float = Field(
        default=20.0,
        ge=0.0,
        le=180.0,
        description="What a direction nearer than preferred_clearance_m costs, in degrees off the goal.",
    )
    through_squeeze: bool | Literal["auto"] = Field(
        default="auto",
        description=(
            "Choosing a side: after a step square to the goal direction, the way to the goal counts as "
            "open when its path keeps squeeze_clearance_m from every trusted point, not clearance_m "
            "(false: clearance_m; auto: true with the semi-global matcher, as memory.block_erode_px). "
            "The SGM smears an opening's jambs inward on the map, so an opening can read too narrow for "
            "clearance_m on both sides of its path and the detour would go round the wall's far side. "
            "StereoBM's map is sparse and a hole in a mapped wall would read as a way through, so auto "
            "leaves it off there."
        ),
    )
    lookahead_m: float = Field(
        default=4.0,
        ge=0.0,
        le=20.0,
        description=(
            "Choosing a side (left or right of the goal): the side where a step square to the goal "
            "direction, on the map's free space, opens the way to the goal soonest is the shorter way "
            "round (an opening, or the end of the wall); steps up to this long are tried (at most 0.8 "
            "memory.map_depth_m), metres; 0 = choose by the free direction nearest the goal only. After "
            "a look round, the middle of an opening the map closes at both ends (free with "
            "squeeze_clearance_m, found in 5 cm steps, on a side with a free direction) counts as such "
            "a step too: a wall's end where the look stopped measuring it is unseen, not free."
        ),
    )
    speed_m_s: float = Field(
        default=0.5,
        ge=0.0,
        le=15.0,
        description=(
            "Forward speed along a detour, m/s (at most command.cruise_speed_m_s and "
            "envelope.max_horizontal_speed_m_s; the controller's own slowing still applies)."
        ),
    )
    turn_in_place_deg: float = Field(
        default=25.0,
        ge=1.0,
        le=180.0,
        description=(
            "Facing more than this many degrees away from the detour's direction, the vehicle stops "
            "and turns in place (holding its position), so the camera looks where it is going first."
        ),
    )
    max_detours_without_progress: int = Field(
        default=3,
        ge=1,
        le=100,
        description=(
            "At most this many detours begin while the vehicle gets no command.progress_step_m nearer "
            "its goal; then the progress watchdog (whose clock stands still during a detour) decides."
        ),
    )
    max_distance_m: float = Field(
        default=10.0,
        gt=0.0,
        le=200.0,
        description=(
            "A detour that has taken the vehicle this far (horizontally) from where it began without "
            "the goal direction coming free ends in a dead-end hold, metres."
        ),
    )
    max_time_s: float = Field(
        default=45.0,
        gt=0.0,
        le=600.0,
        description="A detour that has lasted this long without handing back ends in a dead-end hold, seconds.",
    )
    replan_interval_s: float = Field(
        default=0.4,
        gt=0.0,
        le=10.0,
        description="How often a detour looks again at the memory for its direction, seconds.",
    )
    visited_spacing_m: float = Field(
        default=0.3,
        gt=0.0,
        le=5.0,
        description="The flight's trail (where the vehicle has been) keeps one point per this many metres.",
    )
    visited_clearance_m: float = Field(
        default=0.5,
        gt=0.0,
        le=5.0,
        description=(
            "A direction whose path passes this near a point of the trail older than visited_age_s "
            "leads back where the vehicle has been, metres: it costs visited_cost_deg."
        ),
    )
    visited_age_s: float = Field(
        default=5.0, ge=0.0, le=600.0, description="Trail points younger than this do not count as visited, seconds."
    )
    visited_cost_deg: float = Field(
        default=60.0,
        ge=0.0,
        le=360.0,
        description="What a direction back where the vehicle has been costs, in degrees off the goal.",
    )
    side_memory_m: float = Field(
        default=4.0,
        ge=0.0,
        le=100.0,
        description=(
            "A new detour that starts within this distance of where the last one ended goes round the "
            "same side (it does not swing between two detours), metres; 0 = every detour chooses anew."
        ),
    )

    @property
    def on(self) -> bool:
        """Whether the detour layer is on (``trigger_after_s`` > 0)."""
        return self.trigger_after_s > 0.0

    @model_validator(mode="after")
    def _order(self) -> DetourConfig:
        if self.preferred_clearance_m < self.clearance_m:
            raise ValueError(
                f"preferred_clearance_m ({self.preferred_clearance_m}) must be at least clearance_m ({self.clearance_m})"
            )
        if self.squeeze_clearance_m > self.clearance_m:
            raise ValueError(
                f"squeeze_clearance_m ({self.squeeze_clearance_m}) must be at most clearance_m ({self.clearance_m})"
            )
        if self.line_up_clearance_m > self.squeeze_clearance_m:
            raise ValueError(
                f"line_up_clearance_m ({self.line_up_clearance_m}) must be at most squeeze_clearance_m "
                f"({self.squeeze_clearance_m})"
            )
        return self
