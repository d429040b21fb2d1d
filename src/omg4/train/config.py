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
(:mod:`omg4.train.strategies`), which the config holds, typed, as ``strategy`` (``strategy.densify_until``).
Every field is settable by name (:mod:`omg4.settings`). The settings' earlier flat names (``densify_until``) still
read in config files, records and ``--set`` (config files and ``--set`` with a one-line deprecation message), and
:func:`make_config` takes the density control's settings by their own names. Records of every earlier form are read
by one function, :meth:`TrainConfig.from_dict`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from typing import ClassVar

import torch

from omg4.errors import OMG4Error
from omg4.gaussians.backbone import backbone_named
from omg4.kernels import KERNELS_HELP, check_kernels
from omg4.optimize.parameters import LEARNING_RATES as LR
from omg4.settings import apply_settings, drop_removed, knob
from omg4.train.strategies import STRATEGIES, Strategy, as_strategy, strategy_class
from omg4.train.strategies.base import DensityStrategy, ScheduledEvents
from omg4.train.strategies.densification import Densification

STRATEGY_SETTINGS = tuple(dict.fromkeys(f.name for cls in (DensityStrategy, *STRATEGIES.values())
                                        for f in fields(cls)))
"""The density controls' settings, nested under ``strategy``; their earlier flat names still work (deprecated)."""


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
    sh_increase_interval: int = knob(1000, "steps per SH degree: spatial 0 → max, then temporal 0 → max")
    num_random_points: int = knob(100_000, "initial points made when the data has none (random, rays, mvs)")
    test_interval: int = knob(0, "test PSNR every N steps (0: only at the end)")
    checkpoint_interval: int = knob(1000, "a resumable checkpoint every N steps (0: only at the end)")
    background: tuple[float, float, float] = knob((0.0, 0.0, 0.0), "background colour, RGB in [0, 1]")
    backbone: str = knob("rt4dgs", "the representation (omg4.gaussians.backbone.BACKBONES)")
    velocity_lr: float = knob(LR.velocity_lr, "FreeTimeGS velocity learning rate (× extent)")
    duration_lr: float = knob(LR.duration_lr, "FreeTimeGS log-duration learning rate")
    backend: str = knob("auto", "rasterizer: auto, cpu or gsplat")
    device: str = knob("cpu", "where tensors live: cpu, cuda, cuda:N or auto")
    kernels: str | None = knob(None, KERNELS_HELP)
    strategy: Strategy = field(
        default_factory=Densification, metadata={"help": "the backbone's density control (omg4.train.strategies)"})

    MOVED_SETTINGS: ClassVar[dict[str, str]] = {name: f"strategy.{name}" for name in STRATEGY_SETTINGS}
    """Earlier flat names of settings, and where they are now (read with a one-line deprecation message)."""

    REMOVED_SETTINGS: ClassVar[dict[str, tuple[object, str]]] = {
        "still_weight": (0.0, "the penalty on lasting Gaussians' motion did not pay (docs/results.md, 'Options "
                              "removed, and why'; benchmarks/results/segments_carry_synthetic240.json)")}
    """Settings no longer here: their "off" value, and why they went (:func:`omg4.settings.drop_removed`)."""

    def __post_init__(self) -> None:
        """The strategy is the backbone's density control: another one (``replace(cfg, backbone="freetimegs")``)
        becomes the backbone's, keeping the settings both have (the schedule, the budget). An unknown backbone or
        kernels choice is a one-line error."""
        try:
            check_kernels(self.kernels)
            cls = strategy_class(backbone_named(self.backbone))
        except ValueError as exc:
            raise OMG4Error(str(exc)) from None
        if type(self.strategy) is not cls:
            object.__setattr__(self, "strategy", as_strategy(cls, self.strategy))

    def with_strategy(self, **changes) -> "TrainConfig":
        """A copy with the density control's settings ``changes`` (``max_gaussians=…``)."""
        return replace(self, strategy=replace(self.strategy, **changes))

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "TrainConfig":
        """The config a run's record holds, in any form omg4 has written: nested (the backbone's strategy, or the
        union of every strategy's settings that records held before each strategy had its own class, whose other
        strategies' settings are dropped), or flat as records made before ``strategy`` were; read silently, a record
        not being the user's writing."""
        names = {f.name for f in fields(TrainConfig)}
        d = drop_removed(TrainConfig, dict(d))
        kwargs = {k: (tuple(v) if k == "background" else v) for k, v in d.items() if k in names}
        inner = dict(kwargs.pop("strategy", None) or {})
        inner.update({k: v for k, v in d.items() if k in STRATEGY_SETTINGS})
        cls = strategy_class(backbone_named(kwargs.get("backbone", TrainConfig.backbone)))
        own = {f.name for f in fields(cls)}
        return TrainConfig(**kwargs, strategy=cls(**{k: v for k, v in inner.items() if k in own}))


