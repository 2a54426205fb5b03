"""split_side_by_side, to_grey and check_pair (companion.core.stereo)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.core.stereo import GREY_COEFFS_Q15, check_pair, split_side_by_side, to_bgr, to_grey
from companion.errors import FrameError


def _grey_formula(bgr: np.ndarray) -> np.ndarray:
    """The documented fixed-point formula, in int64."""
    cb, cg, cr = GREY_COEFFS_Q15
    b, g, r = (bgr[..., i].astype(np.int64) for i in range(3))
    return ((cb * b + cg * g + cr * r + (1 << 14)) >> 15).astype(np.uint8)


# ------------------------------------------------------------------ split


@pytest.mark.parametrize("channels", [None, 3, 4])
def test_split_shapes_and_halves(channels: int | None) -> None:
    h, w = 6, 10
    shape = (h, 2 * w) if channels is None else (h, 2 * w, channels)
    frame = np.arange(np.prod(shape), dtype=np.uint64).reshape(shape).astype(np.uint8)
    left, right = split_side_by_side(frame)
    expect = (h, w) if channels is None else (h, w, channels)
    assert left.shape == expect and right.shape == expect
    np.testing.assert_array_equal(left, frame[:, :w])
    np.testing.assert_array_equal(right, frame[:, w:])


def test_split_returns_views_not_copies() -> None:
    frame = np.zeros((4, 8, 3), np.uint8)
    left, right = split_side_by_side(frame)
    assert np.shares_memory(left, frame) and np.shares_memory(right, frame)
    frame[0, 0, 0] = 7
    frame[0, 4, 0] = 9
    assert left[0, 0, 0] == 7 and right[0, 0, 0] == 9


@settings(max_examples=30, deadline=None)
@given(h=st.integers(1, 9), w=st.integers(1, 9), ch=st.sampled_from([None, 3, 4]))
def test_split_recombines_to_the_frame(h: int, w: int, ch: int | None) -> None:
    shape = (h, 2 * w) if ch is None else (h, 2 * w, ch)
    frame = np.random.default_rng(h * 100 + w).integers(0, 256, shape, dtype=np.uint8)
    left, right = split_side_by_side(frame)
    np.testing.assert_array_equal(np.concatenate([left, right], axis=1), frame)


@pytest.mark.parametrize(
    ("frame", "words"),
    [
        (np.zeros((4, 9, 3), np.uint8), ["width 9", "odd"]),
        (np.zeros((4, 8, 3), np.float32), ["uint8", "float32"]),
        (np.zeros((4, 8, 3), np.uint16), ["uint8", "uint16"]),
        (np.zeros(8, np.uint8), ["(H, 2W", "(8,)"]),
        (np.zeros((2, 4, 8, 3), np.uint8), ["(H, 2W", "(2, 4, 8, 3)"]),
        (np.zeros((4, 8, 5), np.uint8), ["(H, 2W, 3)", "(4, 8, 5)"]),
        (np.zeros((0, 8, 3), np.uint8), ["empty"]),
        (np.zeros((4, 0), np.uint8), ["empty"]),
    ],
)
def test_split_rejects_bad_frames_with_a_clear_message(frame: np.ndarray, words: list[str]) -> None:
    with pytest.raises(FrameError) as info:
        split_side_by_side(frame)
    msg = str(info.value)
    assert "\n" not in msg
    for word in words:
        assert word in msg


def test_split_rejects_non_arrays() -> None:
    with pytest.raises(FrameError, match="NumPy array"):
        split_side_by_side([[1, 2]])  # type: ignore[arg-type]


# ------------------------------------------------------------------ to_grey


def test_grey_formula_coefficients_sum_to_one_in_q15() -> None:
    assert sum(GREY_COEFFS_Q15) == 1 << 15


def test_to_grey_matches_the_documented_formula_and_cv2_exactly() -> None:
    rng = np.random.default_rng(1234)
    bgr = rng.integers(0, 256, (257, 311, 3), dtype=np.uint8)
    # Force the extremes and rounding-sensitive corners into the sample.
    bgr[0, :8] = [[0, 0, 0], [255, 255, 255], [255, 0, 0], [0, 255, 0], [0, 0, 255], [1, 1, 1], [254] * 3, [128] * 3]
    grey = to_grey(bgr)
    assert grey.dtype == np.uint8 and grey.shape == (257, 311)
    np.testing.assert_array_equal(grey, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    np.testing.assert_array_equal(grey, _grey_formula(bgr))


def test_to_grey_bgra_ignores_alpha() -> None:
    rng = np.random.default_rng(5)
    bgra = rng.integers(0, 256, (64, 80, 4), dtype=np.uint8)
    grey = to_grey(bgra)
    np.testing.assert_array_equal(grey, _grey_formula(bgra[..., :3]))
    np.testing.assert_array_equal(grey, cv2.cvtColor(bgra, cv2.COLOR_BGRA2GRAY))


def test_to_grey_on_side_by_side_views_with_out_buffer() -> None:
    rng = np.random.default_rng(7)
    frame = rng.integers(0, 256, (48, 2 * 64, 3), dtype=np.uint8)
    left, right = split_side_by_side(frame)
    out_l = np.empty((48, 64), np.uint8)
    out_r = np.empty((48, 64), np.uint8)
    assert to_grey(left, out=out_l) is out_l
    assert to_grey(right, out=out_r) is out_r
    np.testing.assert_array_equal(out_l, _grey_formula(frame[:, :64]))
    np.testing.assert_array_equal(out_r, _grey_formula(frame[:, 64:]))


def test_to_grey_of_yuyv_is_its_luma() -> None:
    # A UVC camera's YUYV bytes undecoded (Y0 U Y1 V): the grey is the Y of each pixel, from either
    # eye's view of a side-by-side frame, with or without an out buffer.
    frame = np.random.default_rng(11).integers(0, 256, (6, 2 * 8, 2), dtype=np.uint8)
    left, right = split_side_by_side(frame)
    grey = to_grey(left)
    assert grey.shape == (6, 8) and grey.flags.c_contiguous
    np.testing.assert_array_equal(grey, frame[:, :8, 0])
    out = np.empty((6, 8), np.uint8)
    assert to_grey(right, out=out) is out
    np.testing.assert_array_equal(out, frame[:, 8:, 0])
    # The luma is what OpenCV's decoding keeps, up to its video-range stretch (255/219 about Y = 16).
    flat = np.zeros((2, 4, 2), np.uint8)
    flat[..., 0], flat[..., 1] = 126, 128  # grey: no chroma
    decoded = cv2.cvtColor(to_bgr(flat), cv2.COLOR_BGR2GRAY)
    assert abs(int(decoded[0, 0]) - round((126 - 16) * 255 / 219)) <= 1


def test_yuyv_eyes_must_be_an_even_number_of_pixels_wide() -> None:
    with pytest.raises(FrameError, match="odd number"):
        split_side_by_side(np.zeros((4, 2 * 5, 2), np.uint8))


def test_to_bgr_shows_every_frame_kind_in_colour() -> None:
    bgr = np.random.default_rng(2).integers(0, 256, (4, 6, 3), dtype=np.uint8)
    assert to_bgr(bgr) is bgr
    assert to_bgr(bgr[..., 0]).shape == (4, 6, 3)
    assert to_bgr(np.dstack([bgr, bgr[..., :1]])).shape == (4, 6, 3)
    yuyv = np.zeros((4, 6, 2), np.uint8)
    yuyv[..., 0], yuyv[..., 1] = 235, 128  # white in BT.601 video range
    assert to_bgr(yuyv).min() >= 254
    with pytest.raises(FrameError, match="YUYV of even width"):
        to_bgr(np.zeros((4, 5, 2), np.uint8))
    with pytest.raises(FrameError, match="uint8"):
        to_bgr(np.zeros((4, 6, 3), np.float32))


def test_to_grey_passes_grey_through() -> None:
    grey = np.random.default_rng(3).integers(0, 256, (10, 12), dtype=np.uint8)
    assert to_grey(grey) is grey
    out = np.empty_like(grey)
    assert to_grey(grey, out=out) is out
    np.testing.assert_array_equal(out, grey)


@pytest.mark.parametrize(
    ("image", "out", "words"),
    [
        (np.zeros((4, 4, 3), np.float32), None, ["uint8", "float32"]),
        (np.zeros((4, 4, 5), np.uint8), None, ["(H, W, 3)", "(4, 4, 5)"]),
        (np.zeros((0, 4, 3), np.uint8), None, ["empty"]),
        (np.zeros((4, 4, 3), np.uint8), np.zeros((4, 5), np.uint8), ["output buffer", "(4, 5)"]),
        (np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4), np.float32), ["output buffer", "float32"]),
    ],
)
def test_to_grey_rejects_bad_input(image: np.ndarray, out: np.ndarray | None, words: list[str]) -> None:
    with pytest.raises(FrameError) as info:
        to_grey(image, out=out)
    for word in words:
        assert word in str(info.value)


# ------------------------------------------------------------------ check_pair


def test_check_pair_accepts_equal_pairs() -> None:
    check_pair(np.zeros((4, 6), np.uint8), np.ones((4, 6), np.uint8))


def test_check_pair_names_both_sizes() -> None:
    with pytest.raises(FrameError) as info:
        check_pair(np.zeros((376, 672), np.uint8), np.zeros((720, 1280), np.uint8))
    msg = str(info.value)
    assert "672x376" in msg and "1280x720" in msg


def test_check_pair_names_both_dtypes() -> None:
    with pytest.raises(FrameError) as info:
        check_pair(np.zeros((4, 6), np.uint8), np.zeros((4, 6), np.float32))
    msg = str(info.value)
    assert "uint8" in msg and "float32" in msg
