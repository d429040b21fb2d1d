"""OMG4 size presets (paper appendix "Additional Implementation Details"), by backbone.

Each backbone lists its sizes (:attr:`omg4.gaussians.backbone.Backbone.size_presets`): Real-Time4DGS L / M /
S / T (M the official N3DV config; T's sampling ratio inferred from the paper's Table 1), FreeTimeGS L / S
(Table 3). A size is a sampling ratio τ_GS, a pruning quantile p and a codebook size per SVQ attribute;
sub-vector lengths are the backbone's (OMG's, omg4 §7).
"""

from __future__ import annotations

from omg4.errors import OMG4Error
from omg4.gaussians.backbone import SizePreset, backbone_named


def presets_of(backbone: str) -> dict[str, SizePreset]:
    """The size presets of ``backbone`` by name."""
    return dict(backbone_named(backbone).size_presets)


def size_preset(name: str | None, backbone: str = "rt4dgs") -> SizePreset:
    """The preset called ``name`` (case-insensitive; None: the backbone's default) of ``backbone``."""
    spec = backbone_named(backbone)
    key = spec.default_preset if name is None else str(name).upper()
    try:
        return spec.size_presets[key]
    except KeyError:
        raise OMG4Error(f"unknown size preset '{name}' for {backbone} (choose from "
                        f"{', '.join(spec.size_presets)})") from None


__all__ = ["SizePreset", "presets_of", "size_preset"]
