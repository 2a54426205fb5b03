"""The map's input: the disparity reduced to blocks of the nearest surface, eroded along rows first.

The erosion takes off what a semi-global matcher smears past a surface's edge and a lone false match,
and keeps a thin upright thing (a fence's bar) that a plain erosion would take off whole.
"""

from __future__ import annotations

import numpy as np
import pytest

from companion.core.blocks import BlockMax, RowErosion, block_max, erode_rows

_FAR, _NEAR = 4.0, 16.0  # px: a wall about 4 m off and a surface about 1 m off with the 336x188 rig


def _row_erosion_numpy(disparity: np.ndarray, k: int) -> np.ndarray:
    """RowErosion's rule as whole-array NumPy, float32 throughout: the statement its kernel must equal."""
    d = disparity.astype(np.float32)
    h, w = d.shape
    d[np.isnan(d)] = -np.inf  # invalid: the smallest, as -1 on the device
    e = d.copy()
    for j in range(1, min(k, w - 1) + 1):
        np.minimum(e[:, j:], d[:, :-j], out=e[:, j:])
        np.minimum(e[:, :-j], d[:, j:], out=e[:, :-j])
    d7, d8 = d * np.float32(7), d * np.float32(8)
    left, right = np.zeros((h, w), bool), np.zeros((h, w), bool)
    for j in range(1, min(2 * k, w - 1) + 1):
        left[:, j:] |= d8[:, :-j] < d7[:, j:]
        right[:, :-j] |= d8[:, j:] < d7[:, :-j]
    near = d.copy()  # each pixel's nearest within one column in its row
    if w > 1:
        np.maximum(near[:, 1:], d[:, :-1], out=near[:, 1:])
        np.maximum(near[:, :-1], d[:, 1:], out=near[:, :-1])
    s = d.copy()
    if h > 1:
        np.minimum(s[1:], near[:-1], out=s[1:])
        np.minimum(s[:-1], near[1:], out=s[:-1])
    out = np.where(left & right, np.maximum(e, s), e)
    out[out == -np.inf] = np.nan
    return out


def _wall(h: int = 12, w: int = 40) -> np.ndarray:
    return np.full((h, w), _FAR, dtype=np.float32)


@pytest.mark.parametrize("width_px", [1, 2])
def test_a_thin_upright_bar_in_front_of_a_wall_keeps_its_depth(width_px: int) -> None:
    """A bar narrower than 2k + 1 px standing in front of the wall, the full height of the image:
    the eroded image keeps it, so the map's blocks see it (a plain erosion left only the wall)."""
    d = _wall()
    d[:, 20:20 + width_px] = _NEAR
    out = erode_rows(d, 1)
    np.testing.assert_array_equal(out[:, 20:20 + width_px], _NEAR)
    assert np.all(np.delete(out, range(20, 20 + width_px), axis=1) == _FAR)
    assert block_max(d, 4, 1)[:, 5].tolist() == [_NEAR] * 3


def test_a_bar_against_unseen_space_keeps_its_depth() -> None:
    """Invalid pixels (a plain wall, the sky) beside the bar count as farther: it is kept."""
    d = np.full((6, 20), np.nan, dtype=np.float32)
    d[:, 9] = _NEAR
    np.testing.assert_array_equal(erode_rows(d, 1)[:, 9], _NEAR)


def test_a_smeared_edge_is_taken_off_and_the_surface_loses_k_pixels() -> None:
    """A near surface (columns 10..19) whose disparity the matcher smeared 1 px onto the wall behind
    it (column 20): the smear goes, and with it one pixel at each side of the surface."""
    d = _wall()
    d[:, 10:21] = _NEAR
    out = erode_rows(d, 1)
    near = np.flatnonzero(out[5] == _NEAR)
    assert near.tolist() == list(range(11, 20))


def test_a_slanted_surface_is_eroded_like_a_flat_one() -> None:
    """A wall seen obliquely changes its disparity by far less than an eighth over 2 px: its edge
    pixel is not thin, and is taken off like a flat surface's."""
    d = _wall()
    d[:, 10:20] = np.linspace(12.0, 13.0, 10, dtype=np.float32)
    out = erode_rows(d, 1)
    assert out[5, 19] == _FAR and out[5, 10] == _FAR
    assert out[5, 18] == d[5, 17]


