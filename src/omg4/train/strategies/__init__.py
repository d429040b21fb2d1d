"""The density controls a backbone may name (:attr:`omg4.gaussians.backbone.Backbone.training`), in one table, and
the settings they own.

Real-Time4DGS names ``"densification"`` (:class:`~omg4.train.strategies.densification.Densification`: densify,
prune, reset opacities; rt4dgs §3.4), FreeTimeGS ``"relocation"``
(:class:`~omg4.train.strategies.relocation.Relocation`: relocate within a fixed budget, regularize opacity;
FreeTimeGS §3.3–3.4). A backbone may also give a :class:`~omg4.train.strategies.base.DensityStrategy` subclass
itself; one that names none trains a fixed set of Gaussians, so a new backbone never inherits another's density
control.

Each strategy's fields are its settings (defaults and help beside them). :class:`StrategySettings`, the training
config's ``strategy`` table, is made from the strategies of :data:`STRATEGIES`: every field of any of them once, a
name two strategies share (the schedule of :class:`~omg4.train.strategies.base.ScheduledEvents`, the budget) being
one setting. A strategy added to the table brings its settings to config files, ``--set strategy.<field>=…`` and
the commands' flags with no other change.
"""

from __future__ import annotations

import dataclasses
import inspect
import typing

from omg4.errors import OMG4Error
from omg4.gaussians.backbone import Backbone
from omg4.train.strategies.base import RUN_FIELDS, DensityStrategy, ScheduledEvents
from omg4.train.strategies.densification import Densification
from omg4.train.strategies.relocation import Relocation

STRATEGIES: dict[str, type[DensityStrategy]] = {"densification": Densification, "relocation": Relocation}
"""Every named density control."""

HOOKS = ("initial_points", "grows_until", "collects_statistics", "regularizer", "after_step")
"""The hooks the trainer calls (:class:`~omg4.train.strategies.base.DensityStrategy`)."""


def settings_class(strategies: typing.Iterable[type[DensityStrategy]]) -> type:
    """A frozen dataclass holding every setting of ``strategies`` (their fields but :data:`RUN_FIELDS`) once, with
    its default and help. A name two strategies declare with different defaults or types is an error."""
    fields: dict[str, tuple] = {}
    for cls in strategies:
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if f.name in RUN_FIELDS:
                continue
            spec = (f.name, hints[f.name], dataclasses.field(default=f.default, metadata=f.metadata))
            if f.name in fields and (fields[f.name][1], fields[f.name][2].default) != (spec[1], f.default):
                raise TypeError(f"{cls.__name__}.{f.name} differs from the setting of the same name of another "
                                "strategy")
            fields.setdefault(f.name, spec)
    made = dataclasses.make_dataclass("StrategySettings", list(fields.values()), frozen=True)
    made.__module__ = __name__
    made.__doc__ = ("The density controls' settings, nested in the training config as ``strategy``: each field is a "
                    f"field of one or more of {', '.join(c.__name__ for c in strategies)}.")
    return made


StrategySettings = settings_class([DensityStrategy, *STRATEGIES.values()])


def strategy_for(backbone: Backbone, cfg) -> DensityStrategy:
    """A new instance of ``backbone``'s density control with its settings from the run's config ``cfg``
    (:meth:`~omg4.train.strategies.base.DensityStrategy.from_config`; :class:`DensityStrategy` when it names
    none)."""
    spec = backbone.training
    if spec is None:
        return DensityStrategy.from_config(cfg)
    if isinstance(spec, str):
        if spec not in STRATEGIES:
            raise OMG4Error(f"backbone {backbone.name} names the density control {spec!r}, which is not one of "
                            f"{', '.join(STRATEGIES)}")
        spec = STRATEGIES[spec]
    if any("cfg" in inspect.signature(getattr(spec, hook)).parameters for hook in HOOKS):
        raise OMG4Error(f"{spec.__name__}: density-control hooks no longer take the TrainConfig; give the strategy "
                        "its settings as dataclass fields (DensityStrategy.from_config)")
    return spec.from_config(cfg)


__all__ = ["STRATEGIES", "DensityStrategy", "ScheduledEvents", "StrategySettings", "settings_class", "strategy_for"]
