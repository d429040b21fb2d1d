"""The compositing work of one rendered frame, counted: how many (pixel, Gaussian) pairs the CPU kernels visit
and how many they blend.

Both backends follow gsplat 1.5.3's per-pixel rules, so the number of Gaussians blended into each pixel
(``α ≥ 1/255``, before the transmittance falls to 1e-4) is work every exact renderer must do, on any
hardware; the visited pairs are those of the pixel boxes the numba kernels walk
(:func:`omg4.render.api.project_and_bin`; the kernels also skip rows and tiles whose pixels are all done,
which this count does not — under 0.1 % on the shared scenes). A compressed model's Gaussians are fewer
but larger, so its frame keeps much of its baseline's blending work however cheap the per-Gaussian part
becomes: on the CPU this is what bounds the frame-rate ratio of OMG4 over its baseline (README "Hot paths").

The count re-renders the frame's transmittance with ``exp`` per pixel and refuses to report when it does
not match the renderer's alpha (the rules would then differ). The renderer's ``e^{−σ}`` comes from a
float64 recurrence, so a Gaussian whose α lies within rounding of 1/255, or whose blending brings the
transmittance within rounding of 1e-4, can be blended by one and not by the other: a pixel or two per frame.
The check sees transmittance only; the counts themselves are tested against a brute-force count
(``tests/render/test_compositing_load.py``); ``benchmarks/speed/render_frame.py`` reports
it beside the frame times.
"""

from __future__ import annotations

import inspect
import math

import numpy as np
import torch
from numba import njit, prange

from omg4.render import rasterize
from omg4.kernels import as_numpy, keeping_torch_threads
from omg4.render.api import project_and_bin
from omg4.render.cpu_kernels import TRANSMITTANCE_MIN, clipped_box, gaussian_terms, tile_bounds
from omg4.render.projection import ALPHA_THRESHOLD
from omg4.render.view import camera_tensors, render_view

RASTER_DEFAULTS = {name: p.default for name, p in inspect.signature(rasterize).parameters.items()
                   if name in ("near", "far", "eps2d", "alpha_max", "tile_size")}
"""The settings ``render_view`` renders with (``rasterize``'s defaults)."""

TRANSMITTANCE_TOLERANCE = 1e-5
"""Agreement expected between the counted transmittance and the renderer's ``1 − alpha`` (float32 output)."""

MAX_THRESHOLD_FLIPS = 1e-3
"""Largest fraction of pixels allowed to differ by more (a Gaussian at one of the thresholds decided apart);
one pixel is always allowed."""


@njit(parallel=True, cache=True)
def _count(params, consts, pix_x, pix_y, boxes, ids, tile_offsets, tiles_x, tile_size, blended, visited, trans):
    """Per pixel: ``blended`` Gaussians, ``visited`` box pixels and the final transmittance ``trans`` (float64,
    starting at 1) of one view, tile by tile, front to back (gsplat's rules, ``exp`` per pixel; σ in the input
    precision from the pixel centres ``pix_x``/``pix_y``, as the renderer). Tiles, boxes and parameters are
    read with the compositing kernels' own functions."""
    height, width = trans.shape
    half, alpha_max, alpha_min = consts[0], consts[1], consts[2]
    n_tiles = tile_offsets.shape[0] - 1
    for tile in prange(n_tiles):
        x0, y0, x1, y1, _ = tile_bounds(tile, tiles_x, n_tiles, tile_size, width, height)
        done = np.zeros((y1 - y0, x1 - x0), np.bool_)
        for k in range(tile_offsets[tile], tile_offsets[tile + 1]):
            gi = ids[k]
            bx0, bx1, by0, by1 = clipped_box(boxes, gi, x0, y0, x1, y1)
            mx, my, ca, cb, cc, opac, cut = gaussian_terms(params, gi)
            for py in range(by0, by1):
                dy = my - pix_y[py]
                for px in range(bx0, bx1):
                    visited[py, px] += 1
                    if done[py - y0, px - x0]:
                        continue
                    dx = mx - pix_x[px]
                    sigma = half * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    if sigma < 0 or sigma > cut:
                        continue
                    alpha = min(alpha_max, opac * math.exp(-sigma))
                    if alpha < alpha_min:
                        continue
                    t_next = trans[py, px] * (1.0 - alpha)
                    if t_next <= TRANSMITTANCE_MIN:
                        done[py - y0, px - x0] = True
                        continue
                    trans[py, px] = t_next
                    blended[py, px] += 1


def compositing_load(model, camera, timestamp: float) -> dict:
    """``{"visited_per_pixel", "blended_per_pixel"}`` of ``model`` rendered (CPU) at ``camera`` and ``timestamp``:
    the mean over the image's pixels of the box pixels the kernels visit and of the Gaussians blended.

    Raises:
        RuntimeError: the counted transmittance differs from the renderer's beyond the tolerances above.
    """
    with torch.no_grad():
        rendered, sl = render_view(model, camera, timestamp, backend="cpu")
    viewmat, K, _ = camera_tensors(camera)
    width, height = camera.width, camera.height
    settings = {k: v for k, v in RASTER_DEFAULTS.items() if k != "alpha_max"}
    means, opacities = sl.means.detach(), sl.opacities.detach()
    proj, bins, cutoff, boxes = project_and_bin(means, sl.covars.detach(), opacities, None, viewmat[None], K[None],
                                                width, height, **settings)
    params = torch.cat([proj.means2d, proj.conics, opacities[:, None].to(means.dtype),
                        cutoff.to(means.dtype)[:, None]], dim=1)
    dtype = as_numpy(params).dtype
    consts = np.array([0.5, RASTER_DEFAULTS["alpha_max"], ALPHA_THRESHOLD], dtype=dtype)
    pix_x, pix_y = np.arange(width, dtype=dtype) + dtype.type(0.5), np.arange(height, dtype=dtype) + dtype.type(0.5)
    blended, visited = np.zeros((height, width), np.int64), np.zeros((height, width), np.int64)
    trans = np.ones((height, width))
    with keeping_torch_threads():
        _count(as_numpy(params), consts, pix_x, pix_y, as_numpy(boxes), as_numpy(bins.gaussian_ids), as_numpy(bins.tile_offsets),
               bins.tiles_x, bins.tile_size, blended, visited, trans)
    gap = np.abs(trans - (1.0 - rendered.alpha[..., 0].double().numpy()))
    off = gap > TRANSMITTANCE_TOLERANCE
    if off.sum() > max(1.0, MAX_THRESHOLD_FLIPS * off.size):
        raise RuntimeError(f"counted transmittance differs from the renderer's by up to {gap.max():.3g} at "
                           f"{int(off.sum())} pixels: the rules differ")
    pixels = width * height
    return {"visited_per_pixel": float(visited.sum()) / pixels, "blended_per_pixel": float(blended.sum()) / pixels}
