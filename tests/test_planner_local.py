"""The local planner: its map (rays clear, unknown is near), the speed law, the cost's choice, the
dead end held, the fuzzy controller as a term and as the whole policy, and the safety chain."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import pytest

from companion.config import CompanionConfig
from companion.config.controller import ControllerConfig
from companion.config.planner import PlannerConfig
from companion.core.fuzzy.avoidance import AvoidanceController
from companion.core.geometry import StereoGeometry
from companion.core.goal import GoalSpec
from companion.core.planner.local import (
    ALTITUDE_RETURN_S,
    LOOKED_FROM_M,
    TRANSITIONS,
    LocalPlanner,
    Mode,
    Plan,
    Snapshot,
    speed_law,
    stopping_m,
)
from companion.core.planner.localmap import LocalMap
from companion.core.planner.paths import floor_bent_lengths, predicted_paths
from companion.core.planner.safety import (
    CHAIN,
    SafetyContext,
    apply_chain,
    brake_hold,
    counter_unexplained,
    envelope,
    floor_ceiling,
    keep_off,
    speed_law_limit,
    stale_to_zero,
    trace_chain,
)
from companion.core.planner.stack import LocalStack
from companion.core.pose import Pose
from companion.core.supervisor import Engage, Resume, State, Supervisor, SupervisorConfig
from companion.core.types import ZERO_SETPOINT, Decision, DecisionKind, VelocitySetpoint
from companion.interfaces import VehicleState

GEOM = StereoGeometry.ideal(336, 188, 90.0, 0.12)
BLOCK_PX = 4
BLOCKS = (47, 84)


def _wall_blocks(depth_m: float, cols: slice = slice(None)) -> np.ndarray:
    """A block image of a wall across the view at ``depth_m`` (px disparity), in columns ``cols``."""
    b = np.full(BLOCKS, np.nan, dtype=np.float32)
    b[:, cols] = GEOM.focal_baseline_px_m / depth_m
    return b


def _map() -> LocalMap:
    return LocalMap(voxel_m=0.15, range_m=8.0, radius_m=0.25, occupied_memory_s=20.0, free_memory_s=6.0)


def _see(m: LocalMap, blocks: np.ndarray, frames: int = 3, pose: Pose | None = None) -> None:
    pose = pose or Pose.at(0.0, 0.0, 1.5)
    for k in range(frames):
        m.integrate(blocks, GEOM, BLOCK_PX, pose, 0.1 * k)


NORTH = np.array([[1.0, 0.0, 0.0]])
EAST = np.array([[0.0, 1.0, 0.0]])


def test_a_wall_ahead_bounds_the_free_length_at_the_radius() -> None:
    m = _map()
    _see(m, _wall_blocks(4.0))
    fl = m.free_lengths(np.array([0.0, 0.0, -1.5]), NORTH)
    # The wall's face at 4 m, less the radius rounded up to whole cubes and a cube of sampling.
    assert 3.2 <= fl.length_m[0] <= 3.85
    assert fl.blocked[0]


def test_from_inside_a_surface_s_radius_the_way_out_is_open_and_the_way_in_is_not() -> None:
    m = _map()
    _see(m, _wall_blocks(4.0))
    inside = np.array([3.8, 0.0, -1.5])  # 0.2 m from the wall's face: within the radius
    m.mark_body_free(inside, 0.3)
    fl = m.free_lengths(inside, np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    assert fl.length_m[0] > 1.0  # back, away from the wall
    assert fl.length_m[1] < 0.2 and fl.blocked[1]  # on into it


def test_unknown_is_near_a_side_never_looked_at_is_not_free() -> None:
    m = _map()
    _see(m, _wall_blocks(6.0))
    fl = m.free_lengths(np.array([0.0, 0.0, -1.5]), EAST)
    assert fl.length_m[0] < 0.5  # east is outside the camera's view: not seen free
    assert not fl.blocked[0]


def test_a_plain_wall_with_no_valid_block_stays_unknown() -> None:
    m = _map()
    _see(m, np.full(BLOCKS, np.nan, dtype=np.float32))
    fl = m.free_lengths(np.array([0.0, 0.0, -1.5]), NORTH)
    assert fl.length_m[0] < 0.5 and not fl.blocked[0]


def test_unknown_beside_the_path_is_near_a_jamb_in_a_plain_wall_bounds_the_line_past_it() -> None:
    """A plain wall 4 m ahead (no valid block: unknown) with a door 1.2 m wide in it (seen through to
    7.5 m). PX4 SITL flew the edge of such a door's free band at 1.7 m/s: the line's centre was seen
    free through the door, the jamb 0.2 m beside it was not seen at all, and when it entered the map
    1.4 m ahead the vehicle could not stop. The body's whole width must be seen free, not its centre."""
    cols = slice(36, 48)  # the door's columns at 4 m: within ±0.6 m of the axis
    door = np.full(BLOCKS, np.nan, dtype=np.float32)
    door[:, cols] = GEOM.focal_baseline_px_m / 7.5
    m = _map()
    _see(m, door)
    start = np.array([0.0, 0.0, -1.5])
    centre = m.free_lengths(start, NORTH)
    assert centre.length_m[0] > 6.0  # through the middle: the whole body's width seen free
    ang = math.atan2(0.4, 4.0)  # through the door 0.4 m east of its middle: 0.2 m from the jamb
    edge = m.free_lengths(start, np.array([[math.cos(ang), math.sin(ang), 0.0]]))
    assert edge.length_m[0] < 4.0 and not edge.blocked[0]  # ends short of the wall, in unknown space
    assert _seen_free_along(m, start, np.array([math.cos(ang), math.sin(ang), 0.0])) > 6.0  # its centre alone was seen free


def test_one_false_match_is_not_an_obstacle_and_is_cleared_by_seeing_through() -> None:
    m = _map()
    m.integrate(_wall_blocks(2.0), GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), 0.0)  # one frame only
    far = _wall_blocks(7.5)
    for k in range(1, 4):
        m.integrate(far, GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), 0.1 * k)
    fl = m.free_lengths(np.array([0.0, 0.0, -1.5]), NORTH)
    assert fl.length_m[0] > 5.0


def test_the_left_edge_clears_no_nearer_than_its_columns_can_match() -> None:
    """The left image's column x matches disparities below x + 1 only: a wall at grazing angle at
    the left edge read far there, rays through it cleared the wall from the map, and a flight at
    0.7 m/s along it turned into its end. A ray is evidence of free space only beyond the nearest
    depth its block's columns could have matched."""
    far = np.full(BLOCKS, np.nan, dtype=np.float32)
    far[:, :4] = GEOM.focal_baseline_px_m / 30.0  # the leftmost 16 px read 30 m
    left = -math.atan(GEOM.cx_px / GEOM.focal_px) + math.radians(3.0)  # a ray of the leftmost columns
    along = np.array([[math.cos(left), math.sin(left), 0.0]])
    seen = []
    for num_disparities in (None, 64):
        m = _map()
        for k in range(3):
            m.integrate(far, GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), 0.1 * k, num_disparities)
        seen.append(_seen_free_along(m, np.array([0.0, 0.0, -1.5]), along[0]))
    assert seen[0] > 3.0  # unlimited: cleared from the camera on
    assert seen[1] < 0.5  # the matcher's range: the ray's first metres say nothing


def _seen_free_along(m: LocalMap, start: np.ndarray, u: np.ndarray) -> float:
    """How far the cubes on the line from ``start`` along ``u`` are seen free, metres (the centre
    line alone: what the rays cleared, before the body's rim is judged)."""
    free = m.seen_free()
    for s in np.arange(m.voxel_m, m.range_m, m.voxel_m):
        ijk = np.floor((start + u * s) / m.voxel_m).astype(np.int64) - m.origin
        if not free[tuple(ijk)]:
            return float(s - m.voxel_m)
    return m.range_m


def test_office_15004_a_fence_hit_in_one_frame_of_three_is_not_seen_free() -> None:
    """Kinematic suite, office-15004 at 3 m/s: a see-through fence of bars 10 cm apart, 4.8 m ahead,
    was hit in some frames and seen through to the wall behind in the others; its cubes' log-odds sank
    and they read as seen free until 1.85 m off, too late to stop. A cube hit twice within half a
    second is unknown, and the free length ends before it; once frames stop hitting it, the space
    behind is free again."""
    m = _map()
    bars, through = _wall_blocks(3.0), _wall_blocks(7.0)
    t = 0.0
    for k in range(12):
        t = k / 30.0
        m.integrate(bars if k % 3 == 0 else through, GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), t)
    fl = m.free_lengths(np.array([0.0, 0.0, -1.5]), NORTH)
    assert fl.length_m[0] < 3.0  # no way through the fence ...
    assert not fl.blocked[0]  # ... though the passes outweigh its hits: it ends in the unknown
    for k in range(1, 20):  # the fence gone: only the wall behind
        m.integrate(through, GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), t + k / 30.0)
    assert m.free_lengths(np.array([0.0, 0.0, -1.5]), NORTH).length_m[0] > 5.0


