"""The EWA projection's backward pass in numba: ∂L/∂means and ∂L/∂covars from ∂L/∂(means2d, conics, depths).

The forward is :func:`omg4.render.forward_kernels.project_forward` (the values of
:func:`omg4.render.projection.project_gaussians`, gsplat 1.5.3's rules). Per rendered Gaussian, with ``p = R m + t``,
``J = [[fx/z, 0, −fx·tx/z²], [0, fy/z, −fy·ty/z²]]`` (``tx = z·clamp(x/z)``, likewise ``ty``), ``M = J R`` (rows
``a``, ``b``), ``S = ½(Σ + Σᵀ)``, ``C = M S Mᵀ + eps2d·I`` and the conic ``(c11, −c01, c00)/det``, the chain rule
by hand, as autograd takes it through the torch form (its clamp passes the gradient at the bounds too):

    ∂L/∂C from the conic's three entries (only ``C[0, 1]`` of the off-diagonal pair is read)
    ∂L/∂S = Mᵀ G M,  ∂L/∂Σ = ½(∂L/∂S + ∂L/∂Sᵀ),  ∂L/∂M = (G + Gᵀ) M S
    ∂L/∂J from ∂L/∂M Rᵀ, then through ``1/z``, ``tx``, ``ty``, ``means2d = (fx x/z + cx, fy y/z + cy)`` and the depth
    ∂L/∂m = Rᵀ ∂L/∂p

A Gaussian the forward did not render (zero radii) was never composited, so no gradient reaches it (zero here, as
there). Sums run in float64; the results are stored in the inputs' dtype.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from omg4.kernels import configure_numba_cache  # noqa: F401  (numba's cache location, before the kernels)


@njit(parallel=True, cache=True)
def project_backward(means, covars, views, viewmats, Ks, consts, rendered, g_means2d, g_conics, g_depths, g_means,
                     g_covars):
    """Write ``g_means [N, 3]`` and ``g_covars [N, 3, 3]`` (module docstring); ``consts`` are
    :data:`omg4.render.forward_kernels.CONSTS`, ``rendered [N]`` whether the forward gave the Gaussian radii."""
    eps2d, fov_margin = np.float64(consts[2]), np.float64(consts[4])
    half_width, half_height = np.float64(consts[5]), np.float64(consts[6])
    width_f, height_f = np.float64(consts[7]), np.float64(consts[8])
    for i in prange(means.shape[0]):
        for a in range(3):
            g_means[i, a] = 0.0
            for b in range(3):
                g_covars[i, a, b] = 0.0
        if not rendered[i]:
            continue
        v = views[i]
        r = viewmats[v].astype(np.float64)
        k = Ks[v].astype(np.float64)
        m0, m1, m2 = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
        x = m0 * r[0, 0] + m1 * r[0, 1] + m2 * r[0, 2] + r[0, 3]
        y = m0 * r[1, 0] + m1 * r[1, 1] + m2 * r[1, 2] + r[1, 3]
        z = m0 * r[2, 0] + m1 * r[2, 1] + m2 * r[2, 2] + r[2, 3]
        fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
        tan_fovx, tan_fovy = half_width / fx, half_height / fy
        lo_x, hi_x = -(cx / fx + fov_margin * tan_fovx), (width_f - cx) / fx + fov_margin * tan_fovx
        lo_y, hi_y = -(cy / fy + fov_margin * tan_fovy), (height_f - cy) / fy + fov_margin * tan_fovy
        rz = 1.0 / z
        ux, uy = x * rz, y * rz
        free_x, free_y = lo_x <= ux <= hi_x, lo_y <= uy <= hi_y
        tx, ty = z * min(max(ux, lo_x), hi_x), z * min(max(uy, lo_y), hi_y)
        j00, j02, j11, j12 = fx * rz, -fx * tx * rz * rz, fy * rz, -fy * ty * rz * rz
        a = np.empty(3)
        b = np.empty(3)
        for c in range(3):
            a[c] = j00 * r[0, c] + j02 * r[2, c]
            b[c] = j11 * r[1, c] + j12 * r[2, c]
        s = np.empty((3, 3))
        for p in range(3):
            for q in range(3):
                s[p, q] = 0.5 * (np.float64(covars[i, p, q]) + np.float64(covars[i, q, p]))
        pa = np.zeros(3)  # a S
        pb = np.zeros(3)  # b S
        for p in range(3):
            for q in range(3):
                pa[q] += a[p] * s[p, q]
                pb[q] += b[p] * s[p, q]
        c00 = pa[0] * a[0] + pa[1] * a[1] + pa[2] * a[2] + eps2d
        c11 = pb[0] * b[0] + pb[1] * b[1] + pb[2] * b[2] + eps2d
        c01 = pa[0] * b[0] + pa[1] * b[1] + pa[2] * b[2]
        det = c00 * c11 - c01 * c01
        # the conic (c11/det, −c01/det, c00/det) → C
        ga, gb, gc = np.float64(g_conics[i, 0]), np.float64(g_conics[i, 1]), np.float64(g_conics[i, 2])
        inv, inv2 = 1.0 / det, 1.0 / (det * det)
        g00 = -ga * c11 * c11 * inv2 + gb * c01 * c11 * inv2 + gc * (inv - c00 * c11 * inv2)
        g11 = ga * (inv - c11 * c00 * inv2) + gb * c01 * c00 * inv2 - gc * c00 * c00 * inv2
        g01 = 2.0 * ga * c01 * c11 * inv2 - gb * (inv + 2.0 * c01 * c01 * inv2) + 2.0 * gc * c01 * c00 * inv2
        # C = M S Mᵀ with G = [[g00, g01], [0, g11]]
        for p in range(3):
            for q in range(3):
                ds_pq = g00 * a[p] * a[q] + g01 * a[p] * b[q] + g11 * b[p] * b[q]
                ds_qp = g00 * a[q] * a[p] + g01 * a[q] * b[p] + g11 * b[q] * b[p]
                g_covars[i, p, q] = 0.5 * (ds_pq + ds_qp)
        g_j00 = g_j02 = g_j11 = g_j12 = 0.0
        for c in range(3):
            ga_c = 2.0 * g00 * pa[c] + g01 * pb[c]
            gb_c = g01 * pa[c] + 2.0 * g11 * pb[c]
            g_j00 += ga_c * r[0, c]
            g_j02 += ga_c * r[2, c]
            g_j11 += gb_c * r[1, c]
            g_j12 += gb_c * r[2, c]
        g_rz = fx * g_j00 - 2.0 * fx * tx * rz * g_j02 + fy * g_j11 - 2.0 * fy * ty * rz * g_j12
        g_tx, g_ty = -fx * rz * rz * g_j02, -fy * rz * rz * g_j12
        gmx, gmy = np.float64(g_means2d[i, 0]), np.float64(g_means2d[i, 1])
        g_x = gmx * fx * rz
        g_y = gmy * fy * rz
        g_rz += gmx * fx * x + gmy * fy * y
        g_z = g_tx * min(max(ux, lo_x), hi_x) + g_ty * min(max(uy, lo_y), hi_y)
        if free_x:
            g_x += g_tx * z * rz
            g_rz += g_tx * z * x
        if free_y:
            g_y += g_ty * z * rz
            g_rz += g_ty * z * y
        g_z += -g_rz * rz * rz + np.float64(g_depths[i])
        for c in range(3):
            g_means[i, c] = r[0, c] * g_x + r[1, c] * g_y + r[2, c] * g_z


__all__ = ["project_backward"]
