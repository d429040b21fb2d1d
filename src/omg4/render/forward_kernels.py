"""The CPU rasterizer's per-Gaussian projection and tile binning, as numba kernels.

Binning (:func:`bin_projected`, :func:`group_by_tile`; called by :func:`omg4.render.api.bin_gaussians`) follows
gsplat 1.5.3's ``isect_tiles``/``isect_offset_encode`` (docs/paper-map.md "Rasterizer backends"): one parallel
pass per Gaussian gives its tile rectangle and pixel box, a radix sort orders the Gaussians by the float32 bit
pattern of their depth (ties in Gaussian order, as a stable sort of the gsplat key leaves them) and a counting
pass lists each tile's intersections in that order.

When nothing asks for a gradient (evaluation, videos, the viewer) :func:`project_forward` also replaces the
differentiable torch projection (:func:`omg4.render.projection.project_gaussians`, many small torch
operations; rt4dgs §1.5) and bins in the same pass: it repeats that path's arithmetic operation by operation
in the input precision, so float32 rounding falls alike — it decides, e.g., whether a needle-thin Gaussian's
2D determinant is positive. That holds bit for bit with torch's CPU kernels, whose tiny matrix products sum
first term first (a BLAS that fused multiply-adds there could round differently). The opacity-dependent box
width and σ cutoff come in from :func:`~omg4.render.projection.opacity_extend` and
:func:`~omg4.render.binning.sigma_cutoff`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from omg4.kernels import configure_numba_cache

configure_numba_cache()


CONSTS = ("near", "far", "eps2d", "one", "fov_margin", "half_width", "half_height", "width", "height", "radius_max")
"""The entries of :func:`project_forward`'s ``consts`` array, in the input dtype (so that the arithmetic stays in it)."""


