"""The density controls a backbone may name (:attr:`omg4.gaussians.backbone.Backbone.training`), in one table.

Real-Time4DGS names ``"densification"`` (:class:`~omg4.train.densify.Densification`: densify, prune, reset
opacities; rt4dgs §3.4), FreeTimeGS ``"relocation"`` (:class:`~omg4.train.relocate.Relocation`: relocate within a
fixed budget, regularize opacity; FreeTimeGS §3.3–3.4). A backbone may also give a
:class:`~omg4.train.strategy.DensityStrategy` subclass itself; one that names none trains a fixed set of Gaussians,
so a new backbone never inherits another's density control.
"""

from __future__ import annotations

import inspect
import warnings

from omg4.errors import OMG4Error
from omg4.gaussians.backbone import Backbone
from omg4.train.config import TrainConfig
from omg4.train.densify import Densification
from omg4.train.relocate import Relocation
from omg4.train.strategy import DensityStrategy

STRATEGIES: dict[str, type[DensityStrategy]] = {"densification": Densification, "relocation": Relocation}
"""Every named density control."""


def strategy_for(backbone: Backbone, cfg: TrainConfig) -> DensityStrategy:
    """A new instance of ``backbone``'s density control with its settings from ``cfg``
    (:meth:`~omg4.train.strategy.DensityStrategy.from_config`; :class:`DensityStrategy` when it names none)."""
    spec = backbone.training
    if spec is None:
        return DensityStrategy.from_config(cfg)
    if isinstance(spec, str):
        if spec not in STRATEGIES:
            raise OMG4Error(f"backbone {backbone.name} names the density control {spec!r}, which is not one of "
                            f"{', '.join(STRATEGIES)}")
        spec = STRATEGIES[spec]
    if _config_positions(spec):
        return _ConfigHooks(spec(), cfg)
    return spec.from_config(cfg)


HOOKS = ("initial_points", "grows_until", "collects_statistics", "regularizer", "after_step")


def _config_positions(cls: type) -> dict[str, int]:
    """Where each hook of ``cls`` that still takes the run's config (the form before strategies owned their
    settings) has its ``cfg`` argument, by hook name; empty for a strategy that owns its settings."""
    positions = {}
    for hook in HOOKS:
        names = list(inspect.signature(getattr(cls, hook)).parameters)
        if "cfg" in names:
            positions[hook] = names.index("cfg") - 1  # without ``self``
    return positions


class _ConfigHooks(DensityStrategy):
    """Runs a strategy whose hooks still take the run's ``TrainConfig`` (deprecated: a strategy owns its settings
    as dataclass fields, see :class:`~omg4.train.strategy.DensityStrategy`)."""

    def __init__(self, legacy, cfg: TrainConfig):
        warnings.warn(f"{type(legacy).__name__}: density-control hooks that take the TrainConfig are deprecated; "
                      "give the strategy its settings as dataclass fields (DensityStrategy.from_config)",
                      DeprecationWarning, stacklevel=3)
        super().__init__(max_gaussians=cfg.max_gaussians)
        self.legacy, self.cfg = legacy, cfg
        self.positions = _config_positions(type(legacy))  # looked up once, not at every step

    def _call(self, hook: str, *args):
        method, position = getattr(self.legacy, hook), self.positions.get(hook)
        return method(*args) if position is None else method(*args[:position], self.cfg, *args[position:])

    def initial_points(self, xyz, rgb, generator):
        return self._call("initial_points", xyz, rgb, generator)

    def grows_until(self) -> int:
        return self._call("grows_until")

    def collects_statistics(self, step: int) -> bool:
        return self._call("collects_statistics", step)

    def regularizer(self, params, timestamps, step: int):
        return self._call("regularizer", params, timestamps, step)

    def after_step(self, model, optimizer, stats, step: int, extent: float) -> None:
        self._call("after_step", model, optimizer, stats, step, extent)


__all__ = ["HOOKS", "STRATEGIES", "strategy_for"]
