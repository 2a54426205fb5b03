"""Depth LUT and release filter."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config.core import LutConfig
from companion.core.lut import DepthLUT, release_filter

# --------------------------------------------------------------------------------------------------
# LUT


def test_lut_interpolates_and_clamps() -> None:
    lut = DepthLUT([(0.5, 0.6), (1.0, 1.2), (3.0, 2.8)])
    got = lut.apply(np.array([0.5, 0.75, 1.0, 2.0, 3.0]))
    np.testing.assert_allclose(got, [0.6, 0.9, 1.2, 2.0, 2.8])
    np.testing.assert_allclose(lut.apply(np.array([0.1, 0.0, 10.0, np.inf])), [0.6, 0.6, 2.8, 2.8])


def test_lut_preserves_nan_shape_and_dtype() -> None:
    lut = DepthLUT([(0.5, 0.6), (3.0, 2.8)])
    d = np.array([[np.nan, 1.0], [np.inf, np.nan]], dtype=np.float32)
    got = lut.apply(d)
    assert got.shape == (2, 2) and got.dtype == np.float32
    assert np.isnan(got[0, 0]) and np.isnan(got[1, 1]) and got[1, 0] == np.float32(2.8)
    assert lut.apply(np.array([np.nan, 2.0])).dtype == np.float64


def test_lut_default_config_is_identity() -> None:
    lut = DepthLUT.from_config(LutConfig())
    d = np.array([0.2, 1.0, 7.5, 40.0])
    np.testing.assert_allclose(lut.apply(d), d)


@pytest.mark.parametrize(
    ("points", "match"),
    [
        ([(1.0, 1.0)], "at least 2"),
        ([(1.0, 1.0), (1.0, 2.0)], r"point 1 \(1.0, 2.0\): computed depth"),
        ([(1.0, 1.0), (2.0, 2.0), (3.0, 1.5)], r"point 2 \(3.0, 1.5\): true depth"),
        ([(1.0, 1.0), (2.0, 2.0), (1.5, 3.0)], r"point 2 \(1.5, 3.0\): computed depth"),
        ([(0.0, 1.0), (2.0, 2.0)], r"point 0 \(0.0, 1.0\).*positive"),
        ([(1.0, 1.0), (math.inf, 2.0)], r"point 1 .*finite"),
    ],
)
def test_lut_rejects_bad_tables(points: list[tuple[float, float]], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        DepthLUT(points)


# --------------------------------------------------------------------------------------------------
# Release filter


def test_release_filter_behaviour() -> None:
    prev = np.array([1.0, 3.0, np.nan, 2.0, 2.0])
    new = np.array([2.0, 1.0, 4.0, np.nan, 2.0])
    out = release_filter(prev, new, dt_s=0.1, time_constant_s=0.5)
    alpha = 1 - math.exp(-0.1 / 0.5)
    np.testing.assert_allclose(out[[0, 1, 2, 4]], [1.0 + alpha * 1.0, 1.0, 4.0, 2.0])
    assert np.isnan(out[3])  # unknown is never hidden by memory


def test_release_filter_first_frame_and_passthrough() -> None:
    new = np.array([1.0, np.nan, 5.0])
    np.testing.assert_array_equal(release_filter(None, new, 0.1, 0.5), new)
    prev = np.array([0.5, 0.5, 0.5])
    np.testing.assert_array_equal(release_filter(prev, new, 0.1, 0.0), new)  # τ = 0


def test_release_filter_converges_and_holds_at_zero_dt() -> None:
    prev = np.array([1.0])
    target = np.array([3.0])
    assert release_filter(prev, target, 0.0, 1.0)[0] == 1.0
    x = prev
    for _ in range(100):
        x = release_filter(x, target, 0.1, 0.5)
    assert x[0] == pytest.approx(3.0, abs=1e-6)
    # After one time constant (in small steps), 63 % of the way.
    x = prev
    for _ in range(50):
        x = release_filter(x, target, 0.01, 0.5)
    assert x[0] == pytest.approx(1.0 + 2.0 * (1 - math.exp(-1.0)))


def test_release_filter_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="dt_s"):
        release_filter(None, np.ones(9), -0.1, 1.0)
    with pytest.raises(ValueError, match="time_constant_s"):
        release_filter(None, np.ones(9), 0.1, -1.0)
    with pytest.raises(ValueError, match="shape"):
        release_filter(np.ones(3), np.ones(9), 0.1, 1.0)


_depth = st.one_of(st.floats(0.0, 1000.0), st.just(math.nan), st.just(math.inf))


@settings(max_examples=300, deadline=None)
@given(
    prev=st.lists(_depth, min_size=9, max_size=9),
    new=st.lists(_depth, min_size=9, max_size=9),
    dt=st.floats(0.0, 10.0),
    tau=st.floats(0.0, 10.0),
)
def test_release_filter_property(prev: list[float], new: list[float], dt: float, tau: float) -> None:
    p, n = np.array(prev), np.array(new)
    out = release_filter(p, n, dt, tau)
    assert out.shape == (9,)
    # Unknown stays unknown; a previous unknown never leaks into a known sample.
    np.testing.assert_array_equal(np.isnan(out), np.isnan(n))
    known = ~np.isnan(n)
    o, nk, pk = out[known], n[known], p[known]
    # Never farther than the newest sample (so never above max(prev, new)), never nearer than
    # min(prev, new); an approaching obstacle (new <= prev, or no previous) passes unchanged.
    assert (o <= nk).all()
    lower = np.where(np.isnan(pk), nk, np.minimum(pk, nk))
    assert (o >= lower).all()
    approach = ~(nk > pk)
    np.testing.assert_array_equal(o[approach], nk[approach])


# --------------------------------------------------------------------------------------------------
# Median filter


def test_median_filter_outvotes_a_reading_that_lasts_one_frame() -> None:
    from companion.core.lut import median_filter

    far, near = np.full(3, 6.0), np.full(3, 0.4)
    # A phantom (one near frame in open space) is outvoted; so is a one-frame drop-out to far.
    np.testing.assert_array_equal(median_filter([far, far], near, 3), far)
    np.testing.assert_array_equal(median_filter([near, near], far, 3), near)
    # An obstacle that stays counts from its second frame, at the nearer of the two readings' median.
    np.testing.assert_array_equal(median_filter([far, near], np.full(3, 0.35), 3), near)
    # Only the newest frames - 1 history frames count.
    np.testing.assert_array_equal(median_filter([near, near, far, far], near, 3), far)


def test_median_filter_never_delays_unknown_and_counts_unknown_history_as_near() -> None:
    from companion.core.lut import median_filter

    far = np.array([6.0, 6.0])
    new = np.array([np.nan, 6.0])
    out = median_filter([far, far], new, 3)
    assert np.isnan(out[0]) and out[1] == 6.0
    unknown = np.array([np.nan, np.nan])
    # Two unknown (near) frames before: a far reading is still outvoted.
    np.testing.assert_array_equal(median_filter([unknown, unknown], far, 3), [0.0, 0.0])


def test_median_filter_start_up_and_off() -> None:
    from companion.core.lut import median_filter

    new = np.array([1.0, 2.0])
    np.testing.assert_array_equal(median_filter([], new, 3), new)
    np.testing.assert_array_equal(median_filter([np.array([9.0, 9.0])], new, 3), new)  # not enough history yet
    np.testing.assert_array_equal(median_filter([np.array([9.0, 9.0])] * 4, new, 1), new)  # 1 = off
    with pytest.raises(ValueError, match="odd"):
        median_filter([], new, 2)
    with pytest.raises(ValueError, match="shape"):
        median_filter([np.zeros(3), np.zeros(3)], new, 3)
