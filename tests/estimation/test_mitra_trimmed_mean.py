"""Trimmed mean and median of Mitra et al. (eqs. (14), (21), Remark 7) on adversarial inputs."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimation.errors import DesignError
from estimation.trimmed_mean import average, fuse, fuse_block, median, trimmed_mean

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)
hostile = st.one_of(
    st.floats(allow_nan=False),  # includes +-inf and +-1.8e308
    st.sampled_from([1e300, -1e300, 1e12, -1e12, 0.0]),
)


@st.composite
def attacked(draw, *, min_extra: int = 0):
    """(values, f, regular values): at most f adversarial entries among >= 2f+1."""
    f = draw(st.integers(0, 3))
    n_adv = draw(st.integers(0, f))
    n_reg = draw(st.integers(max(2 * f + 1 - n_adv, 1) + min_extra, 2 * f + 4 + min_extra))
    reg = draw(st.lists(finite, min_size=n_reg, max_size=n_reg))
    adv = draw(st.lists(hostile, min_size=n_adv, max_size=n_adv))
    perm = draw(st.permutations(list(range(n_reg + n_adv))))
    vals = np.array(reg + adv, dtype=float)[perm]
    return vals, f, np.array(reg)


@settings(max_examples=400, deadline=None)
@given(attacked())
def test_trimmed_mean_stays_within_regular_range(case):
    vals, f, reg = case
    out = trimmed_mean(vals, f=f)
    assert reg.min() - 1e-9 * (1 + abs(reg.min())) <= out <= reg.max() + 1e-9 * (1 + abs(reg.max()))


@settings(max_examples=300, deadline=None)
@given(attacked(), st.data())
def test_weighted_trimmed_mean_stays_within_regular_range(case, data):
    vals, f, reg = case
    w = np.array(data.draw(st.lists(st.floats(0.01, 100.0), min_size=vals.size, max_size=vals.size)))
    out = trimmed_mean(vals, f=f, weights=w)
    assert reg.min() - 1e-9 * (1 + abs(reg.min())) <= out <= reg.max() + 1e-9 * (1 + abs(reg.max()))


@settings(max_examples=300, deadline=None)
@given(attacked())
def test_median_stays_within_regular_range(case):
    vals, f, reg = case
    out = median(vals, f=f)
    assert reg.min() - 1e-9 * (1 + abs(reg.min())) <= out <= reg.max() + 1e-9 * (1 + abs(reg.max()))


@settings(max_examples=150, deadline=None)
@given(st.lists(attacked(), min_size=1, max_size=6))
def test_batch_with_nan_padding_equals_row_by_row(cases):
    d = max(c[0].size for c in cases)
    f = cases[0][1]
    rows = []
    for vals, _, _ in cases:
        rows.append(np.concatenate([vals, np.full(d - vals.size, np.nan)]))
    batch = np.array(rows)
    got = trimmed_mean(batch, f=f, short="nan")
    for q, (vals, _, _) in enumerate(cases):
        if vals.size >= 2 * f + 1:
            ref = trimmed_mean(vals, f=f)
            assert got[q] == pytest.approx(ref, rel=1e-12, abs=1e-12) or (np.isinf(ref) and got[q] == ref)
        else:
            assert np.isnan(got[q])
    # the batch axis may be anywhere
    assert np.array_equal(trimmed_mean(batch.T, f=f, axis=0, short="nan"), got, equal_nan=True)


def test_trimmed_mean_concrete_values():
    assert trimmed_mean([1.0, 2.0, 3.0, 1e300, -1e300], f=1) == 2.0
    assert trimmed_mean([5.0, 1.0, 3.0, 2.0], f=1) == 2.5
    # weights follow their entries through the sort: 2 (w=3) and 3 (w=1) are kept
    assert trimmed_mean([3.0, 100.0, 2.0, -7.0], f=1, weights=[1.0, 9.0, 3.0, 9.0]) == pytest.approx(2.25)
    assert median([1.0, 2.0, 3.0, 4.0]) == 2.5
    assert average([1.0, 2.0, 6.0]) == 3.0


def test_too_few_values_and_bad_budget():
    with pytest.raises(DesignError, match="at least 3"):
        trimmed_mean([1.0, 2.0], f=1)
    assert np.isnan(trimmed_mean([1.0, 2.0, np.nan], f=1, short="nan"))
    with pytest.raises(DesignError, match="non-negative integer"):
        trimmed_mean([1.0, 2.0, 3.0], f=-1)
    with pytest.raises(DesignError, match="non-negative integer"):
        trimmed_mean([1.0, 2.0, 3.0], f=1.5)
    with pytest.raises(DesignError, match="weights"):
        trimmed_mean([1.0, 2.0, 3.0], f=1, weights=[1.0, 0.0, 1.0])


@settings(max_examples=150, deadline=None)
@given(attacked(), st.sampled_from(["trimmed", "median"]))
def test_fast_block_path_matches_nan_aware_rule(case, fusion):
    vals, f, _ = case
    vals = np.nan_to_num(vals, posinf=1e300, neginf=-1e300)  # finite: codec-checked payloads
    block = np.stack([vals, 2 * vals], axis=1)  # (d, 2): two modes with the same neighbours
    fast = fuse_block(block, fusion=fusion, f=f)
    slow = fuse(block.T, fusion=fusion, f=f)
    np.testing.assert_allclose(fast, slow, rtol=1e-12, atol=1e-300)
