"""Pruning's frame floor on a sudden event: Gaussians that one frame needs survive it, where scores summed over the
clip prune them (omg4.compress.pruning)."""

import dataclasses

import numpy as np
import torch

from omg4.compress.pruning import pruning_mask
from omg4.compress.score import compute_sd_scores
from omg4.gaussians import GaussianConfig, Gaussians4D
from omg4.metrics import psnr
from omg4.render.view import camera_tensors, render_image

EVENT_FRAME = 3


def event_scene(tiny_scene):
    """A model of the tiny scene's points living through the clip, plus a bright cluster living only about
    ``EVENT_FRAME``'s time; the scene's views with that model's renders as their images, and the model slightly moved
    (a baseline whose loss has gradients everywhere)."""
    g = torch.Generator().manual_seed(2)
    pts = tiny_scene.initial_points
    pick = torch.randperm(len(pts.xyz), generator=g)[:300]
    xyz = torch.as_tensor(pts.xyz[pick.numpy()], dtype=torch.float32)
    rgb = torch.as_tensor(pts.rgb[pick.numpy()], dtype=torch.float32)
    times = sorted({v.timestamp for v in tiny_scene.train_views})
    eyes = torch.stack([camera_tensors(v.camera)[2].float() for v in tiny_scene.train_views]).mean(0)
    centre = xyz.mean(0) + 0.4 * (eyes - xyz.mean(0))  # in front of the scene, seen by every camera
    event_xyz = centre + 0.05 * torch.randn(16, 3, generator=g)
    model = Gaussians4D.from_points(torch.cat([xyz, event_xyz]), torch.cat([rgb, torch.tensor([[1.0, 0.1, 0.9]]).expand(16, 3)]),
                                    GaussianConfig(time_range=tuple(tiny_scene.time_range)), generator=g)
    span = times[-1] - times[0]
    with torch.no_grad():
        model.params["opacity"].fill_(2.0)
        model.params["t"][:300] = 0.5 * (times[0] + times[-1])
        model.params["scaling_t"][:300] = float(np.log(4 * span))  # every frame
        model.params["t"][300:] = times[EVENT_FRAME]
        model.params["scaling_t"][300:] = float(np.log(0.25 * span / (len(times) - 1)))  # about one frame
        model.params["scaling"][300:] += 0.5
    event = torch.arange(300, 316)

    def shown(view):
        image = render_image(model, view, backend="cpu").numpy()
        return dataclasses.replace(view, loader=lambda: image)

    views = [shown(v) for v in tiny_scene.train_views]
    baseline = Gaussians4D({k: v.detach().clone() for k, v in model.params.items()}, model.config)
    with torch.no_grad():
        baseline.params["xyz"] += 0.01 * torch.randn(baseline.params["xyz"].shape, generator=g)
    return baseline, views, event, times


def test_a_sudden_event_survives_pruning_with_the_frame_floor(tiny_scene):
    """The cluster lives about one frame: summed over the clip its scores are below Eq. 2's quantiles, so the paper's
    pruning removes all of it; the floor keeps the part that ranks among its frame's largest, at the same count, and
    that frame's views come out closer to the truth."""
    baseline, views, event, times = event_scene(tiny_scene)
    scores = compute_sd_scores(baseline, views, backend="cpu", progress=False)
    paper, floored = pruning_mask(scores, 0.9), pruning_mask(scores, 0.9, frame_floor=0.02)
    assert int(paper.sum()) - 2 <= int(floored.sum()) <= int(paper.sum())
    assert int(paper[event].sum()) == 0 and int(floored[event].sum()) >= 3

    def event_psnr(keep):
        kept = Gaussians4D({k: v.detach()[keep] for k, v in baseline.params.items()}, baseline.config)
        return np.mean([float(psnr(render_image(kept, v, backend="cpu"), torch.from_numpy(v.image()))) for v in views
                        if v.timestamp == times[EVENT_FRAME]])

    assert event_psnr(floored) > event_psnr(paper) + 0.5  # 0.94 dB here
