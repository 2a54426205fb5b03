"""The way to the goal on the local map (round the surfaces seen, over what the camera saw over), and
walking-pace flights that the way and the sideways margin changed."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import parse_config
from companion.core.geometry import StereoGeometry
from companion.core.planner.localmap import LocalMap
from companion.core.planner.paths import bend_onto_way, directions
from companion.core.planner.way import WayToGoal
from companion.core.pose import Pose
from companion.sim.courses import make_course
from companion.sim.loop import fly
from companion.sim.scoring import Outcome

GEOM = StereoGeometry.ideal(336, 188, 90.0, 0.12)
BLOCK_PX = 4
BLOCKS = (47, 84)
GOAL = np.array([10.0, 0.0, -1.5])


def _blocks(depth_m: float) -> np.ndarray:
    return np.full(BLOCKS, GEOM.focal_baseline_px_m / depth_m, dtype=np.float32)


def _column_of(east_m: float, north_m: float) -> int:
    """The block column that sees east ``east_m`` at north ``north_m`` from the origin, facing north."""
    return int((GEOM.width_px / 2 + GEOM.focal_px * east_m / north_m) // BLOCK_PX)


def _seen(blocks: np.ndarray) -> LocalMap:
    m = LocalMap(voxel_m=0.15, range_m=8.0, radius_m=0.25, occupied_memory_s=20.0, free_memory_s=6.0)
    for k in range(3):
        m.integrate(blocks, GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), 0.1 * k, 64)
    return m


def _wall_with_gap() -> LocalMap:
    """A wall 3 m north from floor to ceiling across the view, a gap in it from 2.5 to 1.5 m west."""
    b = _blocks(3.0)
    b[:, _column_of(-2.5, 3.0) : _column_of(-1.5, 3.0)] = GEOM.focal_baseline_px_m / 20.0
    return _seen(b)


def test_beside_a_wall_the_way_leads_to_the_gap_seen_in_it() -> None:
    """The goal lies straight through the wall (seen 3 m each side of the line; past that, unknown); as
    the crow flies, a metre east along the wall and a metre west toward the gap are alike. The way is
    not: it leads west, and a line's end toward the gap has less of it left."""
    m = _wall_with_gap()
    way = WayToGoal()
    way.update(m, GOAL, -1.5, 0.5, 3.0)
    here = np.array([2.1, -0.5, -1.5])
    bearing = way.bearing(here)
    assert bearing is not None
    assert math.sin(bearing) < -0.5  # west of north, toward the gap
    east, west = way.length_at(np.array([[2.1, 1.0, -1.5], [2.1, -1.0, -1.5]]))
    assert west < east
    straight = math.hypot(*(GOAL[:2] - here[:2]))
    assert way.length_at(here[None, :])[0] > straight + 1.0  # round the wall, not through it


def test_a_line_into_a_wall_is_scored_on_along_the_way_to_the_gap_from_where_it_would_stop() -> None:
    """The goal lies through the wall; the line straight at it ends at the wall's radius. The vehicle
    flying it would stop a stop margin short and turn along the way, toward the gap: that bent path is
    what it leads to, longer than the line. A line that leads away from the way is not bent onto it."""
    m = _wall_with_gap()
    way = WayToGoal()
    way.update(m, GOAL, -1.5, 0.5, 3.0)
    here = np.array([0.0, 0.0, -1.5])
    yaw = np.radians([0.0, 180.0])
    dirs = directions(yaw, np.zeros(2))
    fl = m.free_lengths(here, dirs)
    assert fl.blocked[0] and fl.length_m[0] < 3.0  # the line meets the wall
    path, blocked = fl.length_m.copy(), fl.blocked.copy()
    knee, onward = np.full(2, np.inf), dirs.copy()
    bend_onto_way(m, way, here, yaw, dirs, np.ones(2, bool), 0.0, float(GOAL[0]), 0.3, blocked, path, knee, onward)
    assert knee[0] == pytest.approx(fl.length_m[0] - 0.3)  # where the speed law stops on the line
    assert onward[0, 1] < -0.5  # on toward the gap, west
    assert path[0] > fl.length_m[0] + 1.0
    assert not np.isfinite(knee[1]) and path[1] == fl.length_m[1]  # south: away from the way, unbent


