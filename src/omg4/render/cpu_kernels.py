"""numba tile kernels: alpha compositing forward and its hand-written backward.

Design (docs/paper-map.md "Rasterizer backends"): one ``prange`` iteration per
image tile; within a tile the Gaussians of the tile's depth-sorted list are visited front
to back (backward: back to front), each only over the pixels of its box
(:func:`omg4.render.api.bin_gaussians`). The backward writes one gradient row per
intersection (each intersection belongs to exactly one tile, so tiles never race);
the caller sums them per Gaussian with ``index_add_``.

Per-pixel rules are gsplat 1.5.3's (``RasterizeToPixels3DGSFwd.cu``/``Bwd.cu``):
``d = mean2d − (pixel + 0.5)``, ``σ = ½(a·dx² + c·dy²) + b·dx·dy``; skip when ``σ < 0`` or
``α = min(α_max, o·e^{−σ}) < 1/255``; stop, without the current Gaussian, once
``T·(1 − α) ≤ 1e-4``; the backward passes no gradient to σ and o where the clamp is
active (``o·e^{−σ} > α_max``). A pixel is skipped when ``σ`` exceeds the per-Gaussian
:func:`omg4.render.binning.sigma_cutoff` (exact). σ is computed in the input precision (as
gsplat) for these tests; ``e^{−σ}`` over a Gaussian's pixel box comes from a recurrence
(:func:`_box_exp`): σ is quadratic in the pixel's x and y, so ``e^{−σ(x+1)} = e^{−σ(x)}·R(x)`` with
``R(x+1) = R(x)·e^{−a}`` along a row, and each row's first value and ratio follow from the previous
row's the same way — six ``exp`` per (Gaussian, tile) and two multiplications per pixel, in float64
(within 10⁻¹¹ of ``exp`` over a 64×64 box, the error growing with the square of the box side; boxes are
clipped to a tile; a box whose σ at a corner exceeds 600, or a conic that is not positive definite,
takes ``exp`` per pixel). Transmittance and sums are accumulated in float64, so
the backward, which runs the same recurrence, recovers ``T_i = T_{i+1} / (1 − α_i)`` by division
without drift.

Backward (per pixel, back to front, ``g = ∂L/∂out_feat``): with ``B`` the g-weighted
features composited behind Gaussian ``i`` plus ``T_final·∂L/∂T_final``,
``∂L/∂α_i = T_i·(f_i·g) − B/(1 − α_i)``; then ``∂L/∂σ = −o·e^{−σ}·∂L/∂α``,
``∂L/∂o = e^{−σ}·∂L/∂α`` and ``∂L/∂f_i = α_i·T_i·g``.

Several views render in one launch: their tiles are numbered view after view and their images
are stacked along the first output axis; a Gaussian row belongs to one view (the caller
concatenates the views' Gaussians), so its pixel box and mean are in that view's pixels.

Arrays (``N`` Gaussians, ``I`` intersections sorted by tile then depth, ``D`` feature channels):
    params: [N, 7] (mean x, mean y, conic a, b, c, opacity, σ cutoff) per Gaussian.
    feats: [N, D] features (colours and view depth) per Gaussian.
    boxes: [N, 4] int32 half-open pixel box (x0, x1, y0, y1) per Gaussian.
    ids: [I] int64 Gaussian of each intersection.
    tile_offsets: [V·T + 1] int64, tile ``t`` owns intersections ``[offsets[t], offsets[t+1])``
        (``T = tiles_per_view`` tiles per view, ``tiles_x`` per row).
    pix_x: [W], pix_y: [H] pixel-centre coordinates (index + 0.5), input dtype.
    consts: [3] (0.5, α_max, 1/255) in the input dtype.

numba's on-disk cache is pointed where it can write (:func:`omg4.kernels.configure_numba_cache`) before the
kernels below are defined (numba binds the cache location at decoration time).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from omg4.kernels import FAST_MATH, configure_numba_cache

TRANSMITTANCE_MIN = 1e-4
"""A pixel stops before the Gaussian that would bring its transmittance to ≤ this (gsplat)."""


configure_numba_cache()


@njit(cache=True, inline="always")
def tile_bounds(tile, tiles_x, tiles_per_view, tile_size, width, height):
    """Pixel box ``[x0, x1) × [y0, y1)`` of a tile in its view's image, clipped to it, and the view's first
    output row.

    Tiles are numbered view by view, row-major within a view; view ``v``'s image occupies output
    rows ``[v·height, (v + 1)·height)``.
    """
    view = tile // tiles_per_view
    local = tile - view * tiles_per_view
    ty = local // tiles_x
    x0 = (local - ty * tiles_x) * tile_size
    y0 = ty * tile_size
    return x0, y0, min(x0 + tile_size, width), min(y0 + tile_size, height), view * height


@njit(cache=True, inline="always")
def clipped_box(boxes, gi, x0, y0, x1, y1):
    """Gaussian ``gi``'s pixel box ``[bx0, bx1) × [by0, by1)`` clipped to the tile ``[x0, x1) × [y0, y1)``."""
    return max(boxes[gi, 0], x0), min(boxes[gi, 1], x1), max(boxes[gi, 2], y0), min(boxes[gi, 3], y1)


