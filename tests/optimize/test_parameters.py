"""Optimizer surgery keeps parameters and Adam moments aligned; the LR schedule is log-linear."""

import math

import torch

from omg4.optimize.parameters import append_rows, expon_lr, keep_rows, make_adam, replace_param


def _setup():
    torch.manual_seed(0)
    params = {"a": torch.randn(6, 3, requires_grad=True), "b": torch.randn(6, 1, 2, requires_grad=True)}
    opt = make_adam(params, {"a": 0.1, "b": 0.01})
    loss = (params["a"] ** 2).sum() + (params["b"] ** 3).sum()
    loss.backward()
    opt.step()
    return params, opt


def _state(opt, name):
    g = next(g for g in opt.param_groups if g["name"] == name)
    return g["params"][0], opt.state[g["params"][0]]


def test_keep_rows_selects_params_and_moments():
    params, opt = _setup()
    before = {k: (_state(opt, k)[1]["exp_avg"].clone(), params[k].detach().clone()) for k in params}
    keep = torch.tensor([True, False, True, True, False, True])
    keep_rows(params, opt, keep)
    for k in params:
        p, st = _state(opt, k)
        assert p is params[k] and p.requires_grad
        assert torch.equal(p.detach(), before[k][1][keep])
        assert torch.equal(st["exp_avg"], before[k][0][keep])


def test_append_rows_zero_moments_and_optimizer_still_steps():
    params, opt = _setup()
    append_rows(params, opt, {"a": torch.ones(2, 3), "b": torch.zeros(2, 1, 2)})
    p, st = _state(opt, "a")
    assert p.shape == (8, 3) and torch.equal(st["exp_avg"][6:], torch.zeros(2, 3))
    loss = params["a"].sum() + params["b"].sum()
    loss.backward()
    opt.step()  # shapes of moments and params agree, else Adam raises
    assert not torch.equal(params["a"].detach()[6:], torch.ones(2, 3))


def test_replace_param_resets_moments():
    params, opt = _setup()
    replace_param(params, opt, "a", torch.zeros(6, 3))
    p, st = _state(opt, "a")
    assert torch.equal(p.detach(), torch.zeros(6, 3))
    assert torch.equal(st["exp_avg_sq"], torch.zeros(6, 3))


def test_expon_lr_endpoints_and_midpoint():
    assert math.isclose(expon_lr(0, 1e-2, 1e-4, 100), 1e-2)
    assert math.isclose(expon_lr(100, 1e-2, 1e-4, 100), 1e-4)
    assert math.isclose(expon_lr(50, 1e-2, 1e-4, 100), 1e-3, rel_tol=1e-9)  # geometric mean
    assert math.isclose(expon_lr(500, 1e-2, 1e-4, 100), 1e-4)


def test_expon_lr_without_steps_is_the_final_rate_and_a_flat_schedule_is_exact():
    assert expon_lr(5, 1e-2, 1e-4, 0) == 1e-4 and expon_lr(0, 1e-2, 1e-4, -3) == 1e-4
    for step in (0, 7, 50, 100, 250):  # equal ends: exactly that rate, not exp(log(rate)) rounded
        assert expon_lr(step, 1.6e-4 * 2.3, 1.6e-4 * 2.3, 100) == 1.6e-4 * 2.3
