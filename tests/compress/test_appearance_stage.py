"""The appearance stage's feature init and MLP optimizer/schedule (omg4 §6b, §9)."""

from __future__ import annotations

import pytest
import torch

from omg4.compress.appearance_stage import (FEATURE_LR, init_appearance_features, make_mlp_optimizer,
                                            mlp_lr_schedule)
from omg4.errors import OMG4Error
from omg4.gaussians.appearance import AppearanceMLP


def test_init_features_from_base_colour():
    dc = torch.randn(11, 1, 3, requires_grad=True)
    rest = torch.randn(11, 47, 3)
    feats = init_appearance_features({"features_dc": dc, "features_rest": rest})
    assert set(feats) == {"f_static", "f_view"}
    assert torch.equal(feats["f_static"], dc.detach()[:, 0])
    assert torch.equal(feats["f_view"], torch.zeros(11, 3))
    assert not feats["f_static"].requires_grad
    feats["f_static"].add_(1.0)  # a copy: the explicit parameters are untouched
    assert not torch.equal(feats["f_static"], dc.detach()[:, 0])
    assert FEATURE_LR == 0.0025


@pytest.mark.parametrize("params", [{}, {"features_dc": torch.zeros(4, 3)}, {"features_dc": torch.zeros(4, 2, 3)}])
def test_init_features_rejects_missing_or_malformed_dc(params):
    with pytest.raises(OMG4Error):
        init_appearance_features(params)


def test_schedule_official_and_scaled():
    assert mlp_lr_schedule(7000) == (100, [1000, 3500, 6000])  # 5000 MLP + 1000 SVQ-3D + 1000 SVQ-4D
    assert mlp_lr_schedule(1400) == (20, [200, 700, 1200])  # the "cpu" schedule: a fifth
    warmup, milestones = mlp_lr_schedule(16)  # the "tiny" smoke schedule
    assert warmup >= 1 and milestones == sorted(milestones) and all(1 <= m <= 16 for m in milestones)
    with pytest.raises(OMG4Error):
        mlp_lr_schedule(0)


def _expected_lr(k: int, base: float, warmup: int, milestones: list[int]) -> float:
    """Closed form of ChainedScheduler(LinearLR(0.01, warmup), MultiStepLR(milestones, 0.33)) after k steps."""
    ramp = 0.01 + 0.99 * min(k, warmup) / warmup
    return base * ramp * 0.33 ** sum(k >= m for m in milestones)


@pytest.mark.parametrize("total", [7000, 1400])
def test_optimizer_and_lr_curve(total):
    mlp = AppearanceMLP()
    opt, sched = make_mlp_optimizer(mlp, total_iterations=total)
    assert isinstance(opt, torch.optim.Adam)
    assert opt.param_groups[0]["eps"] == 1e-15
    assert {id(p) for p in opt.param_groups[0]["params"]} == {id(p) for p in mlp.parameters()}
    warmup, milestones = mlp_lr_schedule(total)
    checkpoints = {0, 1, warmup // 2, warmup - 1, warmup, warmup + 1, total - 1}
    checkpoints |= {m + d for m in milestones for d in (-1, 0, 1)}
    for k in range(total):
        if k in checkpoints:
            assert opt.param_groups[0]["lr"] == pytest.approx(_expected_lr(k, 5e-3, warmup, milestones), rel=1e-9), k
        opt.step()
        sched.step()


def test_one_step_moves_every_weight():
    torch.manual_seed(0)
    mlp = AppearanceMLP()
    opt, sched = make_mlp_optimizer(mlp, lr=1e-2, total_iterations=100)
    before = [p.detach().clone() for p in mlp.parameters()]
    xyz, fs, fv = torch.randn(32, 3), torch.randn(32, 3), torch.randn(32, 3)
    dc, rest, op = mlp(xyz, 0.5, fs, fv)
    (dc.square().sum() + rest.square().sum() + op.sum()).backward()
    opt.step()
    sched.step()
    for b, p in zip(before, mlp.parameters()):
        assert float((p.detach() - b).abs().max()) > 0
