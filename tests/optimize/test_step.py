"""One optimization step's loss in a distributed job: this rank's share of the global batch (omg4.optimize.step)."""

from __future__ import annotations

import pytest
import torch

from omg4 import distributed
from omg4.train import make_config
from omg4.optimize.step import backward_batch
from omg4.train.trainer import initial_model


def test_a_rank_back_propagates_its_share_of_the_batch_loss_and_regularizer(tiny_scene, monkeypatch):
    """With 2 ranks and a batch of 4 views, rank 0 renders views 0 and 2: its loss is Σ of their losses / 4, and a
    regularizer (a mean over the views) counts for 2/4 of its value, so the ranks' sum is the single process's."""
    model = initial_model(tiny_scene, make_config("cpu-small", num_random_points=200, max_gaussians=200))
    for p in model.params.values():
        p.requires_grad_(True)
    weight = torch.ones((), requires_grad=True)
    batch = torch.tensor([0, 3, 5, 7])
    rendered_views = []
    import omg4.optimize.step as step_module

    original = step_module.view_losses

    def recording(model, views, **kw):
        rendered_views.extend(v.camera.name + str(v.frame_index) for v in views)
        yield from original(model, views, **kw)

    monkeypatch.setattr(step_module, "view_losses", recording)
    monkeypatch.setattr(distributed, "world", lambda: distributed.World(rank=0, size=2))
    monkeypatch.setattr(distributed, "all_reduce_", lambda tensors, op="sum", what="": None)
    views = tiny_scene.train_views
    loss, _ = backward_batch(model, views, batch, background=torch.zeros(3), backend="cpu", lambda_dssim=0.2,
                             what="test", step=1, regularizer=lambda times: weight * 3.0)
    assert rendered_views == [views[0].camera.name + str(views[0].frame_index),
                              views[5].camera.name + str(views[5].frame_index)]
    assert float(weight.grad) == 3.0 * 2 / 4
    from omg4.render.view import view_image
    from omg4.render.view import render_view
    from omg4.optimize.loss import photometric_losses  # the same losses, computed alone

    with torch.no_grad():
        own = [photometric_losses(render_view(model, views[i].camera, views[i].timestamp, backend="cpu")[0].image[None],
                                  view_image(views[i])[None], 0.2)[0] for i in (0, 5)]
    assert loss == pytest.approx(float(sum(own)) / 4 + 3.0 * 2 / 4, rel=1e-5)


def test_one_process_adds_the_whole_regularizer_to_the_batch_loss(tiny_scene):
    """A single process renders the whole batch: loss = mean of the views' losses + the regularizer, whose
    gradient reaches its inputs at full weight."""
    from omg4.render.view import view_image
    from omg4.render.view import render_view
    from omg4.optimize.loss import photometric_losses

    model = initial_model(tiny_scene, make_config("cpu-small", num_random_points=200, max_gaussians=200))
    for p in model.params.values():
        p.requires_grad_(True)
    weight = torch.ones((), requires_grad=True)
    views, batch = tiny_scene.train_views, torch.tensor([1, 4])
    loss, _ = backward_batch(model, views, batch, background=torch.zeros(3), backend="cpu", lambda_dssim=0.2,
                             what="test", step=1, regularizer=lambda times: weight * 3.0)
    assert float(weight.grad) == 3.0
    with torch.no_grad():
        own = [photometric_losses(render_view(model, views[i].camera, views[i].timestamp, backend="cpu")[0].image[None],
                                  view_image(views[i])[None], 0.2)[0] for i in (1, 4)]
    assert loss == pytest.approx(float(sum(own)) / 2 + 3.0, rel=1e-5)
