"""The density controls a backbone may name (:attr:`omg4.gaussians.backbone.Backbone.training`), in one table.

Real-Time4DGS names ``"densification"`` (:class:`~omg4.train.densify.Densification`: densify, prune, reset
opacities; rt4dgs §3.4), FreeTimeGS ``"relocation"`` (:class:`~omg4.train.relocate.Relocation`: relocate within a
fixed budget, regularize opacity; FreeTimeGS §3.3–3.4). A backbone may also give a
:class:`~omg4.train.strategy.DensityStrategy` subclass itself; one that names none trains a fixed set of Gaussians,
so a new backbone never inherits another's density control.
"""

from __future__ import annotations

from omg4.errors import OMG4Error
from omg4.gaussians.backbone import Backbone
from omg4.train.densify import Densification
from omg4.train.relocate import Relocation
from omg4.train.strategy import DensityStrategy

STRATEGIES: dict[str, type[DensityStrategy]] = {"densification": Densification, "relocation": Relocation}
"""Every named density control."""


def strategy_for(backbone: Backbone) -> DensityStrategy:
    """A new instance of ``backbone``'s density control (:class:`DensityStrategy` when it names none)."""
    spec = backbone.training
    if spec is None:
        return DensityStrategy()
    if isinstance(spec, str):
        if spec not in STRATEGIES:
            raise OMG4Error(f"backbone {backbone.name} names the density control {spec!r}, which is not one of "
                            f"{', '.join(STRATEGIES)}")
        spec = STRATEGIES[spec]
    return spec()


__all__ = ["STRATEGIES", "strategy_for"]