def test_office_45004_a_fence_looked_away_from_stays_unknown() -> None:
    """office-45004 at 3 m/s with 0.14 m/s drift: the vehicle turned to fly along a see-through fence
    0.6 m off it, the camera looking along the fence, not at it. Half a second later its cubes, hit and
    seen through in turn while the camera faced them, read as seen free, though no frame had seen them
    since: the vehicle turned back through the fence and met it. Evidence that was mixed stays mixed
    until frames see through the cubes again, for half a second, with no hit."""
    m = _map()
    bars, through = _wall_blocks(3.0), _wall_blocks(7.0)
    for k in range(12):
        m.integrate(bars if k % 3 == 0 else through, GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), k / 30.0)
    east = Pose.at(0.0, 0.0, 1.5, yaw_rad=0.5 * math.pi)
    for k in range(12, 60):  # two seconds looking east, along the fence: nothing of it in view
        m.integrate(_wall_blocks(6.0), GEOM, BLOCK_PX, east, k / 30.0)
    fl = m.free_lengths(np.array([0.0, 0.0, -1.5]), NORTH)
    assert fl.length_m[0] < 3.0 and not fl.blocked[0]  # unknown, as it was: no way through
    for k in range(60, 80):  # looking north again: the fence gone, only the wall behind
        m.integrate(through, GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), k / 30.0)
    assert m.free_lengths(np.array([0.0, 0.0, -1.5]), NORTH).length_m[0] > 5.0


def test_a_surface_seen_solid_is_not_erased_by_reads_that_land_where_nothing_stands() -> None:
    """A fence seen solid for a third of a second, then read through at a depth that moves with the
    vehicle (a matcher's alias: three times the fence's distance), never at a surface the map holds:
    the fence stays. Reads of the same wall behind, frame after frame, clear it as before."""
    m = _map()
    t = 0.0
    for k in range(10):
        t = k / 30.0
        m.integrate(_wall_blocks(3.0 - 0.1 * k), GEOM, BLOCK_PX, Pose.at(0.1 * k, 0.0, 1.5), t)
    for k in range(10, 30):  # the alias: 3x the distance, nearer by 0.3 m each frame
        t = k / 30.0
        m.integrate(_wall_blocks(3.0 * (3.0 - 0.1 * k)), GEOM, BLOCK_PX, Pose.at(0.1 * k, 0.0, 1.5), t)
    start = np.array([1.9, 0.0, -1.5])  # the vehicle's last frame: the fence 1.1 m ahead
    fl = m.free_lengths(start, NORTH)
    assert fl.blocked[0] and fl.length_m[0] < 1.1
    for k in range(30, 50):  # the fence gone: the wall 5 m behind it, read where it stands
        m.integrate(_wall_blocks(6.1), GEOM, BLOCK_PX, Pose.at(1.9, 0.0, 1.5), k / 30.0)
    assert m.free_lengths(start, NORTH).length_m[0] > 4.0


def test_office_40123_a_fence_read_at_its_alias_is_not_flown_into() -> None:
    """office-40123 at 3 m/s with 0.14 m/s drift and the GPU's matcher (``cpu-sgm``, bit for bit the
    same): its fence's bars are 8 cm apart, under the 12 cm baseline. Within about 2.5 m the census
    window pairs each bar with its neighbour's image and the wall behind with itself (from 2.2 m every
    ray through the fence reads three times farther), and those reads cleared the fence the map had
    seen solid: the vehicle flew into it at 4.6 s. Reads that end where no surface stands no longer
    clear a surface seen solid."""
    from companion.config import parse_config
    from companion.sim.courses import make_course
    from companion.sim.loop import fly
    from companion.sim.scoring import Outcome

    cfg = parse_config({"stereo": {"backend": "cpu-sgm"}, "sim": {"drift_speed_m_s": 0.14, "camera_rate_hz": 30.0}})
    result = fly(replace(make_course("office", 40123), time_limit_s=7.0), cfg)
    assert result.outcome is not Outcome.COLLISION, result.reason
    assert result.min_clearance_m > 0.0


def test_office_40170_a_fence_seen_from_a_banked_vehicle_is_not_flown_into() -> None:
    """office-40170 at 3 m/s with 0.14 m/s drift and StereoBM (the default without a GPU): the simulator
    drew the fence's bars, thinner than a pixel 4 m off, as broken dashes under the vehicle's slight
    bank (a pixel partly covered came out dark or not at all). No matcher paired the dashes; the ceiling read
    through the gaps cleared the fence's upper cubes, and the vehicle climbed into them at 2.2 m/s. A
    camera's pixel adds up what covers it, and so does the simulator now: the bars are faint unbroken
    lines, and the flight passes the fence."""
    from companion.config import parse_config
    from companion.sim.courses import make_course
    from companion.sim.loop import fly
    from companion.sim.scoring import Outcome

    cfg = parse_config({"stereo": {"backend": "opencv-bm"}, "sim": {"drift_speed_m_s": 0.14, "camera_rate_hz": 30.0}})
    course = replace(make_course("office", 40170), time_limit_s=8.0)  # the fence was met at 3.2 s
    result = fly(course, cfg)
    assert result.outcome is not Outcome.COLLISION, result.reason
    assert result.min_clearance_m > 0.0


def test_office_45004_a_fence_flown_along_is_not_turned_through() -> None:
    """office-45004 at 3 m/s with 0.14 m/s drift and the GPU's matcher (``cpu-sgm``), realization 1:
    past the fence's free end the vehicle turned to fly along the fence, 0.6 m off it, and the
    fence it had seen through in turn read as free half a second after it left the view; the planner
    turned back through it and met it at 7.5 s. The map keeps it unknown until it is seen again."""
    from companion.config import parse_config
    from companion.sim.courses import make_course
    from companion.sim.loop import fly
    from companion.sim.scoring import Outcome

    cfg = parse_config(
        {"stereo": {"backend": "cpu-sgm"}, "sim": {"drift_speed_m_s": 0.14, "camera_rate_hz": 30.0, "realization": 1}}
    )
    result = fly(replace(make_course("office", 45004), time_limit_s=9.0), cfg)
    assert result.outcome is not Outcome.COLLISION, result.reason
    assert result.min_clearance_m > 0.0


def test_office_40154_a_climb_toward_a_fence_top_is_taken_back_before_the_door() -> None:
    """office-40154 at 3 m/s with 0.14 m/s drift and the GPU's matcher (``cpu-sgm``), realization 0:
    the fence's bars unknown and the space over it seen free, the vehicle climbed toward its top,
    flew slowly round the cabinet and, coming back down at 0.1 m/s, met the door with its lintel at
    its altitude and held a dead end. Taken back over the speed flown, the altitude is the goal's
    again by the door, and the vehicle flies through it."""
    from companion.config import parse_config
    from companion.sim.courses import make_course
    from companion.sim.loop import fly
    from companion.sim.scoring import Outcome

    cfg = parse_config(
        {"stereo": {"backend": "cpu-sgm"}, "sim": {"drift_speed_m_s": 0.14, "camera_rate_hz": 30.0, "realization": 0}}
    )
    result = fly(make_course("office", 40154), cfg)
    assert result.outcome is Outcome.GOAL, result.reason
    assert result.min_clearance_m > 0.0


def test_one_false_match_on_seen_free_space_is_not_mixed_evidence() -> None:
    """A single hit on space seen free over and over (a false match, depth noise at a surface's edge)
    is not a thin thing hit in some frames: the line stays seen free in the frames that follow, as
    one hit is not a surface either."""
    m = _map()
    bars, through = _wall_blocks(3.0), _wall_blocks(7.0)
    for k in range(12):
        m.integrate(bars if k == 6 else through, GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), k / 30.0)
    assert m.free_lengths(np.array([0.0, 0.0, -1.5]), NORTH).length_m[0] > 5.0


def test_the_map_rolls_with_the_vehicle_and_keeps_what_it_saw() -> None:
    m = _map()
    _see(m, _wall_blocks(6.0))
    m.centre_on(np.array([5.0, 0.0, -1.5]))  # a quarter of the grid: it rolls
    fl = m.free_lengths(np.array([4.0, 0.0, -1.5]), NORTH)
    assert fl.blocked[0] and fl.length_m[0] < 2.0


def test_the_layers_kept_up_frame_by_frame_equal_the_layers_computed_whole() -> None:
    """The occupancy, its inflation and the seen-free layer are updated round the cubes that change
    (hits, passes, hits and passes that age out, the grid rolling): they equal the layers computed
    from the evidence at once."""
    from companion.core.planner._layers import box_count
    from companion.core.planner.localmap import MIXED_EVIDENCE_S, OCCUPIED_LOG_ODDS

    m = LocalMap(voxel_m=0.15, range_m=8.0, radius_m=0.25, occupied_memory_s=1.0, free_memory_s=0.8)
    t = 0.0
    origins = set()
    for k in range(60):
        t = 0.1 * k
        depth = 1.5 if k < 20 else 30.0  # a wall, then seen through (its hits clear and age out)
        pose = Pose.at(0.12 * k, 0.03 * k, 1.5, yaw_rad=0.05 * k)
        m.integrate(_wall_blocks(depth, slice(10 + k % 7, 60)), GEOM, BLOCK_PX, pose, t)
        origins.add(tuple(m.origin))
        if k in (12, 39, 59):
            occ = (m.log_odds > OCCUPIED_LOG_ODDS) & (m.hit_t >= m.now_s - m.occupied_memory_s)
            assert k != 12 or occ.any()
            assert np.array_equal(m.occupied(), occ)
            assert np.array_equal(m.inflated(), box_count(occ, 2) > 0)
            recent = m.free_t >= m.now_s - m.free_memory_s
            mixed = m.prev_hit_t > m.free_t - MIXED_EVIDENCE_S
            free = (box_count(recent, 1) > 0) & (m.log_odds <= OCCUPIED_LOG_ODDS) & ~mixed & ~occ
            assert np.array_equal(m.seen_free(), free)
    assert len(origins) > 1  # the grid rolled


