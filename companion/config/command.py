"""Config of decision -> velocity setpoint: speeds, rates, course hold, brake hold, watchdog (``[command]``)."""

from __future__ import annotations

from pydantic import Field, model_validator

from companion.config._base import StrictModel
from companion.config.regions import RegionName


class CommandConfig(StrictModel):
    """How a decision becomes a body-frame velocity setpoint, and when frames are too old to trust."""

    cruise_speed_m_s: float = Field(
        default=0.7,
        ge=0.0,
        le=15.0,
        description=(
            "Forward speed when the way is clear, m/s (paper: constant). A multicopter with PX4's "
            "default velocity response (~0.85 s lag) needs the margin 0.7 m/s leaves; raise it only on "
            "a vehicle tuned to respond faster."
        ),
    )
    avoid_speed_fraction: float = Field(
        default=0.1,
        ge=0.0,
        le=1.0,
        description=(
            "Forward speed while the centre is fully near, as a share of the cruise speed, blended "
            "linearly with the centre's near degree. 1 = the paper's constant speed; simulator-tuned "
            "0.1 leaves time to turn before the obstacle."
        ),
    )
    avoid_speed_regions: list[RegionName] = Field(
        default=[],
        max_length=9,
        description=(
            "Regions whose 'near' degree also slows the vehicle (the largest of them and the centre's "
            "drives the avoid_speed_fraction blend); [] = the centre only (the default). [\"left\", "
            "\"right\"] slows while a box passes beside the vehicle: it raises the clearances but costs "
            "time in corridors."
        ),
    )
    max_yaw_rate_deg_s: float = Field(
        default=90.0,
        ge=0.0,
        le=360.0,
        description=(
            "Yaw rate commanded at fuzzy yaw ±1, deg/s (the default output terms defuzzify to at most "
            "±0.63, so 90 gives up to 57 deg/s)."
        ),
    )
    max_vertical_speed_m_s: float = Field(
        default=0.8, ge=0.0, le=5.0, description="Vertical speed commanded at fuzzy pitch ±1, m/s."
    )
    stale_frame_timeout_s: float = Field(
        default=0.5,
        gt=0.0,
        le=10.0,
        description="A newest frame older than this gives a zero-velocity setpoint (state degraded), seconds.",
    )
    failsafe_timeout_s: float = Field(
        default=5.0,
        gt=0.0,
        le=120.0,
        description="A newest frame older than this makes the service leave offboard to Hold (state failsafe), seconds.",
    )
    # Course hold (goal seeking). Not in the paper, whose controller only avoids: a vehicle that yawed
    # away never came back. Applies only when the caller passes the errors to setpoint_for.
    heading_hold_gain_per_s: float = Field(
        default=0.8,
        ge=0.0,
        le=10.0,
        description=(
            "Course hold: on a CLEAR decision, yaw back toward the heading at engagement at this rate "
            "per radian of heading error, 1/s (0 = off: the paper's behaviour)."
        ),
    )
    max_heading_hold_rate_deg_s: float = Field(
        default=20.0, ge=0.0, le=360.0, description="Course hold: largest yaw rate it commands, deg/s."
    )
    turn_back_after_clear_s: float = Field(
        default=3.0,
        ge=0.0,
        le=600.0,
        description=(
            "Course hold, turning back: once the decisions have been CLEAR this long, seconds, turning "
            "or not, turning back acts without waiting for hold_resume_delay_s of CLEAR without "
            "turning. A side rule along a wall keeps a CLEAR decision turning for as long as the wall "
            "reads partly near, and can carry a vehicle round and back along the course at cruise."
        ),
    )
    turn_back_angle_deg: float = Field(
        default=100.0,
        ge=0.0,
        le=180.0,
        description=(
            "Course hold, turning back: facing more than this many degrees away from the heading course "
            "hold aims at (line included), on a CLEAR decision past hold_resume_delay_s, the vehicle "
            "stops going forward and turns toward the course in place at max_heading_hold_rate_deg_s, "
            "whatever its side regions read (a turn in place moves it toward nothing, and the obstacle "
            "memory guards its flanks); 180 = off. A vehicle turned around in a corridor would "
            "otherwise fly back out of it: the walls beside it read nearer than hold_clear_depth_m, so "
            "course hold never turns it."
        ),
    )
    line_hold_gain_per_m: float = Field(
        default=0.5,
        ge=0.0,
        le=10.0,
        description=(
            "Course hold, line: also steer back to the line through the engagement point along the "
            "engagement heading: the heading aimed at turns toward the line by atan(this × cross-track "
            "distance), per metre (0 = off: hold the heading only, and drift sideways with the "
            "autopilot's heading-estimate error)."
        ),
    )
    max_line_hold_angle_deg: float = Field(
        default=30.0, ge=0.0, le=89.0, description="Course hold, line: the largest turn toward the line, degrees."
    )
    line_hold_lateral_gain_per_s: float = Field(
        default=1.0,
        ge=0.0,
        le=10.0,
        description=(
            "Course hold, line, sideways: also fly sideways back toward the line at this speed per "
            "metre of cross-track distance, 1/s (0 = off: the paper never flies sideways). Turning back "
            "takes seconds; a multicopter that drifts sideways (wind, or a velocity-estimate error of a "
            "few tenths of a m/s) is brought back at once, and the camera keeps looking ahead."
        ),
    )
    max_line_hold_lateral_speed_m_s: float = Field(
        default=0.3, ge=0.0, le=2.0, description="Course hold, line, sideways: the largest sideways speed it commands, m/s."
    )
    standoff_depth_m: float = Field(
        default=0.0,
        ge=0.0,
        le=5.0,
        description=(
            "Stand-off: a middle-row region (left, center, right) that reads nearer than this, metres, "
            "pushes the vehicle away from it, whatever the decision and whatever the vehicle believes "
            "its velocity is (0 = off, the default). The autopilot holds the velocity its estimate "
            "reads, and an estimate off by a few tenths of a m/s carries the vehicle on into a wall it "
            "sees; the measured depth is the one thing that knows. Unknown pushes nothing. Off by "
            "default: a false near reading on a plain wall backs the vehicle away blind."
        ),
    )
    standoff_gain_per_s: float = Field(
        default=3.0,
        ge=0.0,
        le=10.0,
        description=(
            "Stand-off: the push away, m/s per metre nearer than standoff_depth_m, away from the "
            "region's direction (straight back for the center, 30° off it for a side)."
        ),
    )
    max_standoff_speed_m_s: float = Field(
        default=0.7, ge=0.0, le=2.0, description="Stand-off: the largest push it commands, m/s."
    )
    line_hold_lateral_clear_depth_m: float = Field(
        default=1.0,
        ge=0.0,
        le=50.0,
        description=(
            "Course hold, line, sideways: only toward a side whose region (left, right) is at least this "
            "deep, metres; unknown blocks it. Nearer than hold_clear_depth_m, because a slow sideways "
            "step is not a turn toward the side: approaching a wall with a doorway, both sides read the "
            "wall ~2 m ahead and the vehicle must still line up with the gap."
        ),
    )
    line_hold_lateral_max_aim_error_deg: float = Field(
        default=15.0,
        ge=1.0,
        le=180.0,
        description=(
            "Course hold, line, sideways: the sideways speed tapers to 0 as the heading the course hold "
            "aims at lies this far from the heading now, degrees (180 = no taper). A vehicle still "
            "turning toward a side would carry its body, sideways, into what the camera has not seen "
            "yet (the left image's unmatched strip, say)."
        ),
    )
    sideways_clear_depth_m: float = Field(
        default=0.0,
        ge=0.0,
        le=50.0,
        description=(
            "The obstacle memory's push, lean and slide past a point, and gap centering, move the "
            "vehicle sideways toward a side whose region (left, right) reads nearer than this, metres, "
            "at no more than (depth - half of this) per second, and not at all from half of it in or "
            "toward a side that cannot be read; 0 = off, the default. The memory places what it saw "
            "with the autopilot's position estimate, which wanders by tenths of a metre; the camera "
            "does not. A limit that shrinks with the room, not a ban: in a dead end both sides read "
            "near, and the push away from the wall the vehicle drifts toward keeps it off it."
        ),
    )
    altitude_hold_gain_per_s: float = Field(
        default=0.5,
        ge=0.0,
        le=10.0,
        description=(
            "Course hold: on a CLEAR decision, climb or descend back toward the altitude at engagement "
            "at this speed per metre of altitude error, 1/s (0 = off)."
        ),
    )
    altitude_hold_on_avoid: bool = Field(
        default=False,
        description=(
            "Course hold's altitude hold acts on AVOID decisions too, where it does not fight the "
            "decision's own climb or descent (a descent only over nothing remembered below). Off by "
            "default: it reaches doors nearer the engaged altitude but pulls the vehicle back toward a "
            "jamb's height band while it avoids."
        ),
    )
    max_altitude_hold_speed_m_s: float = Field(
        default=0.3, ge=0.0, le=5.0, description="Course hold: largest vertical speed it commands, m/s."
    )
    hold_resume_delay_s: float = Field(
        default=1.5,
        ge=0.0,
        le=60.0,
        description=(
            "Course hold resumes only after the decisions have been CLEAR and straight this long, "
            "seconds: an obstacle just passed is beside or below the vehicle, out of the camera's view. "
            "The heading part (and turning back) counts decisions that do not turn, the altitude part "
            "ones that neither turn nor climb (a slight climb away from the ground must not keep a "
            "vehicle facing away from its course from turning back). A climb back up to the engaged "
            "altitude does not wait (only the overhead memory, hold_resume_distance_m, stops it): PX4 "
            "sags 0.2-0.3 m as it speeds up."
        ),
    )
    hold_resume_distance_m: float = Field(
        default=1.5,
        ge=0.0,
        le=50.0,
        description=(
            "Overhead memory, metres (0 = off): no climb at all (by a rule or by course hold) until the "
            "vehicle has flown this far (horizontally) since the up region last read nearer than "
            "hold_clear_depth_m, and course hold's descent also waits this far after the decisions "
            "turned CLEAR and straight. The camera cannot see straight up: under a block, a climb (or a "
            "hold that waited only for a time) flies the vehicle into the block's rear edge."
        ),
    )
    min_altitude_m: float = Field(
        default=0.5,
        ge=0.0,
        le=100.0,
        description=(
            "Floor: no setpoint descends below this altitude above the autopilot's local origin (where "
            "its position estimate began: normally the take-off point on the ground), metres; 0 = off. "
            "Descending, the down speed is capped at 2/s times the height left above it, the measured "
            "sink over motion_brake_lag_s counted as height already lost, so the vehicle's lag does not "
            "carry it through; below it (PX4 drifts vertically under a zero vertical speed), every "
            "fresh setpoint climbs back at 2/s times the shortfall unless the up region measures nearer "
            "than 1 m (an unknown up region does not stop the climb, or a vehicle in front of a plain "
            "wall would sink to the ground). Elsewhere unknown counts as near, and a plain ceiling or "
            "sky the up regions cannot read would send the vehicle down. Above ground that rises from "
            "the take-off point it does not protect: the down regions do."
        ),
    )
    brake_hold_gain_per_s: float = Field(
        default=1.0,
        ge=0.0,
        le=10.0,
        description=(
            "Brake position and heading hold: while braking, command a velocity back to where the brake "
            "began, this gain times the distance, and a yaw rate back to the heading it began with, "
            "this gain times the angle (capped at max_heading_hold_rate_deg_s), per second (0 = plain "
            "zero velocity and yaw rate). Zero velocity lets a real multicopter drift with its "
            "velocity-estimate error, into the obstacle within seconds, and PX4 keeps turning ~0.4 s "
            "after a zero yaw rate, which can open a false escape; holding both does not."
        ),
    )
    brake_hold_max_speed_m_s: float = Field(
        default=0.3, ge=0.0, le=2.0, description="Brake position hold: the largest speed it commands, m/s."
    )
    no_progress_timeout_s: float = Field(
        default=20.0,
        ge=0.0,
        le=600.0,
        description=(
            "Progress watchdog, seconds (0 = off): engaged with course hold, when the vehicle has not got "
            "progress_step_m farther along the course (the line from where it was engaged, along the "
            "heading it had then) for this long, the service stops trying: it holds position (as a "
            "brake does), its state becomes paused with the reason, and it waits for the pilot (resume "
            "tries again, or take over). A vehicle circling in front of an obstacle it cannot get past, "
            "or following a wall away from the only opening, only spends battery near obstacles. The "
            "local planner's watchdog is planner.no_progress_distance_m."
        ),
    )
    progress_step_m: float = Field(
        default=1.0,
        gt=0.0,
        le=50.0,
        description=(
            "Progress watchdog: how much farther along the course (metres) counts as progress and "
            "restarts no_progress_timeout_s."
        ),
    )
    regress_distance_m: float = Field(
        default=1.5,
        ge=0.0,
        le=50.0,
        description=(
            "Progress watchdog, regress: a vehicle this much farther from its goal (along the course, "
            "for the course at engagement) than the nearest it has been is flying back; after "
            "regress_timeout_s of that it holds as for no progress, metres (0 = off). A vehicle that "
            "turned round at a dead end's closed end would otherwise fly back out of the channel until "
            "the no-progress watchdog stopped it. The rule stack's only: the local planner holds its "
            "own dead ends, and its way round can lead away from the goal."
        ),
    )
    regress_timeout_s: float = Field(
        default=3.0,
        ge=0.0,
        le=600.0,
        description="Progress watchdog, regress: how long flying back may last before the hold, seconds.",
    )
    goal_radius_m: float = Field(
        default=0.5,
        gt=0.0,
        le=50.0,
        description=(
            "A goal point counts as reached within this horizontal distance, metres: the run ends "
            "with a position hold there and the state paused ('goal reached')."
        ),
    )
    hold_clear_depth_m: float = Field(
        default=2.25,
        ge=0.0,
        le=50.0,
        description=(
            "Course hold turns (climbs, descends) toward a side only while that side's region (left, "
            "right, up, down) is at least this deep, metres; unknown blocks it."
        ),
    )

    motion_brake_clearance_m: float = Field(
        default=0.5,
        ge=0.0,
        le=5.0,
        description=(
            "The camera's check on where the vehicle is actually going: where its measured velocity "
            "points into the view's middle row (the centre region within 15 degrees of the nose, left "
            "and right to 45), it must be able to stop short of what that region reads, less this, "
            "metres, within motion_brake_lag_s; faster, and the setpoint loses its own motion that way "
            "and leans against the excess (0 = off). The fuzzy controller judges the way along the "
            "heading; a vehicle turning away from a cabinet still flies its old course, into what its "
            "side region reads. Whatever else a setpoint carries (the memory's push, a hold's pull "
            "back) never goes forward faster than the centre region allows by the same rule."
        ),
    )
    motion_brake_lag_s: float = Field(
        default=0.85,
        gt=0.0,
        le=5.0,
        description=(
            "How long the autopilot takes to follow a new velocity setpoint, seconds (a first-order "
            "lag's time constant; PX4 SIH ~0.85 s): the motion brake allows a closing speed of "
            "(range - motion_brake_clearance_m) / this, and the floor (min_altitude_m) counts a sink "
            "over this as height already lost."
        ),
    )
    unseen_closing_range_m: float = Field(
        default=1.5,
        ge=0.0,
        le=10.0,
        description=(
            "The camera's check on the velocity estimate: while the centre region reads nearer than "
            "this, the rate its depth falls less the forward speed the vehicle reports (the forward "
            "drift the autopilot's estimate does not show) comes off the setpoint, metres (0 = off). "
            "The depth of a static point falls at exactly the forward speed; PX4 flies its velocity "
            "estimate, and an estimate a few tenths of a m/s off would carry the vehicle into what it "
            "sees while every setpoint slows it."
        ),
    )
    unseen_closing_window_s: float = Field(
        default=0.4,
        gt=0.0,
        le=2.0,
        description="The check's window: the centre depth's fall is fitted over this many seconds of frames.",
    )
    unseen_closing_min_m_s: float = Field(
        default=0.15,
        ge=0.0,
        le=2.0,
        description=(
            "Unseen closing below this is left alone (stereo noise, the LUT's scale), and the centre's "
            "depth must itself fall at least this fast (backing off a surface whose depth does not "
            "rise is no danger), m/s."
        ),
    )
    unseen_closing_max_yaw_rate_deg_s: float = Field(
        default=20.0,
        gt=0.0,
        le=180.0,
        description=(
            "The check holds only while the vehicle turns slower than this, deg/s: turning sweeps the "
            "centre region over other surfaces, whose depths say nothing of the motion."
        ),
    )
    unseen_closing_max_step_m: float = Field(
        default=0.1,
        gt=0.0,
        le=5.0,
        description=(
            "A frame whose centre depth moved more than this beyond what the reported speed explains "
            "starts the window again (another surface came into the region), metres."
        ),
    )
    unseen_closing_max_fit_error_m: float = Field(
        default=0.03,
        gt=0.0,
        le=1.0,
        description=(
            "The check holds only while the centre's depths lie within this of a straight line in "
            "time (rms, metres): a surface coming steadily nearer, not a see-through fence or a plain "
            "wall whose matches come and go."
        ),
    )
    unseen_closing_hold_s: float = Field(
        default=1.0,
        ge=0.0,
        le=10.0,
        description=(
            "Once measured, the unseen drift is countered this long after the check stops holding "
            "(an escape turning faster than unseen_closing_max_yaw_rate_deg_s), along the heading it "
            "was measured on, seconds: the estimate's error outlasts the turn."
        ),
    )
    max_unseen_closing_counter_m_s: float = Field(
        default=0.5,
        ge=0.0,
        le=2.0,
        description="The most the check takes off the setpoint, m/s.",
    )

    track_velocity_window_s: float = Field(
        default=0.5,
        ge=0.0,
        le=3.0,
        description=(
            "The velocity the memory's guard and the motion brake act on: the reported velocity plus "
            "the motion of the reported position it does not explain, over this window, seconds (0 = "
            "the reported velocity alone, and no track counter). The remembered points and the course "
            "live in the reported position, and an autopilot's position can move a tenth of a m/s "
            "otherwise than the velocity it reports."
        ),
    )
    track_counter_fraction: float = Field(
        default=1.0,
        ge=0.0,
        le=1.0,
        description=(
            "This fraction of that unexplained motion (track_velocity_window_s) comes off a fresh "
            "frame's setpoint, in the body frame, so that the vehicle moves in its reported position as "
            "asked, sideways too, where the camera's own check (unseen_closing_range_m) sees only "
            "motion toward the centre (0 = none); forward it adds nothing while the frame brakes or the "
            "centre cannot be read, never more than the vehicle can stop short of what the centre "
            "reads, and never past cruise_speed_m_s (the horizontal speed it leaves stays within the "
            "cruise). A remembered point on the counter's path slides the counter alone, never the "
            "guard's push away from a wall (sliding both would cancel the push)."
        ),
    )
    max_track_counter_m_s: float = Field(
        default=0.6,
        ge=0.0,
        le=2.0,
        description=(
            "The most unexplained motion counted, m/s (the guard's velocity and the counter); a "
            "position jumping 0.25 m in one sample beyond what the velocity explains is an "
            "estimator's reset, and the window starts again after it."
        ),
    )

    @model_validator(mode="after")
    def _order(self) -> CommandConfig:
        if self.failsafe_timeout_s <= self.stale_frame_timeout_s:
            raise ValueError(
                f"failsafe_timeout_s ({self.failsafe_timeout_s}) must exceed stale_frame_timeout_s "
                f"({self.stale_frame_timeout_s})"
            )
        return self