def test_a_lone_false_match_and_a_short_streak_are_taken_off() -> None:
    """A single too-near pixel, and a streak two rows tall, have no row above and below them that
    sees something as near: both go."""
    d = _wall()
    d[5, 8] = _NEAR
    d[3:5, 30] = _NEAR
    out = erode_rows(d, 1)
    assert np.all(out == _FAR)


def test_a_bar_leaning_a_pixel_per_row_keeps_its_depth() -> None:
    """The rows above and below count within one pixel of the column: a bar leaning up to 45° (a
    pole seen with the vehicle rolled) is still tall."""
    d = _wall(h=10)
    for y in range(10):
        d[y, 10 + y] = _NEAR
    out = erode_rows(d, 1)
    assert all(out[y, 10 + y] == _NEAR for y in range(10))


def test_a_thin_bar_keeps_no_more_than_the_rows_beside_it_see() -> None:
    """Where the rows above and below see the bar farther than this row does, the pixel counts only
    as near as they see it (never nearer than itself)."""
    d = _wall(h=3)
    d[:, 20] = [10.0, 16.0, 12.0]
    out = erode_rows(d, 1)
    assert out[1, 20] == 10.0


def test_the_erosion_reuses_its_buffers_and_leaves_its_input() -> None:
    d = _wall()
    d[:, 20] = _NEAR
    before = d.copy()
    erosion = RowErosion(d.shape, 1)
    first = erosion(d)
    assert erosion(d) is first
    np.testing.assert_array_equal(first, _row_erosion_numpy(d, 1))
    np.testing.assert_array_equal(d, before)
    with pytest.raises(ValueError, match="erode_px"):
        RowErosion(d.shape, 0)
    with pytest.raises(ValueError, match="disparity must be"):
        erosion(d[:, :10])


@pytest.mark.parametrize(("h", "w", "k", "b"), [(19, 50, 1, 4), (19, 50, 2, 3), (7, 9, 4, 4), (1, 12, 1, 2), (8, 1, 1, 4)])
@pytest.mark.parametrize("fixed_point", [True, False])
def test_the_compiled_erosion_equals_the_numpy_statement(h: int, w: int, k: int, b: int, fixed_point: bool) -> None:
    """On random images: the matchers' sixteenths (thin pixels, ties and invalid ones everywhere) and
    arbitrary floats (where 7·d rounds in float32); and the blocks of it, with partial edge blocks."""
    rng = np.random.default_rng([h, w, k])
    if fixed_point:
        d = rng.integers(0, 64 * 16, (h, w)).astype(np.float32) / np.float32(16)
    else:
        d = rng.uniform(1.0, 30.0, (h, w)).astype(np.float32)
    d[rng.random(d.shape) < 0.2] = np.nan
    want = _row_erosion_numpy(d, k)
    np.testing.assert_array_equal(erode_rows(d, k), want)
    np.testing.assert_array_equal(BlockMax(d.shape, b, k)(d), block_max(want, b))


def test_office_31001_a_fence_of_thin_bars_is_seen_and_not_flown_into() -> None:
    """office-31001 with 0.14 m/s drift, realization 2, at 3 m/s with the GPU's matcher (``cpu-sgm``
    makes its disparities bit for bit): a see-through fence of bars 2-3 cm wide, 8 cm apart. The
    plain row erosion took off every bar narrower than 3 px (beyond about a metre), the rays seen
    through the gaps cleared the fence's cubes, and the vehicle flew into it at 1.5 m/s 4.6 s in. The
    bars are thin upright things now, kept; the first 10 s pass with room to spare."""
    import dataclasses

    from companion.config import parse_config
    from companion.sim.courses import make_course
    from companion.sim.loop import fly

    cfg = parse_config({"stereo": {"backend": "cpu-sgm"}, "sim": {"drift_speed_m_s": 0.14, "realization": 2}})
    course = dataclasses.replace(make_course("office", 31001), time_limit_s=10.0)
    result = fly(course, cfg)
    assert result.min_clearance_m > 0.1, result.reason