def test_speed_law_is_the_exact_stopping_solution() -> None:
    cfg = PlannerConfig(cruise_speed_m_s=20.0)
    a, t, margin = cfg.braking_accel_m_s2, cfg.latency_s, cfg.stop_margin_m
    for d in (0.5, 1.0, 3.0, 8.0):
        v = speed_law(d, cfg)
        assert v * t + v * v / (2.0 * a) == pytest.approx(max(d - margin, 0.0), abs=1e-9)
    assert speed_law(0.1, cfg) == 0.0
    assert speed_law(100.0, PlannerConfig(cruise_speed_m_s=3.0)) == 3.0


def _snap(**kw: object) -> Snapshot:
    base = dict(
        now_s=1.0,
        position_ned_m=np.array([0.0, 0.0, -1.5]),
        velocity_ned_m_s=np.zeros(3),
        yaw_rad=0.0,
        goal_ned_m=np.array([20.0, 0.0, -1.5]),
        decision=Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear"),
    )
    base.update(kw)
    return Snapshot(**base)  # type: ignore[arg-type]


def test_open_space_flies_at_the_goal_at_the_speed_the_free_length_allows() -> None:
    m = _map()
    _see(m, _wall_blocks(30.0))  # everything ahead seen free to the range
    p = LocalPlanner(PlannerConfig(), 0.25)
    plan = p.plan(_snap(), m)
    assert plan.mode is Mode.CRUISE
    assert plan.velocity_ned_m_s[0] > 0.5 and abs(plan.velocity_ned_m_s[1]) < 0.5 * plan.velocity_ned_m_s[0]
    assert np.linalg.norm(plan.velocity_ned_m_s) == pytest.approx(speed_law(plan.free_m, p.cfg))


def test_level_flight_holds_the_goal_s_altitude_on_the_position() -> None:
    """An autopilot in offboard velocity control holds a vertical speed, not a height, and a climb
    chosen to look over a wall must be taken back: PX4 SITL flights climbed 1.7 m over 10 m of an
    office and stayed there, into the wall over a door. The planner's "level" candidate is the way
    back to the goal's altitude over the distance flown in ALTITUDE_RETURN_S, however small the
    error: too small for the next candidate climb, it would otherwise never be taken back."""
    p = LocalPlanner(PlannerConfig(ceiling_m=6.0), 0.25)
    cruise = p.cfg.cruise_speed_m_s
    for above_m in (0.3, 0.05, -0.2, 3.0):
        m = _map()
        _see(m, _wall_blocks(30.0), pose=Pose.at(0.0, 0.0, 1.5 + above_m))
        p.engage()
        flying = np.array([cruise, 0.0, 0.0])
        plan = p.plan(_snap(position_ned_m=np.array([0.0, 0.0, -1.5 - above_m]), velocity_ned_m_s=flying), m)
        speed = float(np.linalg.norm(plan.velocity_ned_m_s))
        assert speed == pytest.approx(cruise)
        # within half the steepest climb, so that a climb and a descent are left either way
        back = min(math.atan2(above_m, cruise * ALTITUDE_RETURN_S), 0.5 * math.radians(p.cfg.max_climb_deg))
        assert plan.velocity_ned_m_s[2] == pytest.approx(speed * math.sin(back))


def test_the_way_back_to_altitude_takes_as_long_at_low_speed() -> None:
    """The altitude error decays in ALTITUDE_RETURN_S whatever the speed: a vehicle flying 0.8 m/s
    round something comes down as fast as one at cruise (measured in distance at cruise, one that
    climbed toward a fence's top and flew slowly round a cabinet came down at 0.1 m/s, met a door's
    lintel at that altitude and held it as a dead end). The speed flown is the larger of the
    measured and the one last commanded, which the vehicle is still reaching. Steeper than half the
    steepest climb it is capped there, and flown: level is no cheaper for the vehicle still flying
    level (the last choice and the fuzzy controller's pitch count from the way back)."""

    def down_m_s(flown: float, above_m: float) -> float:
        """The descent rate at the speed flown along the climb chosen, m/s."""
        m = _map()
        _see(m, _wall_blocks(30.0), pose=Pose.at(0.0, 0.0, 1.5 + above_m))
        p = LocalPlanner(PlannerConfig(ceiling_m=6.0), 0.25)
        snap = _snap(
            position_ned_m=np.array([0.0, 0.0, -1.5 - above_m]),
            velocity_ned_m_s=np.array([0.5 * flown, 0.0, 0.0]),  # still reaching the speed commanded
            in_flight_ned_m_s=np.array([flown, 0.0, 0.0]),
        )
        plan = p.plan(snap, m)
        for _ in range(3):  # and kept, tick after tick
            again = p.plan(replace(snap, now_s=snap.now_s + 0.1), m)
            np.testing.assert_allclose(again.direction_ned, plan.direction_ned)
        return flown * float(plan.direction_ned[2])

    above_m = 0.3
    at_cruise, slow = down_m_s(3.0, above_m), down_m_s(0.8, above_m)
    assert 0.9 * above_m / ALTITUDE_RETURN_S < slow <= above_m / ALTITUDE_RETURN_S + 1e-9
    assert slow == pytest.approx(at_cruise, rel=0.02)
    cap = 0.5 * math.radians(PlannerConfig().max_climb_deg)
    assert down_m_s(0.8, 0.8) == pytest.approx(0.8 * math.sin(cap))


def test_a_wall_across_the_way_turns_the_planner_to_look_round() -> None:
    m = _map()
    _see(m, _wall_blocks(1.2))
    p = LocalPlanner(PlannerConfig(), 0.25)
    plan = p.plan(_snap(), m)
    assert plan.mode is Mode.DETOUR
    assert abs(plan.yaw_rate_deg_s) > 30.0  # turning the camera toward a side not yet looked at
    assert np.linalg.norm(plan.velocity_ned_m_s) < 1.0  # slow: only what was seen free counts


def test_a_closed_pocket_is_held_once_looked_round() -> None:
    m = _map()
    p = LocalPlanner(PlannerConfig(), 0.25)
    # Look round a pocket: walls at 1 m in every direction the camera turns to.
    plan = None
    for k in range(50):
        yaw = math.radians(-120.0 + 6.0 * k)
        pose = Pose.at(0.0, 0.0, 1.5, yaw_rad=yaw)
        m.integrate(_wall_blocks(1.0), GEOM, BLOCK_PX, pose, 0.05 * k)
        plan = p.plan(_snap(now_s=0.05 * k, yaw_rad=yaw), m)
    assert plan is not None and plan.mode is Mode.HOLD and "dead end" in plan.reason
    # Held: it stays held whatever comes next (only the operator's resume or a new engagement leaves it).
    assert p.plan(_snap(now_s=5.0), m).mode is Mode.HOLD
    assert all(TRANSITIONS[(Mode.HOLD, e)] is Mode.HOLD for e in ("direct", "steer", "round"))
    p.resume()  # looks again: the pocket is still closed, so it is held again once confirmed
    assert p.plan(_snap(now_s=5.1), m).mode is not Mode.HOLD
    assert p.plan(_snap(now_s=5.7), m).mode is Mode.HOLD


def test_a_direction_looked_along_from_elsewhere_is_worth_a_look_from_here() -> None:
    """PX4 SITL, a wall across the way with an opening to one side: the planner looked toward the
    goal from the start, flew along the wall past the opening (seen only at a grazing angle), and
    the way through it, its space unknown, counted as looked at from 3.7 m away: closed. It held a
    false dead end. Looked along from farther than LOOKED_FROM_M, a direction is worth a look again."""
    m = _map()
    p = LocalPlanner(PlannerConfig(), 0.25)
    for k, yaw in enumerate((-math.pi / 2, -math.pi / 4, 0.0, math.pi / 4)):  # west to north-east, from the start
        p.plan(_snap(now_s=1.0 + 0.01 * k, position_ned_m=np.array([0.0, 0.0, -1.5]), yaw_rad=yaw), m)
    beside = np.array([0.0, 3.0, -1.5])
    assert LOOKED_FROM_M < 3.0
    for k in range(10):  # facing east, 3 m from where it looked north, within the look memory
        plan = p.plan(_snap(now_s=1.2 + 0.1 * k, position_ned_m=beside, yaw_rad=math.pi / 2), m)
    assert plan.mode is not Mode.HOLD, plan.reason
    assert plan.yaw_rate_deg_s < -30.0  # turning left, to look north again from here


def test_the_service_s_watchdog_stops_the_planner_at_the_point_it_holds() -> None:
    m = _map()
    _see(m, _wall_blocks(30.0))
    p = LocalPlanner(PlannerConfig(), 0.25)
    assert p.plan(_snap(now_s=0.3), m).mode is Mode.CRUISE
    p.stop("no progress along the course for 20 s")
    held = p.plan(_snap(now_s=0.35), m)
    assert held.mode is Mode.HOLD and held.reason.startswith("no progress")
    assert np.allclose(held.velocity_ned_m_s, 0.0)
    away = p.plan(_snap(now_s=0.4, position_ned_m=np.array([0.3, 0.0, -1.5])), m)
    assert away.velocity_ned_m_s[0] == pytest.approx(-0.3)  # back to the point held


def test_a_hold_begun_within_the_radius_of_a_surface_backs_out_of_it() -> None:
    """PX4 SITL, two office flights: a dead end declared 0.3 m from a surface (a lintel, a door jamb)
    was held there, and PX4's velocity loop crept on at 0.1 m/s into the surface while told to hold
    the point. A hold that begins within the radius of a surface holds a point out of it, the way
    the map leaves free; one that begins clear of every surface holds where it is."""
    m = _map()
    _see(m, _wall_blocks(1.0))  # a wall across the way 1 m north
    near = np.array([0.85, 0.0, -1.5])
    m.mark_body_free(near, 0.3)
    assert bool(m.within_radius(near))
    p = LocalPlanner(PlannerConfig(), 0.25)
    p.stop("dead end")
    plan = p.plan(_snap(position_ned_m=near), m)
    assert plan.mode is Mode.HOLD
    back = plan.velocity_ned_m_s
    assert back[0] < -0.2 and abs(back[1]) < abs(back[0])  # back, away from the wall
    assert np.linalg.norm(plan.velocity_ned_m_s) <= 0.5 + 1e-9
    clear = np.array([0.0, 0.0, -1.5])
    assert not bool(m.within_radius(clear))
    p.engage()
    p.stop("dead end")
    assert np.allclose(p.plan(_snap(position_ned_m=clear), m).velocity_ned_m_s, 0.0)


