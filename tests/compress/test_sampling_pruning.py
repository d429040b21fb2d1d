"""Gaussian Sampling keeps exactly round(τ·N) by SD score; pruning keeps exactly the OR-set of the quantiles."""

import numpy as np
import pytest
import torch

from omg4.compress.pruning import pruning_mask
from omg4.compress.sampling import sampling_mask, sd_score
from omg4.compress.score import SDScores
from omg4.errors import OMG4Error


def random_scores(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    return SDScores(torch.rand(n, generator=g, dtype=torch.float64) * 5,
                    torch.randn(n, generator=g, dtype=torch.float64))


@pytest.mark.parametrize("n,ratio", [(1000, 0.2), (997, 0.3), (10, 0.25), (7, 1.0)])
def test_sampling_keeps_exact_count_of_top_scores(n, ratio):
    s = random_scores(n)
    keep = sampling_mask(s, ratio)
    k = int(round(ratio * n))
    assert int(keep.sum()) == k
    # independent: SD computed by hand in numpy, the kept set is the top-k
    S, T = s.static.numpy(), s.dynamic.numpy()
    sd = (S - S.min()) / (S.max() - S.min() + 1e-8) * (T - T.min()) / (T.max() - T.min() + 1e-8)
    assert np.allclose(sd_score(s).numpy(), sd)
    kept_min = sd[keep.numpy()].min()
    dropped = sd[~keep.numpy()]
    assert dropped.size == 0 or dropped.max() <= kept_min


def test_dynamic_score_sign_matters():
    # equal static scores: the Gaussian with the most negative dynamic score must be dropped first
    s = SDScores(torch.ones(4, dtype=torch.float64) + torch.tensor([0.0, 0.1, 0.2, 0.3], dtype=torch.float64),
                 torch.tensor([-5.0, 1.0, 2.0, 3.0], dtype=torch.float64))
    keep = sampling_mask(s, 0.75)
    assert keep.tolist() == [False, True, True, True]
    # an absolute value would have kept index 0 (|-5| is the largest)


def test_sampling_rejects_bad_ratio():
    with pytest.raises(OMG4Error):
        sampling_mask(random_scores(10), 0.0)


@pytest.mark.parametrize("p", [0.8, 0.9, 0.5])
def test_pruning_keeps_or_set_of_quantiles(p):
    s = random_scores(2001, seed=3)
    keep = pruning_mask(s, p)
    S, T = s.static.numpy(), s.dynamic.numpy()
    expected = (S >= np.quantile(S, p)) | (T >= np.quantile(T, p))
    assert np.array_equal(keep.numpy(), expected)
    # the OR-set is between max(1-p) and 2(1-p) of the Gaussians
    frac = keep.float().mean().item()
    assert (1 - p) - 0.01 <= frac <= 2 * (1 - p) + 0.01


def test_pruning_counts_on_constructed_scores():
    # S ranks 0..9 ascending, T descending: top-20% of each are disjoint -> 4 kept
    s = SDScores(torch.arange(10, dtype=torch.float64), torch.arange(10, 0, -1, dtype=torch.float64))
    keep = pruning_mask(s, 0.8)
    assert keep.nonzero().squeeze(1).tolist() == [0, 1, 8, 9]
