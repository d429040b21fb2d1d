"""Gaussian Sampling keeps exactly round(τ·N) by SD score; pruning keeps exactly the OR-set of the quantiles."""

import numpy as np
import pytest
import torch

from omg4.compress.pruning import pruning_mask
from omg4.compress.sampling import sampling_mask, sd_score
from omg4.compress.score import UNRANKED, SDScores, frame_ranks
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


def brute_force_frame_ranks(per_frame):
    """Each Gaussian's best place over the frames, counted by hand: how many Gaussians a frame scores above it (ties:
    those of lower index first); never placed where every frame scores it 0."""
    F, N = per_frame.shape
    best = [UNRANKED] * N
    for f in range(F):
        row = per_frame[f].tolist()
        for i in range(N):
            if row[i] > 0:
                place = sum(1 for j in range(N) if row[j] > row[i] or (row[j] == row[i] and j < i))
                best[i] = min(best[i], place)
    return best


def test_frame_ranks_count_each_frames_places():
    g = torch.Generator().manual_seed(4)
    per_frame = torch.rand(5, 40, generator=g)
    per_frame[per_frame < 0.3] = 0.0  # Gaussians a frame does not see
    per_frame[:, 7] = 0.0  # one no frame sees
    per_frame[2, 11] = per_frame[2, 12] = per_frame[2].max()  # a tie at a frame's top
    ranks = frame_ranks(per_frame)
    assert ranks.tolist() == brute_force_frame_ranks(per_frame)
    assert ranks[7] == UNRANKED and ranks[11] == 0 and ranks[12] == 1


def test_the_frame_floor_keeps_what_one_frame_needs_at_the_same_count():
    """Gaussian 3 is scored low over the clip but is one frame's largest: the floor keeps it, the paper's rule does
    not, and both keep as many Gaussians."""
    s = random_scores(500, seed=5)
    s.static[3], s.dynamic[3] = 0.0, s.dynamic.min()
    ranks = torch.full((500,), 400, dtype=torch.int64)
    ranks[3], ranks[10:13] = 0, torch.tensor([1, 2, 3])
    s = SDScores(s.static, s.dynamic, ranks)
    paper, floored = pruning_mask(s, 0.9), pruning_mask(s, 0.9, frame_floor=0.01)  # floor: ranks < 5
    assert not paper[3] and floored[3] and floored[10:13].all()
    # no more than the paper's rule, and short of it by at most one Gaussian of each score (a step of the quantile)
    assert int(paper.sum()) - 2 <= int(floored.sum()) <= int(paper.sum())
    # the rest is Eq. 2 at the lowest quantile of a fine grid whose union with the floor fits: found by hand
    S, T = s.static.numpy(), s.dynamic.numpy()
    floor = np.isin(np.arange(500), [3, 10, 11, 12])
    for q in np.linspace(0.9, 1.0, 20001):
        union = (S >= np.quantile(S, q)) | (T >= np.quantile(T, q)) | floor
        if union.sum() <= paper.sum():
            break
    assert np.array_equal(floored.numpy(), union)


def test_the_frame_floor_needs_frame_ranks_and_a_share_below_one():
    with pytest.raises(OMG4Error, match="frame ranks"):
        pruning_mask(random_scores(10), 0.5, frame_floor=0.1)
    with pytest.raises(OMG4Error, match="frame floor"):
        pruning_mask(random_scores(10), 0.5, frame_floor=1.0)