def test_the_predicted_path_swings_with_the_lagging_velocity() -> None:
    """A vehicle flying east at 3 m/s told to fly north carries on east for about its speed times
    the response time before its velocity turns; told to fly on as it flies, it flies the line."""
    cfg = PlannerConfig()
    north = np.array([[1.0, 0.0, 0.0]])
    offs, arc = predicted_paths(np.array([0.0, 3.0, 0.0]), north, np.array([3.0]), cfg, 0.15)
    ok = np.isfinite(arc[0])
    assert offs[0, ok, 1].max() >= 3.0 * cfg.latency_s * 0.9
    assert np.all(np.diff(arc[0, ok]) > 0.0) and arc[0, ok].max() <= cfg.map_range_m + 1e-9
    offs, arc = predicted_paths(np.array([3.0, 0.0, 0.0]), north, np.array([3.0]), cfg, 0.15)
    ok = np.isfinite(arc[0])
    assert np.abs(offs[0, ok, 1]).max() < 1e-9
    assert offs[0, ok, 0] == pytest.approx(arc[0, ok])


def test_a_sharp_turn_at_speed_costs_speed_not_clearance() -> None:
    """Flying fast along a wall's side and turning away from it costs nothing; turning when the
    lagging velocity would carry the vehicle into a wall ahead of its motion shortens the turn's
    free length (its speed), though the line itself is seen free."""
    m = _map()
    _see(m, _wall_blocks(1.0), pose=Pose.at(0.0, 0.0, 1.5, yaw_rad=math.pi / 2))  # a wall 1 m east
    _see(m, _wall_blocks(30.0))  # north seen free to the range
    p = LocalPlanner(PlannerConfig(), 0.25)
    at_rest = p.plan(_snap(), m).candidates
    p = LocalPlanner(PlannerConfig(), 0.25)
    eastward = p.plan(_snap(velocity_ned_m_s=np.array([0.0, 3.0, 0.0])), m).candidates
    north_level = 2  # yaw row 0 (the goal's direction, north), the level climb
    assert at_rest[north_level, 2] >= 4.0
    assert eastward[north_level, 2] < 0.5 * at_rest[north_level, 2]
    westward = LocalPlanner(PlannerConfig(), 0.25).plan(_snap(velocity_ned_m_s=np.array([0.0, -3.0, 0.0])), m).candidates
    assert westward[north_level, 2] == pytest.approx(at_rest[north_level, 2])


def test_the_swing_is_predicted_from_the_setpoint_in_flight_too() -> None:
    """An autopilot chases the setpoint it was sent until its delay has passed (ArduCopter: 0.36 s),
    whatever the planner chooses now: a vehicle at rest that was just told to fly east toward a wall
    will move east first. The turn north costs speed as it would at that velocity; a setpoint in
    flight along the way chosen costs nothing."""
    m = _map()
    _see(m, _wall_blocks(1.0), pose=Pose.at(0.0, 0.0, 1.5, yaw_rad=math.pi / 2))  # a wall 1 m east
    _see(m, _wall_blocks(30.0))  # north seen free to the range
    north_level = 2
    at_rest = LocalPlanner(PlannerConfig(), 0.25).plan(_snap(), m).candidates
    told_east = LocalPlanner(PlannerConfig(), 0.25).plan(_snap(in_flight_ned_m_s=np.array([0.0, 3.0, 0.0])), m).candidates
    assert told_east[north_level, 2] < 0.5 * at_rest[north_level, 2]
    told_north = LocalPlanner(PlannerConfig(), 0.25).plan(_snap(in_flight_ned_m_s=np.array([3.0, 0.0, 0.0])), m).candidates
    assert told_north[north_level, 2] == pytest.approx(at_rest[north_level, 2])


def test_the_stack_tells_the_planner_the_setpoint_it_sent() -> None:
    cfg = CompanionConfig.model_validate({})
    stack = LocalStack(cfg)
    stack.engage(np.array([0.0, 0.0, -1.5]), 0.0, None)
    for k in range(3):
        stack.add_frame(_wall_blocks(30.0), GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), 0.1 * k)
    seen: list[Snapshot] = []
    plan = stack.planner.plan

    def spy(snap: Snapshot, lmap: LocalMap) -> Plan:
        seen.append(snap)
        return plan(snap, lmap)

    stack.planner.plan = spy  # type: ignore[method-assign]
    clear = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear")
    first = stack.step(0.3, 0.05, clear, np.full(9, 10.0), np.array([0.0, 0.0, -1.5]), np.zeros(3), 0.0)
    stack.step(0.35, 0.05, clear, np.full(9, 10.0), np.array([0.0, 0.0, -1.5]), np.zeros(3), 0.0)
    assert seen[0].in_flight_ned_m_s is None  # nothing sent yet this flight
    sent = first.setpoint
    assert seen[1].in_flight_ned_m_s == pytest.approx([sent.forward_m_s, sent.right_m_s, sent.down_m_s])
    stack.engage(np.array([0.0, 0.0, -1.5]), 0.0, None)
    stack.step(0.4, 0.05, clear, np.full(9, 10.0), np.array([0.0, 0.0, -1.5]), np.zeros(3), 0.0)
    assert seen[2].in_flight_ned_m_s is None  # a new flight starts from what it has


def test_without_a_goal_the_fuzzy_controller_is_the_whole_policy() -> None:
    m = _map()
    _see(m, _wall_blocks(30.0))
    p = LocalPlanner(PlannerConfig(), 0.25)
    right = p.plan(_snap(goal_ned_m=None, decision=Decision(DecisionKind.AVOID, 0.8, 0.0, 0.5, "avoid")), m)
    p.engage()
    left = p.plan(_snap(goal_ned_m=None, decision=Decision(DecisionKind.AVOID, -0.8, 0.0, 0.5, "avoid")), m)
    assert right.yaw_rate_deg_s > 0.0 > left.yaw_rate_deg_s
    p.engage()
    brake = p.plan(_snap(goal_ned_m=None, decision=Decision(DecisionKind.BRAKE, 0.0, 0.0, 0.0, "brake")), m)
    assert np.all(brake.velocity_ned_m_s == 0.0)


def test_membership_functions_reloaded_change_the_flight() -> None:
    """The paper's controller stays in the loop: a reload of its membership functions changes its
    decision for the same region depths, and with it the planner's choice."""
    depths = np.array([4.0, 1.6, 4.0, 4.0, 1.6, 4.0, 4.0, 4.0, 4.0])
    base = CompanionConfig()
    d1 = AvoidanceController(base.controller).decide(depths)
    # Every depth term's breakpoints halved (a live reload): 1.6 m now reads as far.
    terms = {
        n: t.model_copy(update={"params_m": tuple(0.5 * v for v in t.params_m)})
        for n, t in base.controller.input_terms.items()
    }
    reloaded = ControllerConfig.model_validate({**base.controller.model_dump(), "input_terms": {n: t.model_dump() for n, t in terms.items()}})
    d2 = AvoidanceController(reloaded).decide(depths)
    assert (d1.kind, round(d1.yaw, 3), round(d1.pitch, 3)) != (d2.kind, round(d2.yaw, 3), round(d2.pitch, 3))
    m = _map()
    _see(m, _wall_blocks(30.0))
    plans = []
    for d in (d1, d2):
        p = LocalPlanner(PlannerConfig(), 0.25)
        plans.append(p.plan(_snap(goal_ned_m=None, decision=d), m))
    assert not np.allclose(plans[0].velocity_ned_m_s, plans[1].velocity_ned_m_s) or plans[0].yaw_rate_deg_s != plans[1].yaw_rate_deg_s


# -- the safety chain --------------------------------------------------------------------------------


def _ctx(**kw: object) -> SafetyContext:
    base = dict(
        frame_age_s=0.05,
        stale_after_s=0.5,
        holding=False,
        decision=Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear"),
        centre_depth_m=10.0,
        yaw_rad=0.0,
        altitude_m=1.5,
        velocity_ned_m_s=np.zeros(3),
        unexplained_ned_m_s=np.zeros(3),
        free_along=lambda u: 8.0,
        planner=PlannerConfig(),
        max_horizontal_m_s=4.0,
        max_vertical_m_s=1.0,
        max_yaw_rate_deg_s=90.0,
    )
    base.update(kw)
    return SafetyContext(**base)  # type: ignore[arg-type]


FAST = VelocitySetpoint(3.0, 0.0, 0.0, 10.0)


def test_stale_frames_give_zero_velocity() -> None:
    assert stale_to_zero(FAST, _ctx(frame_age_s=0.6)) == ZERO_SETPOINT
    assert stale_to_zero(FAST, _ctx(frame_age_s=math.inf)) == ZERO_SETPOINT
    assert stale_to_zero(FAST, _ctx()) == FAST


