"""Tile binning (numba, ``render.api.bin_gaussians``) vs gsplat's pure-torch ``_isect_tiles``/``_isect_offset_encode``
(where gsplat imports); several views binned at once vs each alone; pixel boxes by brute force."""

from __future__ import annotations

import pytest
import torch
from dense_reference import random_scene

from omg4.render.api import bin_gaussians
from omg4.render.binning import sigma_cutoff, tile_grid
from omg4.render.projection import Projected, project_gaussians


def _projected(seed, n, width, height, **kw):
    sc = random_scene(seed, n, width, height, **kw)
    p = project_gaussians(sc.means.float(), sc.covars.float(), sc.viewmat.float(), sc.K.float(), width, height,
                          opacities=sc.opacities.float())
    return sc, p


@pytest.mark.parametrize("tile_size,size", [(16, (45, 37)), (8, (40, 24)), (5, (23, 31))])
def test_bins_match_gsplat(tile_size, size):
    gsplat_torch = pytest.importorskip("gsplat.cuda._torch_impl")
    width, height = size
    sc, p = _projected(11, 150, width, height, scale=0.15)
    bins, _ = bin_gaussians(p, sigma_cutoff(sc.opacities.float()), None, 1, width, height, tile_size)
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    _, isect_ids, flatten_ids = gsplat_torch._isect_tiles(p.means2d.detach()[None], p.radii[None],
                                                          p.depths.detach()[None], tile_size, tiles_x, tiles_y)
    offsets = gsplat_torch._isect_offset_encode(isect_ids, 1, tiles_x, tiles_y).flatten()
    assert bins.num_intersections > 2 * int(p.visible.sum())  # many Gaussians span several tiles
    assert torch.equal(bins.gaussian_ids, flatten_ids.long())
    assert torch.equal(bins.tile_offsets[:-1], offsets.long())
    assert int(bins.tile_offsets[-1]) == bins.num_intersections


def test_views_binned_at_once_equal_each_view_binned_alone():
    """Rows of three views (view 1 with no rows) in one call: view ``v``'s tiles come after those of the views
    before it, and each view's lists and boxes are its own single-view ones, rows offset."""
    width, height, tile_size = 37, 29, 8
    parts = [_projected(seed, n, width, height, scale=0.15) for seed, n in ((21, 120), (22, 0), (23, 150))]
    cuts = [sigma_cutoff(sc.opacities.float()) for sc, _ in parts]
    joint = Projected(*(torch.cat([getattr(p, f) for _, p in parts])
                        for f in ("means2d", "conics", "depths", "cov2d_diag", "radii", "visible")))
    views = torch.cat([torch.full((p.radii.shape[0],), v) for v, (_, p) in enumerate(parts)])
    bins, boxes = bin_gaussians(joint, torch.cat(cuts), views, 3, width, height, tile_size)
    per_view = bins.tiles_x * bins.tiles_y
    start = 0
    for v, ((_, p), cut) in enumerate(zip(parts, cuts)):
        alone, alone_boxes = bin_gaussians(p, cut, None, 1, width, height, tile_size)
        offsets = bins.tile_offsets[v * per_view:(v + 1) * per_view + 1]
        assert torch.equal(offsets - offsets[0], alone.tile_offsets)
        assert torch.equal(bins.gaussian_ids[offsets[0]:offsets[-1]] - start, alone.gaussian_ids)
        assert torch.equal(boxes[start:start + p.radii.shape[0]], alone_boxes)
        start += p.radii.shape[0]
    assert bins.num_intersections > 200


def test_empty_bins():
    z = torch.zeros(0)
    empty = Projected(means2d=torch.zeros(0, 2), conics=torch.zeros(0, 3), depths=z, cov2d_diag=torch.zeros(0, 2),
                      radii=torch.zeros(0, 2, dtype=torch.int32), visible=torch.zeros(0, dtype=torch.bool))
    bins, boxes = bin_gaussians(empty, z.double(), None, 1, 20, 10, 16)
    assert bins.num_intersections == 0 and bins.tile_offsets.tolist() == [0, 0, 0] and boxes.shape == (0, 4)


def test_pixel_boxes_hold_every_pixel_above_threshold():
    width, height = 40, 30
    sc, p = _projected(12, 300, width, height, scale=0.2, opacity=(0.0, 1.0))
    cut = sigma_cutoff(sc.opacities.float())
    boxes = bin_gaussians(p, cut, None, 1, width, height)[1].long()
    ys, xs = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    d = p.means2d.detach().double()[:, None, None, :] - torch.stack([xs, ys], -1).double()  # [N, H, W, 2]
    a, b, c = p.conics.detach().double().unbind(-1)
    sigma = 0.5 * (a[:, None, None] * d[..., 0] ** 2 + c[:, None, None] * d[..., 1] ** 2) + b[:, None, None] * d[
        ..., 0] * d[..., 1]
    alpha = sc.opacities[:, None, None] * torch.exp(-sigma)
    hit = (alpha >= 1 / 255) & p.visible[:, None, None]
    jx = torch.arange(width)
    jy = torch.arange(height)
    in_box = (((jx >= boxes[:, 0, None]) & (jx < boxes[:, 1, None]))[:, None, :]
              & ((jy >= boxes[:, 2, None]) & (jy < boxes[:, 3, None]))[:, :, None])
    assert int(hit.sum()) > 1000
    assert not (hit & ~in_box).any()
    # and the boxes are tight: at most one pixel of slack on each side of the exact ellipse box
    half = torch.sqrt(2 * cut[:, None].clamp(min=0) * p.cov2d_diag.double())
    width_box = (boxes[:, 1] - boxes[:, 0]).double()
    vis = p.visible & (boxes[:, 0] > 0) & (boxes[:, 1] < width)
    assert vis.sum() > 50 and torch.all(width_box[vis] <= 2 * half[vis, 0] + 2)
