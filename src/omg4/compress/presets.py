"""OMG4 size presets L / M / S / T (paper appendix "Additional Implementation Details").

* M (the official N3DV config): τ_GS = 0.2, pruning quantile p = 0.8; codebooks
  b_s = 2^9 (scale), b_r = 2^13 (rotation), b_f = 2^10 (appearance features),
  2^9 for the time scale and 2^13 for the right quaternion.
* L: τ_GS = 0.4, p = 0.8, the M codebooks.
* S and T: τ_GS = 0.3, p = 0.9; the 3D scale codebook shrinks to b_s = 2^8, the 4D
  codebooks stay. The appendix states the same settings for S and T, yet its Table 1 has
  T with 19% fewer Gaussians than S (111,402 vs 137,414 on N3DV), which codebooks cannot
  cause. omg4's T therefore samples τ_GS = 0.25 (≈ 0.83 × S's count) with S's codebooks:
  an inference from the table, not a stated setting.

Sub-vector lengths follow OMG (reference omg4 §7): scale 1, rotation 2, appearance 2,
time scale 1, right quaternion 2.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from omg4.errors import OMG4Error

SUB_LENGTHS = {"scale": 1, "rotation": 2, "app": 2, "scale_t": 1, "rotation_r": 2}


@dataclass(frozen=True)
class SizePreset:
    """Rate knobs of one OMG4 size: sampling ratio, pruning quantile, codebook size per SVQ attribute."""

    name: str
    tau_gs: float
    prune_quantile: float
    codebook_sizes: dict[str, int] = field(default_factory=dict)

    def codebook(self, attribute: str) -> tuple[int, int]:
        """(sub-vector length, codebook size) of an SVQ attribute."""
        return SUB_LENGTHS[attribute], self.codebook_sizes[attribute]


_M_CODEBOOKS = {"scale": 2**9, "rotation": 2**13, "app": 2**10, "scale_t": 2**9, "rotation_r": 2**13}

SIZE_PRESETS: dict[str, SizePreset] = {
    "L": SizePreset("L", 0.4, 0.8, dict(_M_CODEBOOKS)),
    "M": SizePreset("M", 0.2, 0.8, dict(_M_CODEBOOKS)),
    "S": SizePreset("S", 0.3, 0.9, {**_M_CODEBOOKS, "scale": 2**8}),
    "T": SizePreset("T", 0.25, 0.9, {**_M_CODEBOOKS, "scale": 2**8}),
}


def size_preset(name: str) -> SizePreset:
    """The preset called ``name`` (case-insensitive)."""
    try:
        return SIZE_PRESETS[name.upper()]
    except KeyError:
        raise OMG4Error(f"unknown size preset '{name}' (choose from {', '.join(SIZE_PRESETS)})") from None
