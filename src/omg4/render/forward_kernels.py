"""Projection, tile binning and pixel boxes of a render that needs no gradient, as numba kernels.

The differentiable CPU path (:func:`omg4.render.projection.project_gaussians`,
:func:`omg4.render.binning.bin_tiles`, :func:`~omg4.render.binning.pixel_boxes`) is a few dozen torch
operations over all Gaussians; when nothing asks for a gradient (evaluation, videos, the viewer) the
same rules run here (rt4dgs §1.5; docs/paper-map.md "Rasterizer backends"): one parallel pass per
Gaussian (projection, opacity-aware radius, σ cutoff, pixel box, tile rectangle), a radix sort of the
Gaussians by depth and a counting pass that lists each tile's intersections in that order. Projections are
computed in float64 and stored in the input precision; tile ranges and sort keys use the stored float32
values as gsplat's ``isect_tiles`` does, so each tile's list is front to back with ties in Gaussian order,
the order of :func:`~omg4.render.binning.bin_tiles`' stable sort.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from omg4.render.binning import SIGMA_MARGIN
from omg4.render.cpu_kernels import configure_numba_cache
from omg4.render.projection import ALPHA_THRESHOLD, BOX_EXTEND, RADIUS_MAX

configure_numba_cache()


@njit(parallel=True, cache=True)
def project_forward(means, covars, opacities, views, viewmats, Ks, width, height, near, far, eps2d, largest,
                    tile_size, tiles_x, tiles_y, means2d, conics, depths, cov_diag, radii, cutoff, boxes, tiles):
    """Project every Gaussian through its view's camera (the rules of ``project_gaussians`` with opacities)
    and derive its sort depth, σ cutoff, pixel box and tile rectangle.

    Inputs: ``means [N, 3]``, ``covars [N, 3, 3]``, ``opacities [N]``, ``views [N]`` int64, ``viewmats [V, 4, 4]``,
    ``Ks [V, 3, 3]``; ``largest``, the input precision's largest finite value (a Gaussian whose 2D covariance
    exceeds it is culled, as the torch path culls a determinant that overflows). Outputs (written): ``means2d [N, 2]``, ``conics [N, 3]``, ``depths [N]``, ``cov_diag [N, 2]``
    (input precision), ``radii [N, 2]`` int32, ``cutoff [N]`` float64, ``boxes [N, 4]`` int32 and ``tiles [N, 4]``
    int64 (first tile x, first tile y, tiles across, tiles down; zero spans where not rendered).
    """
    n = means.shape[0]
    ts32 = np.float32(tile_size)
    for i in prange(n):
        v = views[i]
        px = float(means[i, 0])
        py = float(means[i, 1])
        pz = float(means[i, 2])
        r = viewmats[v]
        x = r[0, 0] * px + r[0, 1] * py + r[0, 2] * pz + r[0, 3]
        y = r[1, 0] * px + r[1, 1] * py + r[1, 2] * pz + r[1, 3]
        z = r[2, 0] * px + r[2, 1] * py + r[2, 2] * pz + r[2, 3]
        depths[i] = z
        in_range = near <= z <= far
        if not in_range:
            z = 1.0
        k = Ks[v]
        fx, fy, cx, cy = float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])
        tan_fovx = 0.5 * width / fx
        tan_fovy = 0.5 * height / fy
        rz = 1.0 / z
        tx = z * min(max(x * rz, -(cx / fx + 0.3 * tan_fovx)), (width - cx) / fx + 0.3 * tan_fovx)
        ty = z * min(max(y * rz, -(cy / fy + 0.3 * tan_fovy)), (height - cy) / fy + 0.3 * tan_fovy)
        # J R (2 × 3) with J = [[fx/z, 0, −fx·tx/z²], [0, fy/z, −fy·ty/z²]]
        j02 = -fx * tx * rz * rz
        j12 = -fy * ty * rz * rz
        a0 = fx * rz * r[0, 0] + j02 * r[2, 0]
        a1 = fx * rz * r[0, 1] + j02 * r[2, 1]
        a2 = fx * rz * r[0, 2] + j02 * r[2, 2]
        b0 = fy * rz * r[1, 0] + j12 * r[2, 0]
        b1 = fy * rz * r[1, 1] + j12 * r[2, 1]
        b2 = fy * rz * r[1, 2] + j12 * r[2, 2]
        c = covars[i]
        s00, s11, s22 = float(c[0, 0]), float(c[1, 1]), float(c[2, 2])
        s01 = 0.5 * (float(c[0, 1]) + float(c[1, 0]))
        s02 = 0.5 * (float(c[0, 2]) + float(c[2, 0]))
        s12 = 0.5 * (float(c[1, 2]) + float(c[2, 1]))
        sa0 = s00 * a0 + s01 * a1 + s02 * a2
        sa1 = s01 * a0 + s11 * a1 + s12 * a2
        sa2 = s02 * a0 + s12 * a1 + s22 * a2
        sb0 = s00 * b0 + s01 * b1 + s02 * b2
        sb1 = s01 * b0 + s11 * b1 + s12 * b2
        sb2 = s02 * b0 + s12 * b1 + s22 * b2
        c00 = a0 * sa0 + a1 * sa1 + a2 * sa2 + eps2d
        c11 = b0 * sb0 + b1 * sb1 + b2 * sb2 + eps2d
        c01 = a0 * sb0 + a1 * sb1 + a2 * sb2
        det = c00 * c11 - c01 * c01
        # the torch path's determinant is finite in the input precision exactly when these are
        visible = (in_range and det > 0 and c00 > 0 and c11 > 0 and c00 * c11 <= largest and c01 * c01 <= largest
                   and c00 <= largest and c11 <= largest)
        if visible:
            conics[i, 0] = c11 / det
            conics[i, 1] = -c01 / det
            conics[i, 2] = c00 / det
        else:
            conics[i, 0] = 0.0
            conics[i, 1] = 0.0
            conics[i, 2] = 0.0
        d0, d1 = max(c00, 0.0), max(c11, 0.0)
        cov_diag[i, 0] = d0
        cov_diag[i, 1] = d1
        o = float(opacities[i])
        log_ratio = math.log(max(o, 1e-30) / ALPHA_THRESHOLD)  # ln(255·o): 0 at the alpha threshold
        visible = visible and o >= ALPHA_THRESHOLD
        extend = min(BOX_EXTEND, math.sqrt(2.0 * max(log_ratio, 0.0)))
        rx = math.ceil(min(extend * math.sqrt(d0), RADIUS_MAX))
        ry = math.ceil(min(extend * math.sqrt(d1), RADIUS_MAX))
        mx = fx * x * rz + cx
        my = fy * y * rz + cy
        visible = (visible and (rx > 0 or ry > 0) and mx + rx > 0 and mx - rx < width
                   and my + ry > 0 and my - ry < height)
        cut = log_ratio + SIGMA_MARGIN
        cutoff[i] = cut
        if not visible:
            means2d[i, 0] = 0.0
            means2d[i, 1] = 0.0
            radii[i, 0] = 0
            radii[i, 1] = 0
            for q in range(4):
                tiles[i, q] = 0
        else:
            means2d[i, 0] = mx
            means2d[i, 1] = my
            radii[i, 0] = rx
            radii[i, 1] = ry
            tiles[i, 0], tiles[i, 2] = _tile_span(means2d[i, 0], rx, ts32, tiles_x, ry > 0 and rx > 0)
            tiles[i, 1], tiles[i, 3] = _tile_span(means2d[i, 1], ry, ts32, tiles_y, ry > 0 and rx > 0)
        # pixel boxes from the stored precision (binning.pixel_boxes)
        m0, m1 = float(means2d[i, 0]), float(means2d[i, 1])
        half_x = math.sqrt(2.0 * max(cut, 0.0) * float(cov_diag[i, 0])) * (1 + 1e-3) + 1e-3
        half_y = math.sqrt(2.0 * max(cut, 0.0) * float(cov_diag[i, 1])) * (1 + 1e-3) + 1e-3
        boxes[i, 0] = min(max(math.ceil(m0 - half_x - 0.5), 0), width)
        boxes[i, 1] = min(max(math.floor(m0 + half_x - 0.5) + 1, 0), width)
        boxes[i, 2] = min(max(math.ceil(m1 - half_y - 0.5), 0), height)
        boxes[i, 3] = min(max(math.floor(m1 + half_y - 0.5) + 1, 0), height)


@njit(cache=True, inline="always")
def _tile_span(m, radius, ts32, limit, both_positive):
    """(first tile, tiles spanned) along one axis, in float32 as ``binning.tile_ranges``."""
    mt = np.float32(m) / ts32
    rt = np.float32(radius) / ts32
    lo = min(max(math.floor(mt - rt), 0), limit)
    hi = min(max(math.ceil(mt + rt), 0), limit)
    return lo, (hi - lo) if both_positive else 0


@njit(cache=True)
def _front_to_back(tiles, depth_bits):
    """The Gaussians that touch a tile, ordered by the unsigned bit pattern of their float32 depth (the sort key
    of ``bin_tiles``; monotone for positive depths), ties in Gaussian order: a stable LSD radix sort, four 8-bit
    passes."""
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
    int64)`` from the tile rectangles ``tiles [N, 4]`` of :func:`project_forward`, each row's view ``views [N]``
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
