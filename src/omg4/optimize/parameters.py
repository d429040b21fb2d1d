"""Per-parameter Adam groups, their learning rates and schedules, and optimizer-state surgery.

Real-Time4DGS (rt4dgs §3.3) gives every tensor its own Adam group (eps 1e-15); the position learning rate decays
log-linearly, the others are constant (:class:`LearningRates`, the defaults of training's knobs and compression's
rates). Densification and the OMG4 stages add and remove Gaussians: :func:`keep_rows` and :func:`append_rows` edit
the parameter tensors *and* their Adam moments together so no stage reaches into another's state.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import torch

from omg4 import distributed
from omg4.gaussians.backbone import APPEARANCE_FEATURES, Backbone


@dataclass(frozen=True)
class LearningRates:
    """The learning rates of the per-Gaussian parameters (rt4dgs §3.3; FreeTimeGS's velocity and duration), named as
    the backbone table's attributes name them (:attr:`omg4.gaussians.backbone.Attribute.lr`); those marked
    ``extent_lr`` are multiplied by the scene extent. Training's knobs (:class:`omg4.train.config.TrainConfig`) take
    them as defaults; compression fine-tunes with them."""

    position_lr_init: float = 1.6e-4
    position_lr_final: float = 1.6e-6
    time_lr: float = 1.6e-4
    feature_lr: float = 0.0025
    feature_rest_lr: float = 0.0025 / 20
    opacity_lr: float = 0.05
    scaling_lr: float = 0.005
    rotation_lr: float = 0.001
    velocity_lr: float = 1.6e-3
    duration_lr: float = 0.05


LEARNING_RATES = LearningRates()


def expon_lr(step: int, lr_init: float, lr_final: float, max_steps: int) -> float:
    """Log-linear interpolation from ``lr_init`` to ``lr_final`` over ``max_steps`` (rt4dgs §3.3)."""
    if lr_init == lr_final or max_steps <= 0:
        return lr_final if max_steps <= 0 else lr_init
    u = min(max(step / max_steps, 0.0), 1.0)
    return math.exp(math.log(lr_init) * (1 - u) + math.log(lr_final) * u)


def baseline_lrs(rates, extent: float, schema: Backbone) -> dict[str, float]:
    """Initial learning rate of each per-Gaussian parameter group (rt4dgs §3.3; the appearance features of
    paper §4.4 included), from the backbone's table: the field of ``rates`` (:class:`LearningRates`, or a training
    config holding the same fields) named by each attribute, times ``extent`` for positions, times and
    velocities."""
    return {a.name: getattr(rates, a.lr) * (extent if a.extent_lr else 1.0)
            for a in (*schema.attributes, *APPEARANCE_FEATURES)}


def make_adam(params: dict[str, torch.Tensor], lrs: dict[str, float], eps: float = 1e-15) -> torch.optim.Adam:
    """One Adam group per named tensor; each group remembers its name.

    The fused implementation (one kernel per group on CPU and CUDA) replaces a dozen
    element-wise operations per tensor and step.
    """
    groups = [{"params": [params[name]], "lr": lr, "name": name} for name, lr in lrs.items() if name in params]
    return torch.optim.Adam(groups, lr=0.0, eps=eps, fused=True)


def step_optimizers(optimizers, device: torch.device | str) -> None:
    """Step every optimizer (None entries skipped) and clear its gradients.

    In a distributed job the gradients of every parameter the optimizers hold are first summed over the
    ranks (:func:`omg4.distributed.all_reduce_gradients`), so every replica takes the same step. Runs with
    ``device`` as torch's default device, so state that an optimizer creates lazily (Adam's step counters)
    lands beside the parameters whatever the caller's default device is (a default device set for the step
    intercepts every torch call of the optimizers, so only where the caller's differs).
    """
    present = [opt for opt in optimizers if opt is not None]
    if distributed.world().parallel:
        distributed.all_reduce_gradients([p for opt in present for g in opt.param_groups for p in g["params"]])
    target = torch.device(device)
    with contextlib.nullcontext() if torch.get_default_device() == target else target:
        for opt in present:
            opt.step()
            opt.zero_grad(set_to_none=True)


def set_group_lr(optimizer: torch.optim.Optimizer, name: str, lr: float) -> None:
    """Set the learning rate of the parameter group called ``name`` (if the optimizer has one)."""
    group = _group(optimizer, name)
    if group is not None:
        group["lr"] = lr


def set_position_lr(optimizer: torch.optim.Optimizer, step: int, *, init: float, final: float, extent: float,
                    max_steps: int) -> float:
    """Apply the position schedule (rt4dgs §3.3) at ``step``: the xyz group's learning rate decays
    log-linearly from ``init · extent`` to ``final · extent`` over ``max_steps``; returns it."""
    lr = expon_lr(step, init * extent, final * extent, max_steps)
    set_group_lr(optimizer, "xyz", lr)
    return lr


def _group(optimizer: torch.optim.Optimizer, name: str) -> dict | None:
    return next((g for g in optimizer.param_groups if g.get("name") == name), None)


def _swap_param(optimizer: torch.optim.Optimizer, group: dict, new: torch.Tensor, edit_state) -> None:
    old = group["params"][0]
    state = optimizer.state.pop(old, None)
    if state:
        for key in ("exp_avg", "exp_avg_sq"):
            if key in state:
                state[key] = edit_state(state[key])
        optimizer.state[new] = state
    group["params"][0] = new


def keep_rows(params: dict[str, torch.Tensor], optimizer: torch.optim.Optimizer | None, keep: torch.Tensor,
              names: list[str] | None = None) -> None:
    """Keep only the rows ``keep`` (bool [N] or int64 index) of every per-Gaussian tensor, with its Adam moments.

    Tensors in ``params`` are replaced in place (the dict) by new leaf tensors.
    """
    for name in names or list(params):
        old = params[name]
        new = old.detach()[keep].clone().requires_grad_(old.requires_grad)
        params[name] = new
        group = _group(optimizer, name) if optimizer is not None else None
        if group is not None:
            _swap_param(optimizer, group, new, lambda s: s[keep].clone())


def append_rows(params: dict[str, torch.Tensor], optimizer: torch.optim.Optimizer | None,
                extra: dict[str, torch.Tensor]) -> None:
    """Append new Gaussians (``extra[name]`` rows) with zero Adam moments."""
    for name, rows in extra.items():
        old = params[name]
        new = torch.cat([old.detach(), rows.detach().to(old.dtype)], 0).requires_grad_(old.requires_grad)
        params[name] = new
        group = _group(optimizer, name) if optimizer is not None else None
        if group is not None:
            _swap_param(optimizer, group, new, lambda s: torch.cat([s, torch.zeros_like(rows, dtype=s.dtype)], 0))


def replace_param(params: dict[str, torch.Tensor], optimizer: torch.optim.Optimizer | None, name: str,
                  value: torch.Tensor, reset_state: bool = True) -> None:
    """Replace one tensor's values (same shape), zeroing its Adam moments when ``reset_state``."""
    old = params[name]
    new = value.detach().clone().requires_grad_(old.requires_grad)
    params[name] = new
    group = _group(optimizer, name) if optimizer is not None else None
    if group is not None:
        _swap_param(optimizer, group, new, (lambda s: torch.zeros_like(s)) if reset_state else (lambda s: s))


