"""Counts derived from ratios, over sweeps whose fractional parts fall below, at and above one half.

Each rule is written out here independently of the code: "nearest, halves to even" is Python's ``round``;
the tests state it with exact arithmetic so that floor, ceiling or half-up rules fail them.
"""

from __future__ import annotations

import math
from fractions import Fraction

import pytest
import torch

from omg4.compress.appearance_stage import mlp_lr_schedule
from omg4.compress.merge_clusters import _split_large_cells
from omg4.compress.pruning import pruning_mask
from omg4.compress.sampling import sampling_mask
from omg4.compress.schedule import StageLengths
from omg4.compress.score import SDScores


def nearest_half_even(x: float) -> int:
    """The nearest integer to the float ``x`` (taken exactly), halves to the even neighbour."""
    q = Fraction(x)
    low = math.floor(q)
    rest = q - low
    if rest > Fraction(1, 2):
        return low + 1
    if rest < Fraction(1, 2):
        return low
    return low if low % 2 == 0 else low + 1


def test_the_rule_itself():
    assert [nearest_half_even(x) for x in (0.49, 0.5, 1.5, 2.5, 2.51, 3.49)] == [0, 0, 2, 2, 3, 3]


RATIOS = (0.2, 0.25, 0.3, 0.4, 0.5, 0.7, 0.75, 0.9, 0.125, 0.375)


def _fractions_seen(values):
    parts = {Fraction(v) - math.floor(Fraction(v)) for v in values}
    return any(p < Fraction(1, 2) and p > 0 for p in parts), Fraction(1, 2) in parts, any(p > Fraction(1, 2)
                                                                                          for p in parts)


def test_sampling_keeps_the_nearest_count_to_ratio_times_n_and_prefers_lower_indices_on_ties():
    seen = []
    for n in range(1, 41):
        static = torch.arange(n, dtype=torch.float64) % 5  # many ties in the combined score
        dynamic = torch.ones(n, dtype=torch.float64)
        dynamic[0] = 0.0  # minmax(dynamic) is 0 at row 0 and 1 elsewhere
        for ratio in RATIOS:
            x = ratio * n
            seen.append(x)
            keep = sampling_mask(SDScores(static, dynamic), ratio)
            k = max(1, nearest_half_even(x))
            assert int(keep.sum()) == k, (n, ratio)
            # the highest scores first; among equal scores, the lower index
            score = [(0.0 if i == 0 else (i % 5) / (max(min(n - 1, 4), 1) + 0.0)) for i in range(n)]
            expected = sorted(range(n), key=lambda i: (-score[i], i))[:k]
            assert sorted(keep.nonzero().squeeze(1).tolist()) == sorted(expected), (n, ratio)
    assert _fractions_seen(seen) == (True, True, True)


def reference_quantile(values: list[float], q: float) -> float:
    """Linear interpolation between the order statistics around q·(n − 1), exactly."""
    v = sorted(values)
    pos = Fraction(q) * (len(v) - 1)
    lo = math.floor(pos)
    hi = min(lo + 1, len(v) - 1)
    return float(Fraction(v[lo]) + (pos - lo) * (Fraction(v[hi]) - Fraction(v[lo])))


@pytest.mark.parametrize("p", [0.0, 0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875, 1.0])
def test_pruning_keeps_exactly_the_gaussians_at_or_above_either_quantile(p):
    # dyadic quantiles: p·(n − 1) and the interpolation are exact in floating point, so ties at the quantile
    # are decided by the rule, not by rounding
    g = torch.Generator().manual_seed(int(p * 100))
    for n in range(1, 30):
        static = torch.randint(0, 6, (n,), generator=g).double()  # ties at the quantile happen
        dynamic = torch.randint(-3, 3, (n,), generator=g).double()
        keep = pruning_mask(SDScores(static, dynamic), p)
        qs, qd = reference_quantile(static.tolist(), p), reference_quantile(dynamic.tolist(), p)
        expected = [s >= qs or d >= qd for s, d in zip(static.tolist(), dynamic.tolist())]
        assert keep.tolist() == expected, (n, p)


