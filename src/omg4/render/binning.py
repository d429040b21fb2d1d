"""Which tiles and pixels each projected Gaussian touches, vectorized in torch.

Tile lists follow gsplat 1.5.3's ``isect_tiles``/``isect_offset_encode`` (docs/paper-map.md
"Rasterizer backends"): a Gaussian with box
half-widths ``(rx, ry)`` around ``(mx, my)`` covers tiles ``floor(m/ts − r/ts) …
ceil(m/ts + r/ts) − 1`` (clamped to the grid); intersections are sorted by the key
``tile_id << 32 | float32 bits of depth``, i.e. by tile, then front to back.

The per-Gaussian pixel boxes and exp-skip thresholds let the CPU kernels visit only the
pixels where a Gaussian can pass gsplat's ``alpha ≥ 1/255`` test, which keeps them exact.
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


def tile_ranges(means2d: torch.Tensor, radii: torch.Tensor, tile_size: int, tiles_x: int,
                tiles_y: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Half-open tile rectangles ``(tmin [N, 2], tmax [N, 2])`` int64, empty where ``radii`` is 0.

    ``means2d [N, 2]`` pixels, ``radii [N, 2]`` int box half-widths (gsplat ``isect_tiles``).
    """
    m = means2d.detach().float() / tile_size
    r = radii.float() / tile_size
    hi = torch.tensor([tiles_x, tiles_y], dtype=m.dtype, device=m.device)
    tmin = torch.floor(m - r).clamp(min=0).minimum(hi).long()
    tmax = torch.ceil(m + r).clamp(min=0).minimum(hi).long()
    tmax = torch.where((radii > 0).all(dim=-1, keepdim=True), tmax, tmin)
    return tmin, tmax


def bin_tiles(means2d: torch.Tensor, radii: torch.Tensor, depths: torch.Tensor, width: int, height: int,
              tile_size: int = 16, *, views: torch.Tensor | None = None, num_views: int = 1) -> TileBins:
    """Intersect Gaussians with the tile grid and sort each tile's list front to back.

    With ``views [N]`` (the view of each row) the rows of ``num_views`` views are binned at once:
    view ``v``'s tiles are numbered after those of views ``0 … v − 1``.

    Args:
        means2d: [N, 2] pixel coordinates.
        radii: [N, 2] int box half-widths, 0 for culled Gaussians.
        depths: [N] view depth; as in gsplat the sort key holds its float32 bit pattern
            (monotone for positive depths), ties keep the Gaussians' order.
        width, height: image size in pixels.
        tile_size: tile side in pixels.
    """
    device = means2d.device
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    tmin, tmax = tile_ranges(means2d, radii, tile_size, tiles_x, tiles_y)
    span = tmax - tmin  # [N, 2]
    counts = span[:, 0] * span[:, 1]
    hit = torch.nonzero(counts).squeeze(1)
    counts = counts[hit]
    first = torch.cumsum(counts, 0) - counts
    # one int32 gather for what an intersection needs from its Gaussian (tile ids < 2^31)
    per_gauss = torch.stack([tmin[hit, 0], tmin[hit, 1], span[hit, 0]], dim=1).int()
    slot = torch.repeat_interleave(torch.arange(hit.shape[0], device=device), counts)  # [I]
    tx0, ty0, w = per_gauss.index_select(0, slot).unbind(1)
    local = (torch.arange(slot.shape[0], device=device) - first.index_select(0, slot)).int()
    row = local // w
    tile_id = ((ty0 + row) * tiles_x + tx0 + (local - row * w)).long()
    if views is not None:
        tile_id = tile_id + views[hit].index_select(0, slot) * (tiles_x * tiles_y)
    bits = depths.detach().float()[hit].view(torch.int32).long() & 0xFFFFFFFF
    gid = hit.index_select(0, slot)
    keys, perm = torch.sort((tile_id << 32) | bits.index_select(0, slot), stable=True)
    num_tiles = tiles_x * tiles_y * num_views
    tile_counts = torch.bincount(keys >> 32, minlength=num_tiles)
    offsets = torch.zeros(num_tiles + 1, dtype=torch.int64, device=device)
    torch.cumsum(tile_counts, 0, out=offsets[1:])
    return TileBins(gaussian_ids=gid.index_select(0, perm), tile_offsets=offsets, tiles_x=tiles_x, tiles_y=tiles_y,
                    tile_size=tile_size)


def sigma_cutoff(opacities: torch.Tensor) -> torch.Tensor:
    """[N] exponent above which ``o·exp(−σ) < 1/255`` for sure: ``ln(255·o) + SIGMA_MARGIN``.

    Skipping ``exp`` when σ exceeds it is exact (no kept α is lost; the skip made the forward
    pass 1.7× faster); computed in float64.
    """
    o = opacities.detach().double().clamp(min=1e-30)
    return torch.log(o / ALPHA_THRESHOLD) + SIGMA_MARGIN


def pixel_boxes(means2d: torch.Tensor, cov2d_diag: torch.Tensor, cutoff: torch.Tensor, width: int,
                height: int) -> torch.Tensor:
    """[N, 4] int32 half-open pixel ranges (x0, x1, y0, y1) holding every pixel with σ ≤ ``cutoff``.

    The ellipse ``½ dᵀ Σ⁻¹ d ≤ cut`` spans ``|dx| ≤ sqrt(2·cut·Σ_xx)``; pixel ``j`` has its
    centre at ``j + 0.5``. The half-widths are widened by 0.1 % + 0.001 px so that rounding
    in the conic (inverse of a possibly elongated Σ) never puts a passing pixel outside.
    ``means2d [N, 2]``, ``cov2d_diag [N, 2]`` (with eps2d), ``cutoff [N]``.
    """
    m = means2d.detach().double()
    half = torch.sqrt(2.0 * cutoff.clamp(min=0.0)[:, None] * cov2d_diag.double()) * (1 + 1e-3) + 1e-3
    limit = torch.tensor([width, height], dtype=torch.float64, device=m.device)
    lo = torch.ceil(m - half - 0.5).clamp(min=0).minimum(limit)  # [N, 2]
    hi = (torch.floor(m + half - 0.5) + 1).clamp(min=0).minimum(limit)
    return torch.stack([lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1]], dim=-1).to(torch.int32)