def test_corridor_32004_beside_a_box_flies_round_it_instead_of_dithering_until_the_watchdog() -> None:
    """corridor-32004 with 0.14 m/s drift at 3 m/s with the GPU's matcher (``cpu-sgm`` makes its
    disparities bit for bit): 1.5 m short of its first box (1.2 m wide, near the middle of a corridor
    4.2 m wide), the lines toward either side ended at the box's or the walls' radius and were scored
    as stops there; the vehicle turned from one to another and wandered back for 40 s until the
    no-progress watchdog held it (PX4 SITL's corridor-4 did the same). A line into the box now leads
    on along the way round it, from where it would stop, and the flight reaches the goal."""
    cfg = parse_config({"stereo": {"backend": "cpu-sgm"}, "sim": {"drift_speed_m_s": 0.14}})
    result = fly(make_course("corridor", 32004), cfg)
    assert result.outcome is Outcome.GOAL, result.reason


def _crossing_east_m(way: WayToGoal, here: np.ndarray, wall_north_m: float) -> float:
    """Where the way's walk down its distances from ``here`` crosses north ``wall_north_m``, east m."""
    from companion.core.planner import _waykernels as k

    i, j, _ = way._cell(here[None, :])
    path = np.zeros((60, 2), dtype=np.int64)
    n = k.descend(way.dist, int(i[0]), int(j[0]), 60, path)
    centres = (path[:n] + 0.5 + way._origin) * way._cell_m
    at_wall = centres[np.abs(centres[:, 0] - wall_north_m) <= 0.5 * way._cell_m]
    assert len(at_wall) > 0
    return float(at_wall[0, 1])


def test_doorway_1_the_way_goes_through_the_middle_of_a_door_off_the_line() -> None:
    """ArduPilot SITL, doorway-1 at 3 m/s: a door 1.15 m wide centred 0.22 m east of the line. The
    shortest way bent round the west jamb at the edge of its radius; the free length of the lines
    there flickered from frame to frame, and ArduCopter's response to that swung the vehicle onto the
    jamb. With the stop margin kept off surfaces the way crosses the door within a cell of its middle,
    wherever the door sits; without it, at the edge nearest the line."""
    here = np.array([0.5, 0.0, -1.5])
    for centre in (-0.22, 0.1, 0.22, 0.3):
        b = _blocks(3.0)
        b[:, _column_of(centre - 0.575, 3.0) : _column_of(centre + 0.575, 3.0)] = GEOM.focal_baseline_px_m / 20.0
        m = _seen(b)
        way = WayToGoal()
        way.update(m, GOAL, -1.5, 0.5, 3.0, clearance_m=0.25 + 0.3)
        assert abs(_crossing_east_m(way, here, 3.15) - centre) <= 0.15, centre
        if centre == 0.3:
            edge = WayToGoal()
            edge.update(m, GOAL, -1.5, 0.5, 3.0, clearance_m=0.0)
            assert abs(_crossing_east_m(edge, here, 3.15) - centre) > 0.15


