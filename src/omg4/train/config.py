"""Training configuration of the baselines and their presets.

Defaults follow the official Real-Time4DGS configs (rt4dgs §3.3–3.6): 30k
iterations, densification every 100 iterations from 500 to 15k with gradient threshold
2e-4, opacity reset every 3000, SH degree +1 every 1000. ``cpu-small`` scales the schedule
for a 2-core machine and small scenes.

FreeTimeGS (``backbone="freetimegs"``) trains on the same schedule with a fixed budget
(``max_gaussians``; 0 = one Gaussian per initial point): at each densification event it
relocates Gaussians whose opacity fell below ``relocate_opacity`` instead of densifying and
pruning, never resets opacities, and adds the 4D regularization ``lambda_reg`` · mean σ·sg[p_t]
until ``densify_until`` (FreeTimeGS §3.3–3.4).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace


@dataclass(frozen=True)
class TrainConfig:
    """Every knob of a baseline training run (iterations count optimizer steps)."""

    iterations: int = 30_000
    batch_size: int = 4
    seed: int = 6666
    # learning rates (rt4dgs §3.3); position ones are multiplied by the scene extent
    position_lr_init: float = 1.6e-4
    position_lr_final: float = 1.6e-6
    position_lr_max_steps: int = 30_000
    time_lr: float = 1.6e-4
    feature_lr: float = 0.0025
    feature_rest_lr: float = 0.0025 / 20
    opacity_lr: float = 0.05
    scaling_lr: float = 0.005
    rotation_lr: float = 0.001
    # loss (rt4dgs §3.2)
    lambda_dssim: float = 0.2
    # densification (rt4dgs §3.4)
    densify_from: int = 500
    densify_until: int = 15_000
    densify_interval: int = 100
    densify_grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    prune_screen_size: float = 20.0
    prune_world_size: float = 0.1
    opacity_reset_interval: int = 3000
    max_gaussians: int = 0  # 0 = unbounded
    # SH degree schedule: spatial 0→max, then temporal 0→max, one step per interval
    sh_increase_interval: int = 1000
    # initialization
    num_random_points: int = 100_000
    # evaluation and checkpoints
    test_interval: int = 0  # 0 = only at the end
    checkpoint_interval: int = 1000
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # backbone (omg4.gaussians.backbone) and the FreeTimeGS terms
    backbone: str = "rt4dgs"
    velocity_lr: float = 1.6e-3  # × extent; ten times the position rate (demo scene: +1.2 dB on moving pixels)
    # log duration; demo sweep (test PSNR / moving pixels): 0.005 (the log scales' rate) → 27.98 / 25.19 dB,
    # 0.02 → 28.38 / 25.69, 0.05 → 28.50 / 25.84, 0.1 → 28.20 / 25.59
    duration_lr: float = 0.05
    lambda_reg: float = 0.01
    relocate_opacity: float = 0.05  # demo sweep: 0.005 → 25.96 dB, 0.02 → 27.44, 0.05 → 27.98, 0.1 → 28.10
    backend: str = "auto"
    device: str = "cpu"  # where tensors live (omg4.device.resolve_device); configs written before it load as "cpu"

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
        from omg4.errors import OMG4Error

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