@njit(parallel=True, cache=True)
def project_forward(means, covars, extend, cutoff, views, viewmats, Ks, consts, width, height, tile_size, tiles_x,
                    tiles_y, means2d, conics, depths, cov_diag, radii, boxes, tiles):
    """Project every Gaussian through its view's camera and derive its pixel box and tile rectangle.

    The projection is ``project_gaussians``' with opacities, operation by operation in the input precision (the
    ``consts`` of :data:`CONSTS` carry every constant in it; sums run first term first, as torch's small matrix
    products do), so that float32 rounding — which decides, e.g., whether an elongated Gaussian's 2D determinant
    is positive — falls alike. Inputs: ``means [N, 3]``, ``covars [N, 3, 3]``, ``extend [N]`` box half-widths in
    standard deviations (:func:`omg4.render.projection.opacity_extend`), ``cutoff [N]`` float64 σ cutoffs
    (:func:`omg4.render.binning.sigma_cutoff`), ``views [N]`` int64, ``viewmats [V, 4, 4]``, ``Ks [V, 3, 3]``.
    Outputs (written): ``means2d [N, 2]``, ``conics [N, 3]``, ``depths [N]``, ``cov_diag [N, 2]`` (input precision),
    ``radii [N, 2]`` int32, and, as :func:`bin_projected`, ``boxes [N, 4]`` int32 and ``tiles [N, 4]`` int64.
    """
    near, far, eps2d, one, fov_margin = consts[0], consts[1], consts[2], consts[3], consts[4]
    half_width, half_height, width_f, height_f, radius_max = consts[5], consts[6], consts[7], consts[8], consts[9]
    zero, half = one - one, one / (one + one)
    ts32 = np.float32(tile_size)
    for i in prange(means.shape[0]):
        v = views[i]
        m0, m1, m2 = means[i, 0], means[i, 1], means[i, 2]
        r = viewmats[v]
        x = m0 * r[0, 0] + m1 * r[0, 1] + m2 * r[0, 2] + r[0, 3]
        y = m0 * r[1, 0] + m1 * r[1, 1] + m2 * r[1, 2] + r[1, 3]
        z = m0 * r[2, 0] + m1 * r[2, 1] + m2 * r[2, 2] + r[2, 3]
        depths[i] = z
        in_range = z >= near and z <= far
        if not in_range:
            z = one
        k = Ks[v]
        fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
        tan_fovx = (one / fx) * half_width  # torch's scalar / tensor: the reciprocal times the scalar
        tan_fovy = (one / fy) * half_height
        rz = one / z
        tx = z * min(max(x * rz, -(cx / fx + fov_margin * tan_fovx)), (width_f - cx) / fx + fov_margin * tan_fovx)
        ty = z * min(max(y * rz, -(cy / fy + fov_margin * tan_fovy)), (height_f - cy) / fy + fov_margin * tan_fovy)
        # J R (2 × 3) with J = [[fx/z, 0, −fx·tx/z²], [0, fy/z, −fy·ty/z²]]
        j00, j02 = fx * rz, -fx * tx * rz * rz
        j11, j12 = fy * rz, -fy * ty * rz * rz
        a0 = j00 * r[0, 0] + zero * r[1, 0] + j02 * r[2, 0]
        a1 = j00 * r[0, 1] + zero * r[1, 1] + j02 * r[2, 1]
        a2 = j00 * r[0, 2] + zero * r[1, 2] + j02 * r[2, 2]
        b0 = zero * r[0, 0] + j11 * r[1, 0] + j12 * r[2, 0]
        b1 = zero * r[0, 1] + j11 * r[1, 1] + j12 * r[2, 1]
        b2 = zero * r[0, 2] + j11 * r[1, 2] + j12 * r[2, 2]
        c = covars[i]
        s00, s11, s22 = half * (c[0, 0] + c[0, 0]), half * (c[1, 1] + c[1, 1]), half * (c[2, 2] + c[2, 2])
        s01, s02, s12 = half * (c[0, 1] + c[1, 0]), half * (c[0, 2] + c[2, 0]), half * (c[1, 2] + c[2, 1])
        # (J R) S, then ((J R) S)(J R)ᵀ
        p0 = a0 * s00 + a1 * s01 + a2 * s02
        p1 = a0 * s01 + a1 * s11 + a2 * s12
        p2 = a0 * s02 + a1 * s12 + a2 * s22
        q0 = b0 * s00 + b1 * s01 + b2 * s02
        q1 = b0 * s01 + b1 * s11 + b2 * s12
        q2 = b0 * s02 + b1 * s12 + b2 * s22
        c00 = (p0 * a0 + p1 * a1 + p2 * a2) + eps2d
        c11 = (q0 * b0 + q1 * b1 + q2 * b2) + eps2d
        c01 = p0 * b0 + p1 * b1 + p2 * b2
        det = c00 * c11 - c01 * c01
        visible = in_range and det > 0 and c00 > 0 and c11 > 0 and math.isfinite(det)
        if visible:
            conics[i, 0] = c11 / det
            conics[i, 1] = -c01 / det
            conics[i, 2] = c00 / det
        else:
            conics[i, 0] = zero
            conics[i, 1] = zero
            conics[i, 2] = zero
        d0, d1 = max(c00, zero), max(c11, zero)
        cov_diag[i, 0] = d0
        cov_diag[i, 1] = d1
        radius_x = np.ceil(min(extend[i] * math.sqrt(d0), radius_max))  # capped before any integer conversion
        radius_y = np.ceil(min(extend[i] * math.sqrt(d1), radius_max))
        mx = fx * x * rz + cx
        my = fy * y * rz + cy
        visible = (visible and (radius_x > 0 or radius_y > 0) and mx + radius_x > 0 and mx - radius_x < width_f
                   and my + radius_y > 0 and my - radius_y < height_f)
        radii[i, 0], radii[i, 1] = (int(radius_x), int(radius_y)) if visible else (0, 0)
        means2d[i, 0] = mx if visible else zero
        means2d[i, 1] = my if visible else zero
        _tiles_and_box(i, means2d, radii, cov_diag, cutoff, width, height, ts32, tiles_x, tiles_y, boxes, tiles)


@njit(parallel=True, cache=True)
def bin_projected(means2d, radii, cov_diag, cutoff, width, height, tile_size, tiles_x, tiles_y, boxes, tiles):
    """The tile rectangles ``tiles [N, 4]`` and pixel boxes ``boxes [N, 4]`` (written) of Gaussians projected
    elsewhere: ``means2d [N, 2]`` (0 where not rendered), ``radii [N, 2]`` int32, ``cov_diag [N, 2]``, ``cutoff [N]``
    float64 (the differentiable path's :class:`~omg4.render.projection.Projected`)."""
    ts32 = np.float32(tile_size)
    for i in prange(means2d.shape[0]):
        _tiles_and_box(i, means2d, radii, cov_diag, cutoff, width, height, ts32, tiles_x, tiles_y, boxes, tiles)