@njit(cache=True, inline="always")
def gaussian_terms(params, gi):
    """Gaussian ``gi``'s (mean x, mean y, conic a, b, c, opacity, σ cutoff) from ``params``."""
    return params[gi, 0], params[gi, 1], params[gi, 2], params[gi, 3], params[gi, 4], params[gi, 5], params[gi, 6]


@njit(cache=True, inline="always")
def _box_exp(ca, cb, cc, dx0, dx1, dy0, dy1):
    """Start values of the ``e^{−σ}`` recurrence over a Gaussian's pixel box, float64: ``(E, S, S_step, R, R_step,
    Q, applies)``. The box's pixel offsets run from ``dx0`` to ``dx1`` along a row and ``dy0`` to ``dy1`` down the
    rows, each one less than the one before. σ(dx, dy) = ½(a·dx² + c·dy²) + b·dx·dy, so along a row
    σ(dx − 1) − σ(dx) = a(½ − dx) − b·dy (next pixel: ``e ← e·R``, ``R ← R·Q``, Q = e^{−a}) and down the first
    column σ(dy − 1) − σ(dy) = c(½ − dy) − b·dx0 (next row: ``E ← E·S``, ``S ← S·S_step``, S_step = e^{−c};
    ``R ← R·R_step``, R_step = e^{−b}). E is ``e^{−σ}`` at the box's first pixel and R the ratio to the next
    pixel of that row. Applies to positive definite conics whose σ stays within 600 at the box's corners (σ is
    then convex and non-negative, so every factor inside the box stays finite)."""
    a, b, c = float(ca), float(cb), float(cc)
    x0, x1, y0, y1 = float(dx0), float(dx1), float(dy0), float(dy1)
    corner = 0.0
    for x, y in ((x0, y0), (x1, y0), (x0, y1), (x1, y1)):
        corner = max(corner, 0.5 * (a * x * x + c * y * y) + b * x * y)
    if not (a > 0.0 and a * c > b * b and corner <= 600.0):
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, False
    s0 = 0.5 * (a * x0 * x0 + c * y0 * y0) + b * x0 * y0
    return (math.exp(-s0), math.exp(-(c * (0.5 - y0) - b * x0)), math.exp(-c), math.exp(-(a * (0.5 - x0) - b * y0)),
            math.exp(-b), math.exp(-a), True)


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def composite_forward(params, feats, boxes, ids, tile_offsets, tiles_x, tiles_per_view, tile_size, pix_x, pix_y,
                      consts, out_feat, out_t, out_last):
    """Front-to-back compositing of every tile.

    Writes, for ``V`` views of ``H`` rows stacked along the first axis, ``out_feat [V·H, W, D]``
    (Σ f·α·T, no background), ``out_t [V·H, W]`` float64 final transmittance and ``out_last [V·H, W]``
    int32 (1 + index of the last intersection that contributed to the pixel, 0 if none).
    """
    _, width, n_feat = out_feat.shape
    height = pix_y.shape[0]
    half = consts[0]
    alpha_max = consts[1]
    alpha_min = consts[2]
    n_tiles = tile_offsets.shape[0] - 1
    for tile in prange(n_tiles):
        x0, y0, x1, y1, oy = tile_bounds(tile, tiles_x, tiles_per_view, tile_size, width, height)
        tw = x1 - x0
        n_pix = tw * (y1 - y0)
        trans = np.ones(n_pix)
        acc = np.zeros((n_pix, n_feat))
        last = np.zeros(n_pix, np.int32)
        done = np.zeros(n_pix, np.bool_)
        row_left = np.full(y1 - y0, tw, np.int64)  # pixels of each tile row still compositing
        n_done = 0
        for k in range(tile_offsets[tile], tile_offsets[tile + 1]):
            if n_done == n_pix:
                break
            gi = ids[k]
            bx0, bx1, by0, by1 = clipped_box(boxes, gi, x0, y0, x1, y1)
            if bx0 >= bx1 or by0 >= by1:
                continue
            mx, my, ca, cb, cc, opac, cut = gaussian_terms(params, gi)
            e_row, s_row, s_step, r_row, r_step, step, recur = _box_exp(
                ca, cb, cc, mx - pix_x[bx0], mx - pix_x[bx1 - 1], my - pix_y[by0], my - pix_y[by1 - 1])
            for py in range(by0, by1):
                e_next, ratio = e_row, r_row  # this row's first pixel
                e_row *= s_row
                s_row *= s_step
                r_row *= r_step
                if row_left[py - y0] == 0:
                    continue
                dy = my - pix_y[py]
                row = (py - y0) * tw - x0
                for px in range(bx0, bx1):
                    e_sigma = e_next  # e^{−σ} of this pixel when recur
                    e_next *= ratio
                    ratio *= step
                    li = row + px
                    if done[li]:
                        continue
                    dx = mx - pix_x[px]
                    sigma = half * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    if sigma < 0 or sigma > cut:
                        continue
                    alpha = min(alpha_max, opac * (e_sigma if recur else math.exp(-sigma)))
                    if alpha < alpha_min:
                        continue
                    t = trans[li]
                    t_next = t * (1.0 - alpha)
                    if t_next <= TRANSMITTANCE_MIN:
                        done[li] = True
                        row_left[py - y0] -= 1
                        n_done += 1
                        continue
                    w = alpha * t
                    for d in range(n_feat):
                        acc[li, d] += feats[gi, d] * w
                    trans[li] = t_next
                    last[li] = k + 1
        for py in range(y0, y1):
            for px in range(x0, x1):
                li = (py - y0) * tw + px - x0
                out_t[oy + py, px] = trans[li]
                out_last[oy + py, px] = last[li]
                for d in range(n_feat):
                    out_feat[oy + py, px, d] = acc[li, d]


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def composite_backward(params, feats, boxes, ids, tile_offsets, tiles_x, tiles_per_view, tile_size, pix_x, pix_y,
                       consts, t_final, last_ids, grad_feat, grad_t, out_grad_params, out_grad_feats):
    """Back-to-front gradients per intersection.

    Inputs ``t_final [V·H, W]`` float64 and ``last_ids [V·H, W]`` from :func:`composite_forward`,
    ``grad_feat [V·H, W, D]`` = ∂L/∂out_feat and ``grad_t [V·H, W]`` = ∂L/∂T_final. Writes
    ``out_grad_params [I, 6]`` (∂L/∂ mean x, mean y, conic a, b, c, opacity) and
    ``out_grad_feats [I, D]``; rows of intersections that reached no pixel stay untouched.
    """
    _, width, n_feat = grad_feat.shape
    height = pix_y.shape[0]
    half = consts[0]
    alpha_max = consts[1]
    alpha_min = consts[2]
    n_tiles = tile_offsets.shape[0] - 1
    for tile in prange(n_tiles):
        x0, y0, x1, y1, oy = tile_bounds(tile, tiles_x, tiles_per_view, tile_size, width, height)
        tw = x1 - x0
        n_pix = tw * (y1 - y0)
        trans = np.empty(n_pix)
        last = np.empty(n_pix, np.int32)
        g = np.empty((n_pix, n_feat))
        # behind[p] = Σ_d g_d·(features composited behind the current Gaussian)_d + T_final·∂L/∂T_final:
        # ∂L/∂α_i = T_i·(f_i·g) − behind / (1 − α_i), so one scalar per pixel replaces a [D] buffer
        behind = np.empty(n_pix)
        row_end = np.zeros(y1 - y0, np.int64)  # 1 + last intersection reaching each tile row
        v_feat = np.empty(n_feat)
        start = tile_offsets[tile]
        for py in range(y0, y1):
            for px in range(x0, x1):
                li = (py - y0) * tw + px - x0
                trans[li] = t_final[oy + py, px]
                behind[li] = t_final[oy + py, px] * grad_t[oy + py, px]
                last[li] = last_ids[oy + py, px]
                row_end[py - y0] = max(row_end[py - y0], last_ids[oy + py, px])
                for d in range(n_feat):
                    g[li, d] = grad_feat[oy + py, px, d]
        k_end = max(start, row_end.max())
        for k in range(k_end - 1, start - 1, -1):
            gi = ids[k]
            bx0, bx1, by0, by1 = clipped_box(boxes, gi, x0, y0, x1, y1)
            if bx0 >= bx1 or by0 >= by1:
                continue
            mx, my, ca, cb, cc, opac, cut = gaussian_terms(params, gi)
            v_mx = 0.0
            v_my = 0.0
            v_xx = 0.0
            v_xy = 0.0
            v_yy = 0.0
            v_o = 0.0
            for d in range(n_feat):
                v_feat[d] = 0.0
            e_row, s_row, s_step, r_row, r_step, step, recur = _box_exp(
                ca, cb, cc, mx - pix_x[bx0], mx - pix_x[bx1 - 1], my - pix_y[by0], my - pix_y[by1 - 1])
            for py in range(by0, by1):
                e_next, ratio = e_row, r_row  # this row's first pixel, as in the forward
                e_row *= s_row
                s_row *= s_step
                r_row *= r_step
                if k >= row_end[py - y0]:
                    continue
                dy = my - pix_y[py]
                row = (py - y0) * tw - x0
                for px in range(bx0, bx1):
                    e_sigma = e_next  # the forward's e^{−σ} of this pixel when recur
                    e_next *= ratio
                    ratio *= step
                    li = row + px
                    if k >= last[li]:
                        continue
                    dx = mx - pix_x[px]
                    sigma = half * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    if sigma < 0 or sigma > cut:
                        continue
                    vis = e_sigma if recur else math.exp(-sigma)
                    alpha = min(alpha_max, opac * vis)
                    if alpha < alpha_min:
                        continue
                    ra = 1.0 / (1.0 - alpha)
                    t = trans[li] * ra
                    trans[li] = t
                    fac = alpha * t
                    fg = 0.0
                    for d in range(n_feat):
                        gd = g[li, d]
                        fg += feats[gi, d] * gd
                        v_feat[d] += fac * gd
                    v_alpha = t * fg - ra * behind[li]
                    behind[li] += fac * fg
                    if opac * vis <= alpha_max:  # else the alpha clamp is active: no gradient
                        v_o += vis * v_alpha
                        v_sigma = -opac * vis * v_alpha
                        sx = v_sigma * dx
                        sy = v_sigma * dy
                        v_mx += sx  # moments of v_sigma; the conic is applied once below
                        v_my += sy
                        v_xx += sx * dx
                        v_xy += sx * dy
                        v_yy += sy * dy
            # ∂σ/∂mean = conic·d, ∂σ/∂(a, b, c) = (dx²/2, dx·dy, dy²/2)
            out_grad_params[k, 0] = ca * v_mx + cb * v_my
            out_grad_params[k, 1] = cb * v_mx + cc * v_my
            out_grad_params[k, 2] = 0.5 * v_xx
            out_grad_params[k, 3] = v_xy
            out_grad_params[k, 4] = 0.5 * v_yy
            out_grad_params[k, 5] = v_o
            for d in range(n_feat):
                out_grad_feats[k, d] = v_feat[d]