def test_a_low_wall_the_camera_saw_over_is_no_way_round() -> None:
    """The same wall but only up to 1.3 m, the space over it seen free: the way is straight over it
    (the planner climbs), not along it to the gap."""
    b = _blocks(20.0)
    horizon = int(GEOM.height_px / 2 // BLOCK_PX)
    b[horizon + 2 :, :] = GEOM.focal_baseline_px_m / 3.0  # below the camera's height only
    m = _seen(b)
    way = WayToGoal()
    way.update(m, GOAL, -1.5, 0.5, 3.0)
    bearing = way.bearing(np.array([1.5, 0.0, -1.5]))
    assert bearing is not None and abs(math.degrees(bearing)) < 10.0


def test_without_a_map_or_off_its_grid_there_is_no_way_and_the_caller_keeps_the_straight_line() -> None:
    way = WayToGoal()
    assert way.bearing(np.zeros(3)) is None
    assert np.isnan(way.length_at(np.zeros((1, 3)))).all()
    m = _wall_with_gap()
    way.update(m, GOAL, -1.5, 0.5, 3.0)
    assert np.isnan(way.length_at(np.array([[500.0, 0.0, -1.5]]))).all()


WALKING = {"stereo": {"backend": "opencv-bm"}, "sim": {"drift_speed_m_s": 0.14}, "planner": {"cruise_speed_m_s": 0.7}}


def test_a_walking_pace_detour_goes_back_to_the_gap_it_saw_instead_of_along_the_wall() -> None:
    """detour-3000 at 0.7 m/s with 0.14 m/s drift: the vehicle took the east side of the wall (the gap
    was 3 m west) and, judging progress as the crow flies, followed the wall out of the course. On
    the way round the surfaces seen, the gap is nearer, and it turns back to it."""
    result = fly(make_course("detour", 3000), parse_config(WALKING))
    assert result.outcome is Outcome.GOAL, result.reason
    assert result.time_s < 25.0  # not the long way round


def test_passing_a_trunk_while_drifting_keeps_the_margin_sideways() -> None:
    """forest-3002 at 0.7 m/s, drifting up to 0.3 m/s: it passed a trunk 5 cm outside the map's
    inflation and touched it. Within the stop margin of the nearest surface the setpoint now moves
    the vehicle off it."""
    result = fly(make_course("forest", 3002), parse_config(WALKING))
    assert result.outcome is Outcome.GOAL, result.reason
    assert result.min_clearance_m > 0.15


def test_a_frame_that_leaves_the_closed_columns_as_they_were_keeps_the_distances() -> None:
    """The map changes with every frame, its closed columns at one level seldom: the way's search
    runs again only when they (or the goal, the level or the grid's place) change, and the distances
    it keeps are those a fresh way makes."""
    from companion.core.planner import _waykernels as k

    m = _wall_with_gap()
    way = WayToGoal()
    way.update(m, GOAL, -1.5, 0.5, 3.0, 0.4)
    kept = way.dist.copy()
    runs = []
    original = k.dijkstra

    def counted(*args):
        runs.append(1)
        return original(*args)

    k.dijkstra = counted
    try:
        version = m.version
        b = _blocks(3.0)
        b[:, _column_of(-2.5, 3.0) : _column_of(-1.5, 3.0)] = GEOM.focal_baseline_px_m / 20.0
        m.integrate(b, GEOM, BLOCK_PX, Pose.at(0.0, 0.0, 1.5), 0.4, 64)  # the same wall seen again
        assert m.version > version
        way.update(m, GOAL, -1.5, 0.5, 3.0, 0.4)
        assert runs == [] and np.array_equal(way.dist, kept)
        way.update(m, GOAL + np.array([0.0, 1.0, 0.0]), -1.5, 0.5, 3.0, 0.4)  # a new goal: searched again
        assert runs == [1]
    finally:
        k.dijkstra = original
    fresh = WayToGoal()
    fresh.update(m, GOAL + np.array([0.0, 1.0, 0.0]), -1.5, 0.5, 3.0, 0.4)
    np.testing.assert_array_equal(way.dist, fresh.dist)


def _bearing_numpy(blocked: np.ndarray, here: np.ndarray, path: np.ndarray) -> int:
    """The walk's farthest cell in plain view, as whole-array NumPy (the compiled kernel's statement)."""
    target = (path + 0.5).astype(np.float64)
    span = np.linalg.norm(target - here, axis=1)
    m = int(np.ceil(span.max() * 2.0)) + 1
    t = np.linspace(0.0, 1.0, m)
    samples = here[None, None, :] + (target - here)[:, None, :] * t[None, :, None]
    si = np.clip(np.floor(samples[..., 0]).astype(np.int64), 0, blocked.shape[0] - 1)
    sj = np.clip(np.floor(samples[..., 1]).astype(np.int64), 0, blocked.shape[1] - 1)
    open_ = ~blocked[si, sj]
    open_[:, 0] = True
    clear = open_.all(axis=1)
    return int(np.nonzero(clear)[0].max()) if clear.any() else 0


def test_the_compiled_line_of_sight_equals_numpy_on_random_grids() -> None:
    from companion.core.planner import _waykernels as k

    rng = np.random.default_rng(5)
    seen = set()
    for _ in range(300):
        blocked = rng.random((30, 30)) < rng.uniform(0.0, 0.3)
        here = rng.uniform(0.0, 30.0, size=2)
        steps = rng.integers(-1, 2, size=(int(rng.integers(1, 20)), 2))
        path = np.clip(np.floor(here).astype(np.int64) + np.cumsum(steps, axis=0), 0, 29)
        expected = _bearing_numpy(blocked, here, path)
        assert k.farthest_in_view(blocked, here[0], here[1], path) == expected
        seen.add(expected == len(path) - 1)
    assert seen == {True, False}


def _dijkstra_heapq(blocked: np.ndarray, start: np.ndarray, cell_m: float, penalty: np.ndarray) -> np.ndarray:
    """The way's distances stated plainly: Python's heap, the same 8 steps and the same sums."""
    import heapq

    nx, ny = blocked.shape
    out = np.full((nx, ny), np.inf)
    heap = []
    for i in range(nx):
        for j in range(ny):
            if not blocked[i, j] and start[i, j] < np.inf:
                out[i, j] = start[i, j]
                heap.append((float(start[i, j]), i, j))
    heapq.heapify(heap)
    diag = cell_m * math.sqrt(2.0)
    while heap:
        d, i, j = heapq.heappop(heap)
        if d > out[i, j]:
            continue
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                p, q = i + di, j + dj
                if (di, dj) == (0, 0) or not (0 <= p < nx and 0 <= q < ny) or blocked[p, q]:
                    continue
                nd = d + (diag if di and dj else cell_m) * (1.0 + penalty[p, q])
                if nd < out[p, q]:
                    out[p, q] = nd
                    heapq.heappush(heap, (nd, p, q))
    return out


def test_the_compiled_search_equals_a_plain_dijkstra_on_random_grids() -> None:
    from companion.core.planner import _waykernels as k

    rng = np.random.default_rng(11)
    for _ in range(60):
        nx, ny = (int(v) for v in rng.integers(1, 40, size=2))
        blocked = rng.random((nx, ny)) < rng.uniform(0.0, 0.5)
        start = np.where(rng.random((nx, ny)) < 0.05, rng.uniform(0.0, 20.0, (nx, ny)), np.inf)
        penalty = np.where(rng.random((nx, ny)) < 0.5, rng.uniform(0.0, 3.0, (nx, ny)), 0.0)
        out = np.empty((nx, ny))
        keys = np.empty(8 * nx * ny + 1)
        cells = np.empty(8 * nx * ny + 1, dtype=np.int64)
        k.dijkstra(blocked, start, 0.3, penalty, out, keys, cells)
        np.testing.assert_array_equal(out, _dijkstra_heapq(blocked, start, 0.3, penalty))


def test_office_25008_a_door_reached_off_its_middle_is_flown_through_not_held_as_a_dead_end() -> None:
    """office-25008 at 3 m/s with the GPU's matcher (``cpu-sgm`` makes its disparities bit for bit): the
    vehicle reached the far wall's door 0.4 m off its middle at speed and braked a step from the wall;
    from there every line within 100° of the goal met the radius of a jamb or of the wall within
    1.5 m, and it held a dead end while the way round the surfaces seen led on through the door. A dead
    end is now one where the way does not lead on within the cone either."""
    cfg = parse_config({"stereo": {"backend": "cpu-sgm"}})
    result = fly(make_course("office", 25008), cfg)
    assert result.outcome is Outcome.GOAL, result.reason


def test_a_closed_channel_started_inside_with_its_sides_unseen_is_still_held() -> None:
    """The dead end's other half: started inside a closed channel, with its sides beside and behind
    the vehicle unseen at first (the way counts unknown space open), the channel is still held as a
    dead end once seen closed."""
    cfg = parse_config({"stereo": {"backend": "cpu-sgm"}})
    result = fly(make_course("deadend", 25008), cfg)
    assert result.outcome is Outcome.HELD, result.reason
    assert "dead end" in result.hold_reason
