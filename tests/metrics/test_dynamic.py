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


# ----------------------------------------------------------- the mask's rule, pixel by pixel
def reference_mask(frames: np.ndarray, threshold: float, dilation: int, median_frames: int) -> np.ndarray:
    """The documented rule written out with loops: the background is the per-pixel median of every
    ⌈T / median_frames⌉-th frame (from the first); a pixel moves when some frame differs from it by more than
    ``threshold`` in some channel; the moving set grows by a (2·dilation + 1)² square."""
    count, h, w, c = frames.shape
    step = -(-count // median_frames)
    samples = frames[::step]
    moving = np.zeros((h, w), bool)
    for y in range(h):
        for x in range(w):
            for ch in range(c):
                values = sorted(float(v) for v in samples[:, y, x, ch])
                k = len(values)
                median = values[k // 2] if k % 2 else 0.5 * (values[k // 2 - 1] + values[k // 2])
                if any(abs(float(frames[t, y, x, ch]) - median) > threshold for t in range(count)):
                    moving[y, x] = True
    grown = np.zeros_like(moving)
    for y in range(h):
        for x in range(w):
            grown[y, x] = moving[max(0, y - dilation):y + dilation + 1, max(0, x - dilation):x + dilation + 1].any()
    return grown


def _grid_clip(count: int, seed: int, h: int = 9, w: int = 11) -> np.ndarray:
    """Frames whose values are multiples of 1/64 (exact in float32), so differences hit thresholds exactly."""
    rng = np.random.default_rng(seed)
    base = rng.integers(8, 56, (h, w, 3))
    frames = np.repeat(base[None], count, axis=0).copy()
    for _ in range(12):  # twelve changes in all, by 1 to 12 steps of 1/64, in random frames and places
        t, y, x, ch = rng.integers(0, count), rng.integers(0, h), rng.integers(0, w), rng.integers(0, 3)
        frames[t, y, x, ch] += rng.integers(1, 13) * rng.choice([-1, 1])
    return (frames / 64.0).astype(np.float32)


@pytest.mark.parametrize("count,dilation", [(5, 0), (12, 1), (130, 2), (200, 3)])
def test_mask_equals_the_written_rule_pixel_by_pixel(count, dilation):
    frames = _grid_clip(count, seed=count)
    threshold = 8 / 64  # a change of exactly 8 steps is not movement; 9 is
    expected = reference_mask(frames, threshold, dilation, median_frames=64)
    assert 0 < expected.sum() < expected.size  # the clip exercises both outcomes
    np.testing.assert_array_equal(dynamic_mask(frames, threshold=threshold, dilation=dilation), expected)


def test_the_defaults_are_the_documented_threshold_dilation_and_median_sample():
    from omg4.metrics import dynamic

    assert (dynamic.DYNAMIC_THRESHOLD, dynamic.DYNAMIC_DILATION, dynamic.MEDIAN_FRAMES) == (0.1, 2, 64)
    frames = _grid_clip(150, seed=7)
    np.testing.assert_array_equal(dynamic_mask(frames), reference_mask(frames, 0.1, 2, 64))


def test_a_change_exactly_at_the_threshold_is_not_movement():
    frames = np.full((4, 6, 6, 3), 0.5, np.float32)
    frames[2, 1, 1, 0] = 0.625  # exactly 0.125 above the median
    frames[3, 4, 4, 2] = 0.375 - 2 ** -10  # just beyond 0.125 below it
    mask = dynamic_mask(frames, threshold=0.125, dilation=0)
    assert mask.sum() == 1 and mask[4, 4]


def test_the_median_comes_from_every_ceil_t_over_64th_frame():
    # 130 frames: the median sample is frames 0, 3, …, 129 (44 frames), alternately 1 and 0 at one pixel, so its
    # median is 0.5 and no frame is more than 0.6 away; any other sample (every 2nd frame: a third of them 1)
    # has median 0 or 1 and would call the pixel moving
    frames = np.zeros((130, 2, 2, 3), np.float32)
    t = np.arange(130)
    frames[(t % 3 == 0) & ((t // 3) % 2 == 0), 0, 0] = 1.0
    assert not reference_mask(frames, 0.6, 0, 64).any()
    assert not dynamic_mask(frames, threshold=0.6, dilation=0).any()
    assert reference_mask(frames, 0.6, 0, 65).any()  # the rule with another sample does see movement