def test_holding_is_zero_and_the_fuzzy_brake_caps_forward_speed_by_the_centre_depth() -> None:
    assert brake_hold(ZERO_SETPOINT, _ctx(holding=True)) == ZERO_SETPOINT
    held = brake_hold(FAST, _ctx(holding=True))  # the way back to the held point: slow, no turn
    assert held.forward_m_s == pytest.approx(0.5) and held.yaw_rate_deg_s == 0.0
    brake = Decision(DecisionKind.BRAKE, 0.0, 0.0, 0.0, "brake")
    capped = brake_hold(FAST, _ctx(decision=brake, centre_depth_m=1.5))
    assert capped.forward_m_s == pytest.approx(speed_law(1.5, PlannerConfig()))
    assert brake_hold(FAST, _ctx(decision=brake, centre_depth_m=math.nan)).forward_m_s == 0.0  # unknown is near


def test_speed_law_limits_the_command_and_brakes_the_motion() -> None:
    short = speed_law_limit(FAST, _ctx(free_along=lambda u: 1.5))
    assert short.forward_m_s == pytest.approx(speed_law(1.5, PlannerConfig()))
    # Moving north at 3 m/s toward a wall 2 m off, commanded east: the north component brakes.
    moving = _ctx(velocity_ned_m_s=np.array([3.0, 0.0, 0.0]), free_along=lambda u: 2.0 if u[0] > 0.9 else 8.0)
    out = speed_law_limit(VelocitySetpoint(2.5, 2.0, 0.0, 0.0), moving)
    cfg = PlannerConfig()
    # Faster than it can stop from: the setpoint is a·t below the speed, so that it decelerates at a.
    assert out.forward_m_s <= 3.0 - cfg.braking_accel_m_s2 * cfg.latency_s + 1e-9
    assert out.right_m_s > 1.5  # the sideways part stays (within cruise)


def test_a_vehicle_a_hair_over_the_law_brakes_by_a_hair_and_fully_only_with_no_latency_left() -> None:
    """pitch-17001 at 3 m/s, descending under an overhead block: the speed reported along the motion
    crossed the law on the length ahead by 0.01 m/s, and the setpoint stepped from 1.9 m/s to zero
    (a·t below its speed), then back: 0.6 s lost on a 6 s flight. The braking now grows with the
    latency the law budgets that is already spent at this speed: continuous at the law, a·t below
    the speed when none is left."""
    cfg = PlannerConfig()
    a, t, margin = cfg.braking_accel_m_s2, cfg.latency_s, cfg.stop_margin_m
    free = 3.0
    law = float(speed_law(free, cfg))
    over = law + 0.01
    ctx = _ctx(velocity_ned_m_s=np.array([over, 0.0, 0.0]), free_along=lambda u: free)
    out = speed_law_limit(VelocitySetpoint(over, 0.0, 0.0, 0.0), ctx).forward_m_s
    assert law - 0.05 < out < law  # a hair below the law, not zero
    # Faster, with less of the latency left at that speed: more braking, continuously.
    outs = []
    for ms in np.linspace(over, 3.0, 20):
        ctx = _ctx(velocity_ned_m_s=np.array([ms, 0.0, 0.0]), free_along=lambda u: free)
        outs.append(speed_law_limit(VelocitySetpoint(3.0, 0.0, 0.0, 0.0), ctx).forward_m_s)
        left = max((free - margin - ms * ms / (2 * a)) / ms, 0.0)
        assert outs[-1] == pytest.approx(max(0.0, ms - a * (t - left)))
    assert np.all(np.diff(outs) < 0.1)  # no step
    # None left (it just stops braking at a now): the full a·t below the speed.
    edge = math.sqrt(2.0 * a * (2.0 - margin)) - 1e-9
    ctx = _ctx(velocity_ned_m_s=np.array([edge, 0.0, 0.0]), free_along=lambda u: 2.0)
    assert speed_law_limit(FAST, ctx).forward_m_s == pytest.approx(edge - a * t)


def test_a_command_outside_the_camera_s_view_flies_slower_the_farther_off_the_axis() -> None:
    """Fly where you look. A flight at 0.7 m/s round an overhead block turned the camera east along
    its edge; the goal then lay north, and the planner flew body-left at once into space it had seen
    free seconds before, under the block's edge (the block's lowest cubes cleared by rays passing
    beneath it), and touched it. Off the camera's view the speed comes only as the camera turns."""
    sideways = VelocitySetpoint(0.0, -3.0, 0.0, 0.0)  # body-left: 90 deg off the axis
    assert speed_law_limit(sideways, _ctx()).right_m_s == pytest.approx(0.0, abs=1e-9)
    ahead = VelocitySetpoint(2.0, 1.0, 0.0, 0.0)  # 27 deg off: within the view
    assert speed_law_limit(ahead, _ctx()) == ahead
    off = speed_law_limit(VelocitySetpoint(1.5, 2.6, 0.0, 0.0), _ctx())  # 60 deg off: 0.6 of the speed
    assert math.hypot(off.forward_m_s, off.right_m_s) == pytest.approx(0.6 * 3.0, rel=2e-3)
    assert math.atan2(off.right_m_s, off.forward_m_s) == pytest.approx(math.atan2(2.6, 1.5))
    back = speed_law_limit(VelocitySetpoint(-0.3, 0.0, 0.0, 0.0), _ctx(holding=True))  # the hold's way back
    assert back.forward_m_s == pytest.approx(-0.3)


def test_a_vehicle_that_cannot_stop_in_time_is_told_to_back_off() -> None:
    """Told zero, PX4 creeps on for seconds (its velocity integrator): a flight at 0.7 m/s crept at
    0.15 m/s on into a fence it had turned from. Moving toward a surface nearer than it can stop
    from braking now, the setpoint reverses along the motion by the excess, at most the hold's speed."""
    creeping = _ctx(velocity_ned_m_s=np.array([0.15, 0.0, 0.0]), free_along=lambda u: 0.1)
    assert speed_law_limit(FAST, creeping).forward_m_s == pytest.approx(-0.15)
    fast = _ctx(velocity_ned_m_s=np.array([3.0, 0.0, 0.0]), free_along=lambda u: 0.5)
    assert speed_law_limit(FAST, fast).forward_m_s == pytest.approx(-0.5)
    room = _ctx(velocity_ned_m_s=np.array([1.5, 0.0, 0.0]), free_along=lambda u: 2.0)  # stops in time
    assert speed_law_limit(FAST, room).forward_m_s >= 0.0


def test_a_motion_whose_swing_onto_the_command_stops_clear_is_not_braked_on_its_own_line() -> None:
    """Moving at 2.4 m/s along a line that meets a surface 2.25 m on (short of the 4.1 m it needs to
    stop), commanded onto a line seen free for 7.8 m: where the path the vehicle swings onto the
    command by is seen free for the stopping length, the vehicle can stop on it, and is not braked;
    it gains no speed along the motion's line. Where that swing is short too, or the vehicle holds,
    or a surface is within the stop margin, the motion brakes as before."""
    motion = np.array([2.4, -0.3, 0.0])
    u = motion / np.linalg.norm(motion)
    command = VelocitySetpoint(2.9, 0.4, 0.0, 0.0)

    def ctx(swing_m: float | None, **kw: object) -> SafetyContext:
        return _ctx(
            velocity_ned_m_s=motion,
            free_along=lambda u: 2.25 if u[1] < 0.0 else 7.8,
            free_swinging=None if swing_m is None else (lambda v: swing_m),
            **kw,
        )

    assert stopping_m(2.9, PlannerConfig()) > 2.25
    kept = speed_law_limit(command, ctx(7.8))
    v = np.array([kept.forward_m_s, kept.right_m_s, kept.down_m_s])
    asked = np.array([2.9, 0.4, 0.0])
    assert float(v @ u) == pytest.approx(np.linalg.norm(motion))  # its speed along the motion, no more
    assert v - float(v @ u) * u == pytest.approx(asked - float(asked @ u) * u)  # the rest as commanded
    for braked in (ctx(None), ctx(2.0), ctx(7.8, holding=True), ctx(7.8, surface_gap_m=0.1)):
        out = speed_law_limit(command, braked)
        assert out.forward_m_s < 1.5


def _pillar_blocks(depth_m: float, bearing_deg: float, width_m: float) -> np.ndarray:
    """A block image of a pillar ``width_m`` wide, ``depth_m`` ahead at ``bearing_deg`` (right
    positive), the rest seen open to 20 m."""
    b = np.full(BLOCKS, GEOM.focal_baseline_px_m / 20.0, dtype=np.float32)
    centre = depth_m * math.tan(math.radians(bearing_deg))
    for c in range(BLOCKS[1]):
        lateral = depth_m * (BLOCK_PX * c + 0.5 * (BLOCK_PX - 1) - GEOM.cx_px) / GEOM.focal_px
        if abs(lateral - centre) <= 0.5 * width_m:
            b[:, c] = GEOM.focal_baseline_px_m / depth_m
    return b