def overwrite_rows(params: dict[str, torch.Tensor], optimizer: torch.optim.Optimizer | None, rows: torch.Tensor,
                   values: dict[str, torch.Tensor]) -> None:
    """Write ``values[name]`` into the rows ``rows`` (int64 [K]) of every tensor named, zeroing those rows' Adam
    moments."""
    def zero_rows(state: torch.Tensor) -> torch.Tensor:
        state = state.clone()
        state[rows] = 0
        return state

    for name, value in values.items():
        old = params[name]
        new = old.detach().clone()
        new[rows] = value.to(new.dtype)
        params[name] = new.requires_grad_(old.requires_grad)
        group = _group(optimizer, name) if optimizer is not None else None
        if group is not None:
            _swap_param(optimizer, group, params[name], zero_rows)


def rebuilt_adam(old: torch.optim.Adam, params: dict[str, torch.Tensor], lrs: dict[str, float],
                 extra_groups: list[dict] = ()) -> torch.optim.Adam:
    """A new Adam (:func:`make_adam`) over ``params`` plus ``extra_groups``, with the moments ``old`` holds for
    tensors that survive (used when a stage adds or removes parameter tensors)."""
    new = make_adam(params, lrs)
    for group in extra_groups:
        new.add_param_group(group)
    for g in new.param_groups:
        p = g["params"][0]
        if p in old.state:
            new.state[p] = old.state[p]
    return new