PRESETS: dict[str, dict] = {
    # the official schedule (N3DV configs: batch 4, 30k iterations)
    "official": {},
    # a 2-core laptop on a small scene (≈ 256×192, a few dozen thousand Gaussians)
    "cpu-small": {
        "iterations": 3000,
        "batch_size": 2,
        "position_lr_max_steps": 3000,
        "strategy.densify_from": 150,
        "strategy.densify_until": 2000,
        "strategy.densify_interval": 100,
        "strategy.opacity_reset_interval": 1000,
        "sh_increase_interval": 250,
        "num_random_points": 20_000,
        "strategy.max_gaussians": 60_000,
        "checkpoint_interval": 500,
    },
}
"""Each preset's settings by dotted name (:mod:`omg4.settings`)."""


def default_preset(device) -> str:
    """The preset a run takes when none is named: the official schedule on a CUDA device, ``cpu-small`` elsewhere
    (30,000 official iterations would take a 2-core machine hours)."""
    return "official" if torch.device(device).type == "cuda" else "cpu-small"


MIN_DENSIFY_INTERVAL = ScheduledEvents().densify_interval
"""Scaling a schedule never densifies more often than the official every 100 iterations (rt4dgs §3.4)."""

SCHEDULE_FIELDS = ("strategy.densify_from", "strategy.densify_until", "strategy.densify_interval",
                   "strategy.opacity_reset_interval", "sh_increase_interval", "position_lr_max_steps")


def setting_of(cfg: TrainConfig, name: str):
    """The value of the dotted setting ``name`` in ``cfg``."""
    for part in name.split("."):
        cfg = getattr(cfg, part)
    return cfg


def make_config(preset: str = "official", overrides: dict | None = None, **settings) -> TrainConfig:
    """The preset's config with ``overrides`` (dotted names: ``{"strategy.densify_until": 2000}``) and ``settings``
    (keyword arguments: the fields, ``strategy`` as a mapping or a strategy, and the density control's settings by
    their own names, ``densify_until=2000``) applied, ``None`` values ignored; the density control's settings are
    those of the backbone's (:func:`omg4.train.strategies.strategy_class`).

    Overriding ``iterations`` scales the preset's schedule (densification window,
    opacity resets, SH degree steps, position decay) by the same factor, unless those are
    overridden too, so a shorter run still ends with a settled model. The densification
    interval scales too but never below :data:`MIN_DENSIFY_INTERVAL`: densifying more often
    multiplies the Gaussian count (an explicit ``densify_interval`` is taken as given).
    """
    if preset not in PRESETS:
        raise OMG4Error(f"unknown training preset '{preset}' (choose from {', '.join(PRESETS)})")
    cfg = apply_settings(TrainConfig(), PRESETS[preset])
    given = dict(overrides or {})
    strategy = settings.pop("strategy", None)
    if isinstance(strategy, DensityStrategy):
        strategy = {f.name: getattr(strategy, f.name) for f in fields(strategy)}
    given.update({f"strategy.{k}": v for k, v in (strategy or {}).items()})
    for name, value in settings.items():
        given[f"strategy.{name}" if name in STRATEGY_SETTINGS else name] = value
    given = {k: v for k, v in given.items() if v is not None}
    if "iterations" in given:
        factor = given["iterations"] / cfg.iterations
        backbone = backbone_named(given.get("backbone", cfg.backbone))
        own = {f"strategy.{f.name}" for f in fields(strategy_class(backbone))}
        for name in SCHEDULE_FIELDS:
            if name not in given and (name in own or not name.startswith("strategy.")):
                floor = MIN_DENSIFY_INTERVAL if name == "strategy.densify_interval" else 1
                given[name] = max(floor, int(round(setting_of(cfg, name) * factor)))
    return apply_settings(cfg, given)