def test_corridor_42000_a_turn_past_a_surface_on_the_motion_s_line_keeps_its_speed() -> None:
    """Simulated corridor at 3 m/s: climbing over a box's top, the vehicle moved a degree shallower
    than the planner's climb, and its straight line met the box 2.25 m on while the way it was
    commanded onto was seen free for 7.8 m. The chain braked the motion from 2.4 m/s to 0.2 m/s and
    the planner then fell back to a detour at 1 m/s; not braked so, the flight takes 11.9 s, not
    13.4. The same here with a pillar on the motion's line: the planner's turn past it swings clear,
    so the chain lets it fly; head-on and nearer, where no swing clears, it still brakes, and so it
    does where the motion's line ends in space not seen (the map's swing judges surfaces alone:
    unknown is near)."""
    cfg = CompanionConfig.model_validate({"envelope": {"max_horizontal_speed_m_s": 4.0}})
    clear = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear")
    pos = np.array([0.0, 0.0, -1.5])
    for depth_m, bearing_deg, swings in ((2.6, -8.0, True), (2.0, 0.0, False)):
        stack = LocalStack(cfg)
        stack.engage(pos, 0.0, GoalSpec(kind="point", north_m=15.0, east_m=0.0))
        for k in range(3):
            stack.add_frame(_pillar_blocks(depth_m, bearing_deg, 0.3), GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), 0.1 * k)
        h = math.radians(bearing_deg)
        motion = 2.4 * np.array([math.cos(h), math.sin(h), 0.0])
        assert stack.map.free_lengths(pos, motion[None, :] / 2.4).length_m[0] < stopping_m(2.4, cfg.planner)
        step = stack.step(0.3, 0.05, clear, np.full(9, 10.0), pos, motion, 0.0)
        if swings:  # not braked: at most trimmed where the lagging swing nears the pillar
            assert math.hypot(step.setpoint.forward_m_s, step.setpoint.right_m_s) > 2.5, (step.limited_by, step.plan.reason)
        else:
            assert "speed_law_limit" in step.limited_by
            assert step.setpoint.forward_m_s < 0.5
    # Moving the same way, toward space the camera has not seen (no pillar: the left of the view
    # unseen): braked, as before.
    stack = LocalStack(cfg)
    stack.engage(pos, 0.0, GoalSpec(kind="point", north_m=15.0, east_m=0.0))
    unseen_left = _pillar_blocks(2.6, -8.0, 0.0)
    unseen_left[:, : BLOCKS[1] * 2 // 5] = np.nan
    for k in range(3):
        stack.add_frame(unseen_left, GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), 0.1 * k)
    h = math.radians(-30.0)
    motion = 2.4 * np.array([math.cos(h), math.sin(h), 0.0])
    line = stack.map.free_lengths(pos, motion[None, :] / 2.4)
    assert not line.blocked[0] and line.length_m[0] < stopping_m(2.4, cfg.planner)
    step = stack.step(0.3, 0.05, clear, np.full(9, 10.0), pos, motion, 0.0)
    assert "speed_law_limit" in step.limited_by, step.plan.reason


def test_the_unexplained_motion_comes_off_the_setpoint_and_a_hold_but_not_off_zero() -> None:
    west = np.array([0.0, -0.3, 0.0])  # the vehicle moves west the reported velocity does not show
    out = counter_unexplained(FAST, _ctx(unexplained_ned_m_s=west))
    assert out.forward_m_s == pytest.approx(3.0) and out.right_m_s == pytest.approx(0.3)
    facing_east = counter_unexplained(FAST, _ctx(unexplained_ned_m_s=west, yaw_rad=math.pi / 2))
    assert facing_east.forward_m_s == pytest.approx(3.3) and facing_east.right_m_s == pytest.approx(0.0, abs=1e-9)
    # Holding, the point is held against the drift too (the position loop alone lags it).
    held = counter_unexplained(ZERO_SETPOINT, _ctx(unexplained_ned_m_s=west, holding=True))
    assert held.forward_m_s == pytest.approx(0.0, abs=1e-9) and held.right_m_s == pytest.approx(0.3)
    assert apply_chain(FAST, _ctx(unexplained_ned_m_s=west, frame_age_s=9.0)) == ZERO_SETPOINT
    sinking = counter_unexplained(FAST, _ctx(unexplained_ned_m_s=np.array([0.0, 0.0, 0.2])))
    assert sinking.down_m_s == pytest.approx(-0.2) and sinking.forward_m_s == pytest.approx(3.0)


def test_the_stack_measures_the_motion_the_reported_velocity_does_not_show() -> None:
    """A velocity estimate 0.3 m/s off carried a vehicle passing a box at 3 m/s sideways into it (the
    reported velocity read the setpoint while the position moved toward the box): the stack now
    reads the position's track, predicts with the motion it shows and takes the unseen part off the
    setpoint, at most ``vehicle.odometry_drift_m_s``."""
    def last_setpoint(drift_m_s: float) -> VelocitySetpoint:
        cfg = CompanionConfig.model_validate(
            {"envelope": {"max_horizontal_speed_m_s": 4.0},
             "vehicle": {"odometry_drift_m_s": drift_m_s}}
        )
        stack = LocalStack(cfg)
        stack.engage(np.array([0.0, 0.0, -1.5]), 0.0, None)
        for k in range(3):
            stack.add_frame(_wall_blocks(30.0), GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), 0.1 * k)
        clear = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear")
        for k in range(12):  # the position moves west at 0.3 m/s; the reported velocity reads zero
            t = 0.3 + 0.05 * k
            step = stack.step(t, 0.05, clear, np.full(9, 10.0), np.array([0.0, -0.3 * 0.05 * k, -1.5]), np.zeros(3), 0.0)
        return step.setpoint

    assert last_setpoint(0.5).right_m_s == pytest.approx(0.3 - 0.02, abs=0.02)  # east, less the dead band
    assert last_setpoint(0.1).right_m_s == pytest.approx(0.1, abs=0.01)  # at most the setting
    assert last_setpoint(0.0).right_m_s == pytest.approx(0.0, abs=1e-9)


def test_the_stack_counters_a_climb_the_reported_velocity_does_not_show() -> None:
    """Vertically too: a vehicle sinking 0.3 m/s unseen by its velocity estimate, passing over a low
    wall, is told to climb by that much (the altitude's own return is slow by design)."""
    cfg = CompanionConfig.model_validate({})
    stack = LocalStack(cfg)
    stack.engage(np.array([0.0, 0.0, -1.5]), 0.0, None)
    for k in range(3):
        stack.add_frame(_wall_blocks(30.0), GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), 0.1 * k)
    clear = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear")
    for k in range(12):  # the position sinks at 0.3 m/s; the reported velocity reads zero
        step = stack.step(0.3 + 0.05 * k, 0.05, clear, np.full(9, 10.0), np.array([0.0, 0.0, -1.5 + 0.3 * 0.05 * k]), np.zeros(3), 0.0)
    assert step.setpoint.down_m_s == pytest.approx(-(0.3 - 0.02), abs=0.03)  # up, less the dead band


def test_within_the_margin_of_a_surface_the_vehicle_moves_off_it_and_not_toward_it() -> None:
    """A flight at 0.7 m/s slid along a wall 0.1 m outside its inflation, turned in place there
    with no speed to judge, and a drift the measure of the unexplained motion lagged by 0.1 m/s
    carried it into the wall. Within the stop margin of the nearest surface, the setpoint has no
    component toward it and moves off it at the hold's gain; along the surface it is left alone."""
    margin = PlannerConfig().stop_margin_m
    north = np.array([1.0, 0.0, 0.0])  # the wall is north
    near = _ctx(surface_gap_m=0.1, surface_dir_ned=north)
    still = keep_off(ZERO_SETPOINT, near)
    assert still.forward_m_s == pytest.approx(-(margin - 0.1)) and still.right_m_s == pytest.approx(0.0)
    sliding = keep_off(VelocitySetpoint(0.5, 2.0, 0.0, 5.0), near)  # into the wall and along it
    assert sliding.forward_m_s == pytest.approx(-(margin - 0.1)) and sliding.right_m_s == pytest.approx(2.0)
    assert sliding.yaw_rate_deg_s == 5.0
    leaving = VelocitySetpoint(-0.5, 1.0, 0.0, 0.0)  # already off it faster than the push
    assert keep_off(leaving, near) == leaving
    facing_east = keep_off(ZERO_SETPOINT, _ctx(surface_gap_m=0.1, surface_dir_ned=north, yaw_rad=math.pi / 2))
    assert facing_east.right_m_s == pytest.approx(margin - 0.1)  # north is body-left: right is away
    assert keep_off(FAST, _ctx(surface_gap_m=margin + 0.01, surface_dir_ned=north)) == FAST  # outside the margin
    assert keep_off(FAST, _ctx()) == FAST  # nothing near
    assert apply_chain(FAST, _ctx(surface_gap_m=0.0, surface_dir_ned=north, frame_age_s=9.0)) == ZERO_SETPOINT


def test_the_map_names_the_nearest_surface_seen_and_the_way_to_it() -> None:
    m = _map()
    _see(m, _wall_blocks(4.0))
    near = m.nearest_surface(np.array([3.5, 0.0, -1.5]), 1.0)
    assert near is not None
    gap, toward = near
    assert 0.3 <= gap <= 0.5 + 1e-9  # the wall's face at 4 m, in whole cubes
    assert toward @ np.array([1.0, 0.0, 0.0]) > 0.95
    assert m.nearest_surface(np.array([0.0, 0.0, -1.5]), 1.0) is None  # nothing within a metre
    assert _map().nearest_surface(np.zeros(3), 1.0) is None  # an empty map


def test_a_vehicle_turning_in_place_beside_a_wall_is_moved_off_it() -> None:
    """The stack end to end: a wall seen about 0.45 m north of the vehicle (0.2 m from its body), the
    vehicle still, its goal beyond the wall: the setpoint leads away from the wall."""
    cfg = CompanionConfig.model_validate({})
    stack = LocalStack(cfg)
    stack.engage(np.array([0.0, 0.0, -1.5]), 0.0, None)
    for k in range(3):
        stack.add_frame(_wall_blocks(4.0), GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), 0.1 * k)
    dist, _ = stack.map.nearest_surface(np.array([3.55, 0.0, -1.5]), 1.0)  # type: ignore[misc]
    assert dist - cfg.vehicle.radius_m < cfg.planner.stop_margin_m
    clear = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear")
    step = stack.step(0.4, 0.05, clear, np.full(9, 10.0), np.array([3.55, 0.0, -1.5]), np.zeros(3), 0.0)
    assert "keep_off" in step.limited_by
    assert step.setpoint.forward_m_s < -0.05