@njit(cache=True, inline="always")
def _tiles_and_box(i, means2d, radii, cov_diag, cutoff, width, height, ts32, tiles_x, tiles_y, boxes, tiles):
    """Gaussian ``i``'s tile rectangle (first tile x, first tile y, tiles across, tiles down; empty unless both
    radii are positive: gsplat's ``isect_tiles``) and its pixel box ``[x0, x1) × [y0, y1)`` holding every pixel
    whose σ is within its cutoff: the ellipse ``½ dᵀ Σ⁻¹ d ≤ cut`` spans ``|dx| ≤ sqrt(2·cut·Σ_xx)``, widened by
    0.1 % + 0.001 px so that rounding in the conic never puts a passing pixel outside (float64)."""
    rx, ry = radii[i, 0], radii[i, 1]
    tiles[i, 0], tiles[i, 2] = _tile_span(means2d[i, 0], rx, ts32, tiles_x, rx > 0 and ry > 0)
    tiles[i, 1], tiles[i, 3] = _tile_span(means2d[i, 1], ry, ts32, tiles_y, rx > 0 and ry > 0)
    cut = max(cutoff[i], 0.0)
    half_x = math.sqrt(2.0 * cut * np.float64(cov_diag[i, 0])) * (1 + 1e-3) + 1e-3
    half_y = math.sqrt(2.0 * cut * np.float64(cov_diag[i, 1])) * (1 + 1e-3) + 1e-3
    boxes[i, 0], boxes[i, 1] = _pixel_range(np.float64(means2d[i, 0]), half_x, width)
    boxes[i, 2], boxes[i, 3] = _pixel_range(np.float64(means2d[i, 1]), half_y, height)


@njit(cache=True, inline="always")
def _pixel_range(centre, half, limit):
    """``[lo, hi)``: the pixels whose centres (index + 0.5) lie within ``half`` of ``centre``, clamped to
    ``[0, limit]``; the bounds are clamped to ``[−1, limit]`` before rounding, so that a huge box never overflows
    the integers."""
    lo = math.ceil(min(max(centre - half - 0.5, -1.0), float(limit)))
    hi = math.floor(min(max(centre + half - 0.5, -1.0), float(limit))) + 1
    return min(max(lo, 0), limit), min(max(hi, 0), limit)


@njit(cache=True, inline="always")
def _tile_span(m, radius, ts32, limit, both_positive):
    """(first tile, tiles spanned) along one axis: ``floor(m/ts − r/ts) … ceil(m/ts + r/ts) − 1`` clamped to the
    grid, in float32 as gsplat's ``isect_tiles``."""
    mt = np.float32(m) / ts32
    rt = np.float32(radius) / ts32
    lo = min(max(math.floor(mt - rt), 0), limit)
    hi = min(max(math.ceil(mt + rt), 0), limit)
    return lo, (hi - lo) if both_positive else 0


@njit(cache=True)
def _front_to_back(tiles, depth_bits):
    """The Gaussians that touch a tile, ordered by the unsigned bit pattern of their float32 depth (the sort key
    of gsplat's ``isect_tiles``; monotone for positive depths), ties in Gaussian order: a stable LSD radix sort,
    four 8-bit passes."""
    order = np.nonzero((tiles[:, 2] > 0) & (tiles[:, 3] > 0))[0]
    keys = depth_bits[order]
    spare_order, spare_keys = np.empty_like(order), np.empty_like(keys)
    for shift in range(0, 32, 8):
        counts = np.zeros(257, np.int64)
        for k in keys:
            counts[((k >> shift) & 255) + 1] += 1
        starts = np.cumsum(counts)
        for j in range(keys.shape[0]):
            b = (keys[j] >> shift) & 255
            spare_order[starts[b]] = order[j]
            spare_keys[starts[b]] = keys[j]
            starts[b] += 1
        order, spare_order = spare_order, order
        keys, spare_keys = spare_keys, keys
    return order


@njit(cache=True)
def group_by_tile(tiles, views, depth_bits, tiles_x, tiles_per_view, num_tiles):
    """Intersections sorted by tile, then front to back: ``(gaussian_ids [I] int64, tile_offsets [num_tiles + 1]
    int64)`` from the tile rectangles ``tiles [N, 4]`` of :func:`project_forward` or :func:`bin_projected`, each
    row's view ``views [N]``
    and ``depth_bits [N]`` int64, the unsigned bit patterns of the float32 depths."""
    order = _front_to_back(tiles, depth_bits)
    counts = np.zeros(num_tiles + 1, np.int64)
    for i in order:
        base = views[i] * tiles_per_view
        for ty in range(tiles[i, 1], tiles[i, 1] + tiles[i, 3]):
            for tx in range(tiles[i, 0], tiles[i, 0] + tiles[i, 2]):
                counts[base + ty * tiles_x + tx + 1] += 1
    offsets = np.cumsum(counts)
    fill = offsets[:-1].copy()
    ids = np.empty(offsets[-1], np.int64)
    for i in order:
        base = views[i] * tiles_per_view
        for ty in range(tiles[i, 1], tiles[i, 1] + tiles[i, 3]):
            for tx in range(tiles[i, 0], tiles[i, 0] + tiles[i, 2]):
                t = base + ty * tiles_x + tx
                ids[fill[t]] = i
                fill[t] += 1
    return ids, offsets
