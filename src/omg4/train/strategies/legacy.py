"""Strategies whose hooks still take the run's ``TrainConfig`` (the form before strategies owned their settings):
run through :class:`ConfigHooks`, with a deprecation warning."""

from __future__ import annotations

import inspect
import warnings

from omg4.train.strategies.base import DensityStrategy

HOOKS = ("initial_points", "grows_until", "collects_statistics", "regularizer", "after_step")


def config_positions(cls: type) -> dict[str, int]:
    """Where each hook of ``cls`` that still takes the run's config has its ``cfg`` argument, by hook name; empty
    for a strategy that owns its settings."""
    positions = {}
    for hook in HOOKS:
        names = list(inspect.signature(getattr(cls, hook)).parameters)
        if "cfg" in names:
            positions[hook] = names.index("cfg") - 1  # without ``self``
    return positions


class ConfigHooks(DensityStrategy):
    """Runs ``legacy``, a strategy whose hooks take the run's config ``cfg`` (deprecated: a strategy owns its
    settings as dataclass fields, see :class:`~omg4.train.strategies.base.DensityStrategy`)."""

    def __init__(self, legacy, cfg):
        warnings.warn(f"{type(legacy).__name__}: density-control hooks that take the TrainConfig are deprecated; "
                      "give the strategy its settings as dataclass fields (DensityStrategy.from_config)",
                      DeprecationWarning, stacklevel=3)
        super().__init__(max_gaussians=cfg.strategy.max_gaussians)
        self.legacy, self.cfg = legacy, cfg
        self.positions = config_positions(type(legacy))  # looked up once, not at every step

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


__all__ = ["HOOKS", "ConfigHooks", "config_positions"]