def test_floor_and_ceiling_stop_descent_and_climb() -> None:
    down = VelocitySetpoint(0.0, 0.0, 1.0, 0.0)
    up = VelocitySetpoint(0.0, 0.0, -1.0, 0.0)
    assert floor_ceiling(down, _ctx(altitude_m=0.5)).down_m_s == 0.0
    assert floor_ceiling(up, _ctx(altitude_m=3.0)).down_m_s == 0.0
    assert floor_ceiling(down, _ctx(altitude_m=2.0)).down_m_s == 1.0


def test_envelope_bounds_speed_and_rate() -> None:
    out = envelope(VelocitySetpoint(6.0, 0.0, 3.0, 400.0), _ctx())
    assert out.forward_m_s == pytest.approx(4.0) and out.down_m_s == 1.0 and out.yaw_rate_deg_s == 90.0


def test_the_chain_order_is_written_once() -> None:
    assert [f.__name__ for f in CHAIN] == [
        "stale_to_zero", "brake_hold", "speed_law_limit", "keep_off", "counter_unexplained", "floor_ceiling",
        "envelope",
    ]
    assert apply_chain(FAST, _ctx(frame_age_s=9.0)) == ZERO_SETPOINT


def test_the_chain_names_the_filters_that_changed_the_planner_s_setpoint() -> None:
    """A PX4 SITL flight planned 1.7 m/s past a box and flew 0.1 m/s: without the names of what cut
    the setpoint, the health log could not tell a brake from the view from the motion's speed law."""
    assert trace_chain(FAST, _ctx(frame_age_s=9.0)) == (ZERO_SETPOINT, ("stale_to_zero",))
    out, names = trace_chain(FAST, _ctx(free_along=lambda u: 1.5))
    assert names == ("speed_law_limit",) and out == speed_law_limit(FAST, _ctx(free_along=lambda u: 1.5))
    assert trace_chain(VelocitySetpoint(2.0, 1.0, 0.0, 0.0), _ctx()) == (VelocitySetpoint(2.0, 1.0, 0.0, 0.0), ())


def test_the_stack_flies_a_course_goal_and_needs_the_envelope_raised() -> None:
    cfg = CompanionConfig.model_validate(
        {"envelope": {"max_horizontal_speed_m_s": 4.0}}
    )
    stack = LocalStack(cfg)
    stack.engage(np.array([0.0, 0.0, -1.5]), 0.0, None)
    for k in range(3):
        stack.add_frame(_wall_blocks(30.0), GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), 0.1 * k)
    step = stack.step(0.3, 0.05, Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear"), np.full(9, 10.0),
                      np.array([0.0, 0.0, -1.5]), np.zeros(3), 0.0)
    assert step.setpoint.forward_m_s > 0.5
    with pytest.raises(ValueError, match="planner.cruise_speed_m_s"):
        CompanionConfig.model_validate({"envelope": {"max_horizontal_speed_m_s": 2.0}})


def test_a_reload_in_flight_reaches_the_planner_and_keeps_the_map_unless_its_grid_changed() -> None:
    """Users retune in flight: a reloaded planner setting flies from the next tick, with the map seen
    so far; a new grid (voxel, range, radius, memories) starts the map afresh, and unknown is near."""
    cfg = CompanionConfig.model_validate({})
    stack = LocalStack(cfg)
    at = np.array([0.0, 0.0, -1.5])
    stack.engage(at, 0.0, None)
    for k in range(3):
        stack.add_frame(_wall_blocks(30.0), GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), 0.1 * k)
    clear = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear")

    def forward(now_s: float) -> float:
        return stack.step(now_s, 0.05, clear, np.full(9, 10.0), at, np.zeros(3), 0.0).setpoint.forward_m_s

    assert forward(0.3) > 2.0
    stack.reconfigure(CompanionConfig.model_validate({"planner": {"cruise_speed_m_s": 1.2}}))
    assert 0.5 < forward(0.35) <= 1.2 + 1e-9
    stack.reconfigure(CompanionConfig.model_validate({"planner": {"cruise_speed_m_s": 1.2, "voxel_m": 0.2}}))
    assert forward(0.4) == 0.0


@dataclass(frozen=True)
class _Seen:
    """The parts of a frame's outcome the supervisor's local stack reads."""

    timestamp_s: float
    decision: Decision
    near_blocks: object
    geometry: object
    refined: object = None


def _switched_to_offboard(cfg: CompanionConfig) -> tuple[Supervisor, VehicleState, float, _Seen]:
    """A supervisor asked to engage a vehicle hovering at 1.5 m in Position mode, fed clear frames
    with no valid block for 0.6 s, and the vehicle then switched to Offboard (not yet stepped).
    Returns (supervisor, vehicle, time s, that blind frame)."""
    sup = Supervisor(SupervisorConfig.from_config(cfg))
    clear = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear")
    v = VehicleState(connected=True, armed=True, flight_mode="POSCTL", in_offboard=False,
                     position_ned_m=np.array([0.0, 0.0, -1.5]), velocity_ned_m_s=np.zeros(3),
                     attitude_rad=np.zeros(3), position_timestamp_s=0.0)
    now = 0.0
    blind = _Seen(now, clear, np.full(BLOCKS, np.nan, dtype=np.float32), GEOM)
    sup.step(now, blind, v, [Engage()], camera_ok=True)
    for _ in range(12):
        now += 0.05
        v = replace(v, position_timestamp_s=now)
        sup.step(now, replace(blind, timestamp_s=now - 0.02), v, [], camera_ok=True)
    return sup, replace(v, flight_mode="OFFBOARD", in_offboard=True), now, blind


def test_the_service_flies_the_local_stack() -> None:
    """The supervisor's engaged step runs the local stack: frames enter its map from the pose at
    capture, and the setpoint is the stack's (forward into space seen free; zero before any is
    seen). A dead end the planner holds pauses the flight with the planner's reason, and holds the
    point where it stopped (told
    zero velocity, PX4 crept on at 0.2 m/s after a stop from 3 m/s and touched the dead end's wall);
    the operator's resume flies again."""
    cfg = CompanionConfig.model_validate({"envelope": {"max_horizontal_speed_m_s": 4.0}})
    sup, v, now, blind = _switched_to_offboard(cfg)
    clear = blind.decision
    at = np.array(v.position_ned_m)
    now += 0.05
    out = sup.step(now, replace(blind, timestamp_s=now - 0.02), v, [], camera_ok=True)
    assert out.state is State.ENGAGED
    assert out.setpoint is not None and out.setpoint.forward_m_s == 0.0  # nothing seen free: no motion
    for _ in range(4):
        now += 0.05
        v = replace(v, position_timestamp_s=now)
        seen = _Seen(now - 0.01, clear, _wall_blocks(30.0), GEOM)
        out = sup.step(now, seen, v, [], camera_ok=True)
    assert out.setpoint is not None and out.setpoint.forward_m_s > 0.5
    # The health message says what the planner does and why.
    status = sup.planner_status()
    assert status is not None and status["mode"] == "cruise" and "seen free" in status["reason"], status
    assert status["speed_m_s"] > 0.5 and status["free_m"] > 1.0, status
    assert status["limited_by"] == [], status  # open space ahead: flown as planned
    # The planner declares a dead end: the service pauses (zero velocity) and says why.
    planner = sup._flight.stack.planner
    planner.mode, planner.reason = Mode.HOLD, "dead end: no direction within 100 deg of the goal is free for 1.5 m"
    now += 0.05
    v = replace(v, position_timestamp_s=now)
    out = sup.step(now, _Seen(now - 0.01, clear, _wall_blocks(30.0), GEOM), v, [], camera_ok=True)
    assert out.state is State.PAUSED and "dead end" in out.reason
    assert out.setpoint is not None and out.setpoint.forward_m_s == 0.0
    assert sup.planner_status()["mode"] == "hold" and "dead end" in sup.planner_status()["reason"]
    # Creeping on toward the wall at 0.2 m/s: back to the held point, without turning.
    for k in range(1, 21):
        now += 0.05
        v = replace(v, position_ned_m=at + np.array([0.01 * k, 0.0, 0.0]), velocity_ned_m_s=np.array([0.2, 0.0, 0.0]),
                    position_timestamp_s=now)
        out = sup.step(now, _Seen(now - 0.01, clear, _wall_blocks(30.0), GEOM), v, [], camera_ok=True)
    assert out.state is State.PAUSED and "dead end" in out.reason
    assert out.setpoint is not None and out.setpoint.forward_m_s < -0.15 and out.setpoint.yaw_rate_deg_s == 0.0
    now += 0.05
    out = sup.step(now, _Seen(now - 0.01, clear, _wall_blocks(30.0), GEOM), v, [Resume()], camera_ok=True)
    assert out.state is State.ENGAGED and planner.mode is not Mode.HOLD
    assert out.setpoint is not None and out.setpoint.forward_m_s > 0.5


def test_the_service_s_watchdog_lets_the_local_planner_go_round_away_from_the_goal() -> None:
    """Flying back from the goal is no stall by itself: the planner's way round can lead away from
    the goal for seconds (PX4 SITL flights turning along an office's wall). Only no progress in the
    time to fly planner.no_progress_distance_m at cruise holds."""
    def fly_back() -> State:
        cfg = CompanionConfig.model_validate({"envelope": {"max_horizontal_speed_m_s": 4.0}})
        sup, v, now, blind = _switched_to_offboard(cfg)
        clear, start = blind.decision, now
        for _ in range(200):  # 10 s flying south, away from the course ahead, at 0.5 m/s
            now += 0.05
            v = replace(v, position_ned_m=np.array([-0.5 * (now - start), 0.0, -1.5]),
                        velocity_ned_m_s=np.array([-0.5, 0.0, 0.0]), position_timestamp_s=now)
            seen = _Seen(now - 0.01, clear, _wall_blocks(30.0), GEOM)
            out = sup.step(now, seen, v, [], camera_ok=True)
            if out.state is not State.ENGAGED:
                break
        return out.state

    assert fly_back() is State.ENGAGED


