"""Dynamic-region mask and masked metrics (beyond the paper): a known moving square on a static texture."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from omg4.errors import OMG4Error
from omg4.metrics.dynamic import DYNAMIC_DILATION, dynamic_mask, masked_psnr, masked_ssim
from omg4.metrics.ssim import ssim_map

H, W, T, SIDE = 48, 64, 12, 6


def moving_square_clip(seed=0):
    """A noisy static texture with a bright square moving right along row 20, 3 px per frame."""
    rng = np.random.default_rng(seed)
    background = rng.uniform(0.2, 0.6, (H, W, 3)).astype(np.float32)
    frames, covered = [], np.zeros((H, W), bool)
    for t in range(T):
        f = background + rng.normal(0, 0.01, background.shape).astype(np.float32)  # sensor noise, static
        x0 = 5 + 3 * t
        f[20:20 + SIDE, x0:x0 + SIDE] = [1.0, 0.95, 0.1]
        covered[20:20 + SIDE, x0:x0 + SIDE] = True
        frames.append(np.clip(f, 0, 1))
    return np.stack(frames), covered


def test_mask_covers_the_moving_square_and_nothing_static_far_from_it():
    clip, covered = moving_square_clip()
    mask = dynamic_mask(clip)
    assert mask[covered].all()
    ys, xs = np.nonzero(covered)
    far = np.ones((H, W), bool)
    margin = DYNAMIC_DILATION + 1
    far[max(ys.min() - margin, 0):ys.max() + margin + 1, max(xs.min() - margin, 0):xs.max() + margin + 1] = False
    assert not mask[far].any()
    assert mask.sum() < 0.3 * H * W


def test_a_static_clip_has_no_dynamic_pixels_and_short_clips_are_refused():
    clip, _ = moving_square_clip()
    still = np.repeat(clip[:1], 5, axis=0)
    assert not dynamic_mask(still).any()
    with pytest.raises(OMG4Error):
        dynamic_mask(clip[:1])


def test_masked_psnr_and_ssim_equal_a_direct_computation():
    clip, covered = moving_square_clip()
    gt = clip[4]
    rng = np.random.default_rng(1)
    render = np.clip(gt + rng.normal(0, 0.05, gt.shape), 0, 1).astype(np.float32)
    render[covered] = 0.5  # the moving object rendered badly
    mask = dynamic_mask(clip)
    diff = (render.astype(np.float64) - gt.astype(np.float64))[mask]
    expected = -10 * math.log10(np.mean(diff ** 2))
    assert masked_psnr(torch.from_numpy(render), torch.from_numpy(gt), mask) == pytest.approx(expected, rel=1e-12)
    full = -10 * math.log10(np.mean((render.astype(np.float64) - gt) ** 2))
    assert expected < full - 3  # the region metric sees what the full image hides
    smap = ssim_map(torch.from_numpy(render), torch.from_numpy(gt))[0].double().numpy()
    assert masked_ssim(render, gt, mask) == pytest.approx(smap[:, mask].mean(), rel=1e-6)
    assert math.isnan(masked_psnr(render, gt, np.zeros((H, W), bool)))


def test_evaluate_reports_dynamic_metrics_over_the_same_mask_for_every_model(tiny_scene):
    from omg4.evaluate import dynamic_masks, evaluate
    from omg4.gaussians import Gaussians4D, GaussianConfig

    masks = dynamic_masks(tiny_scene.test_views)
    assert masks and all(m.any() for m in masks.values())  # the synthetic scene has moving objects
    g = torch.Generator().manual_seed(0)
    n = 50
    params = {"xyz": torch.randn(n, 3, generator=g), "t": torch.rand(n, 1, generator=g) * 0.2,
              "scaling": torch.full((n, 3), -2.0), "scaling_t": torch.zeros(n, 1),
              "rotation": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), "rotation_r": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
              "opacity": torch.zeros(n, 1), "features_dc": torch.randn(n, 1, 3, generator=g),
              "features_rest": torch.zeros(n, 47, 3)}
    model = Gaussians4D(params, GaussianConfig(time_range=tiny_scene.time_range))
    result = evaluate(model, tiny_scene.test_views, lpips_nets=(), backend="cpu", fps_views=2, progress=False)
    expected = [masked_psnr(np.clip(r, 0, 1), v.image(), masks[v.camera.name]) for v, r in
                ((v, _render(model, v)) for v in tiny_scene.test_views)]
    assert result["psnr_dynamic"] == pytest.approx(float(np.mean(expected)), rel=1e-6)
    assert 0 < result["dynamic_fraction"] < 1


def _render(model, view):
    from omg4.render.view import render_view

    with torch.no_grad():
        return render_view(model, view.camera, view.timestamp, backend="cpu")[0].image.numpy()
