"""The density controls a backbone may name (:attr:`omg4.gaussians.backbone.Backbone.training`), in one table; each
is a dataclass whose fields are its settings, and the training config holds the backbone's one, typed, as
``strategy`` (as gsplat's ``DefaultStrategy | MCMCStrategy``).

Real-Time4DGS names ``"densification"`` (:class:`~omg4.train.strategies.densification.Densification`: densify,
prune, reset opacities; rt4dgs §3.4), FreeTimeGS ``"relocation"``
(:class:`~omg4.train.strategies.relocation.Relocation`: relocate within a fixed budget, regularize opacity;
FreeTimeGS §3.3–3.4). A backbone may also give a :class:`~omg4.train.strategies.base.DensityStrategy` subclass
itself; one that names none trains a fixed set of Gaussians, so a new backbone never inherits another's density
control. A strategy added to :data:`STRATEGIES` and :data:`Strategy` brings its settings to config files,
``--set strategy.<field>=…`` and the commands' flags with no other change.
"""

from __future__ import annotations

import dataclasses
import inspect

from omg4.errors import OMG4Error
from omg4.gaussians.backbone import Backbone
from omg4.train.strategies.base import DensityStrategy, ScheduledEvents
from omg4.train.strategies.densification import Densification
from omg4.train.strategies.relocation import Relocation

STRATEGIES: dict[str, type[DensityStrategy]] = {"densification": Densification, "relocation": Relocation}
"""Every named density control."""

Strategy = Densification | Relocation | DensityStrategy
"""The type of the training config's ``strategy``: a named density control's settings, or none's."""

HOOKS = ("initial_points", "grows_until", "collects_statistics", "regularizer", "after_step")
"""The hooks the trainer calls (:class:`~omg4.train.strategies.base.DensityStrategy`)."""


def strategy_class(backbone: Backbone) -> type[DensityStrategy]:
    """The density control ``backbone`` trains with (:class:`DensityStrategy` when it names none)."""
    spec = backbone.training
    if spec is None:
        return DensityStrategy
    if isinstance(spec, str):
        if spec not in STRATEGIES:
            raise OMG4Error(f"backbone {backbone.name} names the density control {spec!r}, which is not one of "
                            f"{', '.join(STRATEGIES)}")
        spec = STRATEGIES[spec]
    if any("cfg" in inspect.signature(getattr(spec, hook)).parameters for hook in HOOKS):
        raise OMG4Error(f"{spec.__name__}: density-control hooks no longer take the TrainConfig; give the strategy "
                        "its settings as dataclass fields")
    return spec


def as_strategy(cls: type[DensityStrategy], settings: DensityStrategy) -> DensityStrategy:
    """The ``cls`` density control with the settings of ``settings`` (a strategy's) that ``cls`` has too; the rest of
    ``cls``'s keep their defaults, and those ``cls`` lacks are left (a change of backbone keeps the schedule and budget
    both controls share)."""
    names = {f.name for f in dataclasses.fields(cls)}
    return cls(**{f.name: getattr(settings, f.name) for f in dataclasses.fields(settings) if f.name in names})


def strategy_for(backbone: Backbone, cfg) -> DensityStrategy:
    """A new instance of ``backbone``'s density control with the run ``cfg``'s settings (its ``strategy``, taken as
    :func:`as_strategy` does) and seed."""
    strategy = as_strategy(strategy_class(backbone), cfg.strategy)
    strategy.seed = cfg.seed
    return strategy


__all__ = ["STRATEGIES", "DensityStrategy", "ScheduledEvents", "Strategy", "as_strategy", "strategy_class",
           "strategy_for"]