@pytest.mark.parametrize("cruise_m_s", [3.0, 0.7])
def test_the_local_planner_s_watchdog_gives_a_slower_cruise_the_same_way_round(cruise_m_s: float) -> None:
    """The progress watchdog of the local planner is a distance at cruise
    (``planner.no_progress_distance_m``): a vehicle that gets no nearer its goal is held once it has
    had the time to fly that far at cruise, whatever the cruise. A 20 s limit at every cruise held
    detours at walking pace while they were still coming back from the wrong side of a wall (the
    same way round at 3 m/s took 8 s), so 0.7 m/s got 86 s."""
    cfg = CompanionConfig.model_validate(
        {"planner": {"cruise_speed_m_s": cruise_m_s}, "envelope": {"max_horizontal_speed_m_s": 4.0}}
    )
    limit_s = cfg.planner.no_progress_distance_m / cruise_m_s
    sup, v, now, blind = _switched_to_offboard(cfg)
    start = now
    paused_at = None
    while now - start < limit_s + 2.0:  # hovering beside the way, no nearer the goal ahead
        now += 0.1
        v = replace(v, position_timestamp_s=now)
        out = sup.step(now, replace(blind, timestamp_s=now - 0.02), v, [], camera_ok=True)
        if out.state is State.PAUSED:
            paused_at = now - start
            break
        assert out.state is State.ENGAGED, (out.state, out.reason)
    assert paused_at is not None and limit_s - 1.0 <= paused_at <= limit_s + 1.0, (paused_at, limit_s)
    assert f"{cfg.planner.no_progress_distance_m:g} m at {cruise_m_s:g} m/s" in out.reason, out.reason
    assert "no progress" in out.reason  # the announcement reads the watchdog by it


def test_a_descent_cut_by_the_floor_flies_on_under_an_overhead_block() -> None:
    """Simulated pitch courses: a block overhead whose bottom edge is too low to pass at the cruise
    altitude, open beneath. Every way under it descends to the floor before it is past; counted as
    closed there, the planner flew along the block and was held by the watchdog. A descent cut by the
    floor levels off along it: it is closed only where that level line meets a surface."""
    m = _map()
    edge_row = 28  # the block's bottom edge: 1.25 m high at 2.5 m ahead, seen from 1.5 m
    blocks = np.full(BLOCKS, GEOM.focal_baseline_px_m / 2.5, dtype=np.float32)
    blocks[edge_row:] = GEOM.focal_baseline_px_m / 20.0  # beneath it, open beyond the map's range
    _see(m, blocks)
    cfg = PlannerConfig()
    alt = 1.5
    # The level line is closed by the block; the steepest descent passes beneath it and meets the floor.
    down = math.radians(-cfg.max_climb_deg)
    level_free = m.free_lengths(np.array([0.0, 0.0, -alt]), NORTH)
    assert level_free.blocked[0] and level_free.length_m[0] < 2.5
    to_floor = (alt - cfg.floor_m) / math.sin(-down)
    steep = m.free_lengths(np.array([0.0, 0.0, -alt]), np.array([[math.cos(down), 0.0, -math.sin(down)]]))
    assert steep.length_m[0] > to_floor
    p = LocalPlanner(cfg, 0.25)
    plan = p.plan(_snap(), m)
    assert plan.mode is not Mode.HOLD, plan.reason
    v = plan.velocity_ned_m_s
    # Straight on toward the goal, descending beneath the block (not round it).
    assert v[0] > 0.5 and v[2] > 0.2 and abs(v[1]) < 0.1 * v[0], plan.reason
    # Flown at the speed law's speed on the levelled path, not braked toward the floor as toward a
    # wall (pitch-44005: a vehicle passing under a block slowed on every descent to it). Only the
    # vertical speed's limit trims it.
    u = plan.direction_ned
    to_floor_chosen = (alt - cfg.floor_m) / u[2]  # u is NED: down is positive
    assert plan.free_m > to_floor_chosen + 2.0, plan.reason
    law = speed_law(plan.free_m, cfg)
    want = law * min(1.0, cfg.max_vertical_speed_m_s / (law * u[2]))
    assert float(np.linalg.norm(v)) == pytest.approx(want)
    assert float(np.linalg.norm(v)) > speed_law(to_floor_chosen, cfg) + 0.5


def test_a_descent_cut_by_the_floor_before_a_wall_down_to_the_ground_is_closed() -> None:
    """The other side of the same principle: where the level line along the floor meets a surface (a
    wall down to the ground), the descent is closed as the wall itself is, and the way round is sought."""
    m = _map()
    _see(m, _wall_blocks(3.0))
    p = LocalPlanner(PlannerConfig(), 0.25)
    plan = p.plan(_snap(), m)
    climb = math.degrees(math.asin(-plan.direction_ned[2])) if np.linalg.norm(plan.direction_ned) else 0.0
    assert climb > -5.0, plan.reason  # no dive toward the foot of the wall


def _ground_blocks(alt_m: float) -> np.ndarray:
    """A block image of flat ground ``alt_m`` below the camera (px disparity), open above the horizon."""
    b = np.full(BLOCKS, GEOM.focal_baseline_px_m / 20.0, dtype=np.float32)
    f = GEOM.focal_px
    for r in range(BLOCKS[0]):
        down_px = (BLOCK_PX * r + 0.5 * (BLOCK_PX - 1)) - GEOM.cy_px
        if down_px > 0:
            b[r] = GEOM.focal_baseline_px_m / min(alt_m * f / down_px, 20.0)
    return b


def test_pitch_42007_a_vehicle_sinking_toward_the_floor_is_judged_on_the_path_it_levels_onto() -> None:
    """Simulated pitch courses: descending beneath an overhead block, the vehicle levelled off near the
    floor while still sinking 0.3 m/s, and the chain's speed law judged that motion on the straight
    line into the ground 2.7 m on: the setpoint's forward speed fell from 3 to 1.6 m/s under an open
    way. The floor filter takes a descent off over the last metre: a motion reaching the floor before
    any surface levels off there and flies on, as a planned descent does."""
    alt = 0.7
    m = _map()
    _see(m, _ground_blocks(alt), pose=Pose.at(0.0, 0.0, alt))
    pos = np.array([0.0, 0.0, -alt])
    sinking = np.array([[math.cos(math.radians(11.0)), 0.0, math.sin(math.radians(11.0))]])
    line = m.free_lengths(pos, sinking)
    assert line.blocked[0] and line.length_m[0] < 2.5  # the straight line meets the ground
    floor = PlannerConfig().floor_m
    flown = floor_bent_lengths(m, pos, sinking, line.length_m, floor)
    assert flown[0] > 6.0  # levelled at the floor, the way on is open
    # A level line is as it was, and so is a descent that meets a surface before the floor.
    assert floor_bent_lengths(m, pos, NORTH, m.free_lengths(pos, NORTH).length_m, floor)[0] == pytest.approx(
        m.free_lengths(pos, NORTH).length_m[0]
    )
    assert floor_bent_lengths(m, pos, sinking, line.length_m, 0.0)[0] == pytest.approx(line.length_m[0])

    cfg = CompanionConfig.model_validate({"envelope": {"max_horizontal_speed_m_s": 4.0}})
    stack = LocalStack(cfg)
    stack.engage(pos, 0.0, None)
    for k in range(3):
        stack.add_frame(_ground_blocks(alt), GEOM, BLOCK_PX, Pose.at(0.0, 0.0, alt), 0.1 * k)
    clear = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear")
    step = stack.step(0.3, 0.05, clear, np.full(9, 10.0), pos, 2.5 * sinking[0], 0.0)
    assert step.plan.velocity_ned_m_s[0] > 2.5, step.plan.reason
    assert "speed_law_limit" not in step.limited_by
    assert step.setpoint.forward_m_s > 2.5


def test_the_visited_memory_is_the_seconds_flown_in_each_cell() -> None:
    """The seconds remembered per cell, read for many points at once, equal a plain sum per cell
    (negative cells too, each tick's time at most 0.5 s)."""
    from companion.core.planner.local import VISITED_CELL_M

    rng = np.random.default_rng(3)
    p = LocalPlanner(PlannerConfig(), 0.25)
    plain: dict[tuple[int, int], float] = {}
    t, last = 0.0, None
    for _ in range(400):
        t += float(rng.choice([0.02, 0.1, 0.9]))
        pos = np.array([*rng.uniform(-3.0, 3.0, 2), -1.5])
        p._remember(_snap(now_s=t, position_ned_m=pos))
        dt = 0.0 if last is None else min(t - last, 0.5)
        last = t
        key = (math.floor(pos[0] / VISITED_CELL_M), math.floor(pos[1] / VISITED_CELL_M))
        plain[key] = plain.get(key, 0.0) + dt
    points = np.column_stack([rng.uniform(-4.0, 4.0, (500, 2)), np.full(500, -1.5)])
    want = [plain.get((math.floor(n / VISITED_CELL_M), math.floor(e / VISITED_CELL_M)), 0.0) for n, e, _ in points]
    assert p._visited_at(points).tolist() == want
    assert LocalPlanner(PlannerConfig(), 0.25)._visited_at(points).tolist() == [0.0] * 500
