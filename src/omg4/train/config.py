"""Training configuration of the baselines and their presets.

Defaults follow the official Real-Time4DGS configs (rt4dgs §3.3–3.6): 30k
iterations, densification every 100 iterations from 500 to 15k with gradient threshold
2e-4, opacity reset every 3000, SH degree +1 every 1000. ``cpu-small`` scales the schedule
for a 2-core machine and small scenes.

FreeTimeGS (``backbone="freetimegs"``) trains on the same schedule with a fixed budget
(``max_gaussians``; 0 = one Gaussian per initial point): at each densification event it
relocates Gaussians whose opacity fell below ``relocate_opacity`` instead of densifying and
pruning, never resets opacities, and adds the 4D regularization ``lambda_reg`` · mean σ·sg[p_t]
until ``densify_until`` (FreeTimeGS §3.3–3.4). Which of these a run uses is its backbone's density control
(:mod:`omg4.train.strategy`). Every field is settable by name (:mod:`omg4.settings`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace

import torch

from omg4.errors import OMG4Error
from omg4.optimize.parameters import LEARNING_RATES as LR
from omg4.settings import knob


@dataclass(frozen=True)
class TrainConfig:
    """Every knob of a baseline training run (iterations count optimizer steps)."""

    iterations: int = knob(30_000, "optimizer steps")
    batch_size: int = knob(4, "views per step")
    seed: int = knob(6666, "random seed of every draw (initial points, batches, densification)")
    # learning rates (rt4dgs §3.3); position ones are multiplied by the scene extent
    position_lr_init: float = knob(LR.position_lr_init, "position learning rate at the start (× scene extent)")
    position_lr_final: float = knob(LR.position_lr_final, "position learning rate at position_lr_max_steps (× scene "
                                                          "extent)")
    position_lr_max_steps: int = knob(30_000, "steps of the log-linear position decay")
    time_lr: float = knob(LR.time_lr, "time-centre learning rate (× scene extent)")
    feature_lr: float = knob(LR.feature_lr, "learning rate of the SH DC term (and of the OMG4 appearance features)")
    feature_rest_lr: float = knob(LR.feature_rest_lr, "learning rate of the other SH coefficients")
    opacity_lr: float = knob(LR.opacity_lr, "opacity learning rate")
    scaling_lr: float = knob(LR.scaling_lr, "learning rate of the log scales (spatial and temporal)")
    rotation_lr: float = knob(LR.rotation_lr, "quaternion learning rate")
    lambda_dssim: float = knob(0.2, "weight of the D-SSIM term in the loss (rt4dgs §3.2)")
    # density control (rt4dgs §3.4; FreeTimeGS relocation uses the same schedule)
    densify_from: int = knob(500, "first density event after this step")
    densify_until: int = knob(15_000, "no density events, statistics or regularization from this step on")
    densify_interval: int = knob(100, "steps between density events")
    densify_grad_threshold: float = knob(2e-4, "mean view-space gradient (NDC) from which a Gaussian is densified")
    percent_dense: float = knob(0.01, "largest scale (× extent) of a Gaussian that is cloned rather than split")
    prune_opacity: float = knob(0.005, "Gaussians below this opacity are pruned")
    prune_screen_size: float = knob(20.0, "after the first opacity reset, prune Gaussians wider than this (pixels)")
    prune_world_size: float = knob(0.1, "after the first opacity reset, prune Gaussians larger than this (× extent)")
    opacity_reset_interval: int = knob(3000, "steps between opacity resets (to 0.01)")
    max_gaussians: int = knob(0, "cap on the Gaussian count (0: none); FreeTimeGS: its fixed budget")
    sh_increase_interval: int = knob(1000, "steps per SH degree: spatial 0 → max, then temporal 0 → max")
    num_random_points: int = knob(100_000, "initial points made when the data has none (random, rays, mvs)")
    test_interval: int = knob(0, "test PSNR every N steps (0: only at the end)")
    checkpoint_interval: int = knob(1000, "a resumable checkpoint every N steps (0: only at the end)")
    background: tuple[float, float, float] = knob((0.0, 0.0, 0.0), "background colour, RGB in [0, 1]")
    backbone: str = knob("rt4dgs", "the representation (omg4.gaussians.backbone.BACKBONES)")
    velocity_lr: float = knob(LR.velocity_lr, "FreeTimeGS velocity learning rate (× extent)")
    duration_lr: float = knob(LR.duration_lr, "FreeTimeGS log-duration learning rate")
    lambda_reg: float = knob(0.01, "FreeTimeGS 4D regularization weight (FreeTimeGS §3.3)")
    relocate_opacity: float = knob(0.05, "FreeTimeGS: Gaussians below this opacity are relocated")
    backend: str = knob("auto", "rasterizer: auto, cpu or gsplat")
    device: str = knob("cpu", "where tensors live: cpu, cuda, cuda:N or auto")

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "TrainConfig":
        names = {f.name for f in fields(TrainConfig)}
        kwargs = {k: (tuple(v) if k == "background" else v) for k, v in d.items() if k in names}
        return TrainConfig(**kwargs)


PRESETS: dict[str, dict] = {
    # the official schedule (N3DV configs: batch 4, 30k iterations)
    "official": {},
    # a 2-core laptop on a small scene (≈ 256×192, a few dozen thousand Gaussians)
    "cpu-small": dict(
        iterations=3000,
        batch_size=2,
        position_lr_max_steps=3000,
        densify_from=150,
        densify_until=2000,
        densify_interval=100,
        opacity_reset_interval=1000,
        sh_increase_interval=250,
        num_random_points=20_000,
        max_gaussians=60_000,
        checkpoint_interval=500,
    ),
}


def default_preset(device) -> str:
    """The preset a run takes when none is named: the official schedule on a CUDA device, ``cpu-small`` elsewhere
    (30,000 official iterations would take a 2-core machine hours)."""
    return "official" if torch.device(device).type == "cuda" else "cpu-small"


MIN_DENSIFY_INTERVAL = TrainConfig().densify_interval
"""Scaling a schedule never densifies more often than the official every 100 iterations (rt4dgs §3.4)."""

SCHEDULE_FIELDS = ("densify_from", "densify_until", "densify_interval", "opacity_reset_interval",
                   "sh_increase_interval", "position_lr_max_steps")


def make_config(preset: str = "official", **overrides) -> TrainConfig:
    """The preset's config with ``overrides`` (``None`` values ignored) applied.

    Overriding ``iterations`` scales the preset's schedule (densification window,
    opacity resets, SH degree steps, position decay) by the same factor, unless those are
    overridden too, so a shorter run still ends with a settled model. The densification
    interval scales too but never below :data:`MIN_DENSIFY_INTERVAL`: densifying more often
    multiplies the Gaussian count (an explicit ``densify_interval`` is taken as given).
    """
    if preset not in PRESETS:
        raise OMG4Error(f"unknown training preset '{preset}' (choose from {', '.join(PRESETS)})")
    cfg = replace(TrainConfig(), **PRESETS[preset])
    overrides = {k: v for k, v in overrides.items() if v is not None}
    if "iterations" in overrides:
        factor = overrides["iterations"] / cfg.iterations
        for name in SCHEDULE_FIELDS:
            if name not in overrides:
                floor = MIN_DENSIFY_INTERVAL if name == "densify_interval" else 1
                overrides[name] = max(floor, int(round(getattr(cfg, name) * factor)))
    return replace(cfg, **overrides)
