"""The tile grid, its intersection lists and the σ cutoffs that bound each Gaussian's pixels.

Tile lists follow gsplat 1.5.3's ``isect_tiles``/``isect_offset_encode`` (docs/paper-map.md "Rasterizer
backends"); :func:`omg4.render.api.bin_gaussians` builds them with the numba kernels of
:mod:`omg4.render.forward_kernels`. The per-Gaussian pixel boxes and exp-skip thresholds
(:func:`sigma_cutoff`) let the CPU kernels visit only the pixels where a Gaussian can pass gsplat's
``alpha ≥ 1/255`` test, which keeps them exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from omg4.render.projection import ALPHA_THRESHOLD

SIGMA_MARGIN = 1e-4
"""Slack added to the exact skip exponent ln(255·o): far above float32 rounding of exp."""


@dataclass
class TileBins:
    """Gaussian–tile intersections sorted by tile, then depth.

    Attributes:
        gaussian_ids: [I] int64 Gaussian index of each intersection.
        tile_offsets: [V·T + 1] int64; tile ``t`` owns intersections ``tile_offsets[t]:tile_offsets[t + 1]``
            (tiles numbered row-major, view after view, ``T = tiles_x · tiles_y`` per view).
        tiles_x: tiles per image row.
        tiles_y: tiles per image column.
        tile_size: tile side in pixels.
    """

    gaussian_ids: torch.Tensor
    tile_offsets: torch.Tensor
    tiles_x: int
    tiles_y: int
    tile_size: int

    @property
    def num_intersections(self) -> int:
        return int(self.gaussian_ids.shape[0])


def tile_grid(width: int, height: int, tile_size: int) -> tuple[int, int]:
    """(tiles_x, tiles_y) covering a ``width × height`` image."""
    return math.ceil(width / tile_size), math.ceil(height / tile_size)


def sigma_cutoff(opacities: torch.Tensor) -> torch.Tensor:
    """[N] exponent above which ``o·exp(−σ) < 1/255`` for sure: ``ln(255·o) + SIGMA_MARGIN``.

    Skipping ``exp`` when σ exceeds it is exact (no kept α is lost); computed in float64.
    """
    o = opacities.detach().double().clamp(min=1e-30)
    return torch.log(o / ALPHA_THRESHOLD) + SIGMA_MARGIN