def test_pruning_an_empty_set_and_out_of_range_quantiles():
    from omg4.errors import OMG4Error

    empty = SDScores(torch.zeros(0, dtype=torch.float64), torch.zeros(0, dtype=torch.float64))
    assert pruning_mask(empty, 0.8).shape == (0,)
    one = SDScores(torch.ones(1, dtype=torch.float64), torch.ones(1, dtype=torch.float64))
    for bad in (-0.01, 1.01):
        with pytest.raises(OMG4Error):
            pruning_mask(one, bad)
    for bad in (0.0, -0.5, 1.01):
        with pytest.raises(OMG4Error):
            sampling_mask(one, bad)
    assert sampling_mask(one, 1.0).tolist() == [True]


def test_scaled_stage_lengths_round_to_nearest_with_a_floor():
    base = StageLengths(sample=1000, prune=1000, merge=1000, appearance=5000, svq3d=1000, svq4d=1000)
    seen = []
    for factor in (0.0005, 0.0015, 0.0025, 0.0035, 0.0007, 0.0013, 0.2, 0.1, 0.0101, 0.0099):
        for minimum in (0, 1, 2, 10):
            got = base.scaled(factor, minimum)
            for name in ("sample", "prune", "merge", "appearance", "svq3d", "svq4d"):
                x = getattr(base, name) * factor
                seen.append(x)
                assert getattr(got, name) == max(minimum, nearest_half_even(x)), (factor, minimum, name)
    assert _fractions_seen(seen) == (True, True, True)
    assert base.scaled(0.2) == StageLengths(200, 200, 200, 1000, 200, 200)  # the "cpu" schedule
    assert StageLengths().scaled(0.001) == StageLengths(10, 10, 10, 10, 10, 10)  # default floor of 10


@pytest.mark.parametrize("total", [1, 7, 35, 70, 105, 350, 700, 1400, 3150, 6999, 7000, 7001, 14000])
def test_mlp_schedule_scales_warmup_and_milestones_to_the_nearest_iteration(total):
    warmup, milestones = mlp_lr_schedule(total)
    scale = total / 7000  # in floating point: 3500 · 7001/7000 is 3500.5000000000005, not a tie
    assert warmup == max(1, nearest_half_even(100 * scale))
    assert milestones == [max(1, nearest_half_even(m * scale)) for m in (1000, 3500, 6000)]
    if total == 7000:
        assert (warmup, milestones) == (100, [1000, 3500, 6000])  # the official schedule


def test_mlp_schedule_needs_an_iteration():
    from omg4.errors import OMG4Error

    with pytest.raises(OMG4Error):
        mlp_lr_schedule(0)


@pytest.mark.parametrize("cap", [1, 2, 3, 4, 7, 10])
def test_large_cells_split_into_ceil_m_over_cap_near_equal_slabs_along_x(cap):
    sizes = [1, 2, 3, 5, 9, 10, 11, 20]
    cell = torch.cat([torch.full((m,), c) for c, m in enumerate(sizes)])
    g = torch.Generator().manual_seed(cap)
    x = torch.rand(len(cell), generator=g)
    block = _split_large_cells(cell, x, cap)
    if max(sizes) <= cap:
        assert torch.equal(block, cell)
        return
    for c, m in enumerate(sizes):
        members = (cell == c).nonzero().squeeze(1)
        pieces = -(-m // cap)
        ranked = members[torch.sort(x[members], stable=True).indices]
        slabs = [ranked[int(Fraction(j * m, pieces).__ceil__()):int(Fraction((j + 1) * m, pieces).__ceil__())]
                 for j in range(pieces)]
        assert len({int(b) for b in block[members]}) == pieces, (c, m)
        for slab in slabs:  # each slab is one block of consecutive x ranks, sizes differing by at most one
            assert len({int(b) for b in block[slab]}) == 1
            assert len(slab) in (m // pieces, -(-m // pieces))
    assert len(torch.unique(block)) == sum(-(-m // cap) for m in sizes)
