"""Lifetime-weighted SD scores: the weights against counts worked out by hand, and the mechanism — Gaussians the
clip's start cuts short are no longer the ones sampling removes."""

import math
from types import SimpleNamespace

import pytest
import torch

from omg4.compress.sampling import sampling_mask
from omg4.compress.score import SDScores, lifetime_weights

FRAMES = [i / 10 for i in range(60)]  # 60 frames, spacing 0.1
CULL = 0.05


def stub_model(t: list[float], half_widths: list[float]):
    """Gaussians at times ``t`` whose temporal cull p_t > 0.05 holds within ``half_widths`` of them."""
    var_t = torch.tensor(half_widths, dtype=torch.float64) ** 2 / (2 * math.log(1 / CULL))
    schema = SimpleNamespace(motion=lambda params, config: (None, None, var_t))
    return SimpleNamespace(params={"t": torch.tensor(t, dtype=torch.float64)[:, None]},
                           config=SimpleNamespace(time_cull=CULL, schema=schema))


def test_weights_are_lifetime_over_the_frames_the_clip_holds():
    # half-width 0.55 = 5.5 frames: a life of 11 frames. Centred on frame 30 the clip holds all 11 (frames 25..35):
    # weight 1. Centred on frame 0 it holds 6 (0..5): 11/6. Centred on frame 59: 6 again. Half-width 10 (200 frames'
    # life) anywhere in the clip: all 60 frames, 200/60. Centred 0.3 before the clip: frames 0..2, 11/3.
    w = lifetime_weights(stub_model([3.0, 0.0, 5.9, 3.0, -0.3], [0.55, 0.55, 0.55, 10.0, 0.55]), FRAMES)
    torch.testing.assert_close(w, torch.tensor([1.0, 11 / 6, 11 / 6, 200 / 60, 11 / 3], dtype=torch.float64))


def test_a_gaussian_the_clip_never_shows_and_a_short_clip_keep_weight_one():
    assert lifetime_weights(stub_model([50.0], [0.55]), FRAMES).tolist() == [1.0]  # never shown: nothing to scale
    assert lifetime_weights(stub_model([0.0, 1.0], [0.55, 0.55]), [0.0]).tolist() == [1.0, 1.0]  # one frame


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gaussians_cut_short_by_the_clips_start_survive_sampling(seed):
    """Half the Gaussians sit at the clip's first frame, half in its middle, every one as important per frame it
    shows (rates drawn alike): summed over the clip, the first half scores about 6/11 of the second, and the paper's
    ranking samples none of them; lifetime-weighted, sampling keeps both halves alike."""
    g = torch.Generator().manual_seed(seed)
    n = 400
    t = [0.0] * (n // 2) + [3.0] * (n // 2)
    model = stub_model(t, [0.55] * n)
    frames_shown = torch.tensor([6.0] * (n // 2) + [11.0] * (n // 2), dtype=torch.float64)
    rate = 1.0 + 0.1 * torch.rand(n, generator=g, dtype=torch.float64)
    summed = rate * frames_shown
    scores = SDScores(summed, summed.clone())  # SD = minmax(S)²: the ranking is the summed score's
    at_start = torch.arange(n) < n // 2
    paper = sampling_mask(scores, 0.5)
    assert int(paper[at_start].sum()) == 0
    weighted = sampling_mask(scores.weighted(lifetime_weights(model, FRAMES)), 0.5)
    assert 0.35 * n / 2 <= int(weighted[at_start].sum()) <= 0.65 * n / 2
