"""EWA projection of 3D Gaussians through a pinhole camera, differentiable by autograd.

Follows gsplat 1.5.3's CUDA projection (``ProjectionEWA3DGSFused.cu``, ``persp_proj`` in
``Utils.cuh``) so that the CPU and gsplat backends agree (docs/paper-map.md "Rasterizer backends";
rt4dgs §1.5):

* world → camera with the 4×4 OpenCV ``viewmat``; near/far cull on the view depth
  (kept when ``near ≤ z ≤ far``);
* Jacobian of the perspective map with ``x/z`` and ``y/z`` clamped to the field of view
  widened by 30 % (limits computed from ``K`` and the image size);
* ``cov2d = J Σ_c Jᵀ + eps2d·I``, conic = ``cov2d⁻¹`` stored as (inv00, inv01, inv11);
* means in pixels ``(fx·x/z + cx, fy·y/z + cy)``: pixel centres sit at +0.5;
* an axis-aligned box of half-widths ``ceil(extend·sqrt(cov2d_ii))`` (at most :data:`RADIUS_MAX`) with ``extend = 3.33``,
  shrunk by opacity to ``sqrt(2 ln(255·o))`` when opacities are given (gsplat's
  opacity-aware bound); Gaussians with opacity < 1/255, a non-positive determinant or a box
  outside the image get radius 0, and so do those whose 2D covariance overflows the input precision
  (a determinant that is not finite; beyond gsplat, so that every CPU path culls them alike).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from omg4.render.small_matmul import small_matmul

ALPHA_THRESHOLD = 1.0 / 255.0
"""Smallest alpha a Gaussian may add to a pixel (gsplat's ``ALPHA_THRESHOLD``)."""

BOX_EXTEND = 3.33
"""Box half-width in standard deviations when opacity does not shrink it (gsplat)."""

RADIUS_MAX = 2**31 - 128
"""Largest box half-width in pixels (beyond gsplat): the largest float32 below 2³¹, so radii stay int32. A wider
box already spans any image whose centre lies within ~2·10⁹ pixels of the Gaussian's."""


@dataclass
class Projected:
    """Screen-space Gaussians of one camera.

    Attributes:
        means2d: [N, 2] pixel coordinates, zero where not visible (as gsplat); differentiable.
        conics: [N, 3] inverse 2D covariance (inv00, inv01, inv11), zero where out of range or
            degenerate; differentiable.
        depths: [N] view-space z; differentiable.
        cov2d_diag: [N, 2] diagonal of the 2D covariance incl. eps2d (detached).
        radii: [N, 2] int32 box half-widths in pixels, 0 where not visible.
        visible: [N] bool, ``radii > 0``.
    """

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    cov2d_diag: torch.Tensor
    radii: torch.Tensor
    visible: torch.Tensor


def fov_clamp_limits(K: torch.Tensor, width: int, height: int) -> tuple[torch.Tensor, ...]:
    """(lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos): bounds on x/z and y/z used in the Jacobian.

    gsplat ``persp_proj``: ``lim_x_pos = (W − cx)/fx + 0.3·tan_fovx`` with ``tan_fovx = W/(2 fx)``.
    """
    fx, fy, cx, cy = K[..., 0, 0], K[..., 1, 1], K[..., 0, 2], K[..., 1, 2]
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    return (cx / fx + 0.3 * tan_fovx, (width - cx) / fx + 0.3 * tan_fovx,
            cy / fy + 0.3 * tan_fovy, (height - cy) / fy + 0.3 * tan_fovy)


def project_gaussians(means: torch.Tensor, covars: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor,
                      width: int, height: int, *, opacities: torch.Tensor | None = None, near: float = 0.2,
                      far: float = 1e10, eps2d: float = 0.3) -> Projected:
    """Project ``means [N, 3]`` and ``covars [N, 3, 3]`` through ``viewmat [4, 4]`` and ``K [3, 3]``.

    ``viewmat [N, 4, 4]`` and ``K [N, 3, 3]`` give each row its own camera (the rows of several
    views projected in one pass; all views share ``width × height``).

    ``opacities [N]`` (optional) shrinks the boxes as in gsplat's CUDA projection and culls
    Gaussians below 1/255; without it the boxes use 3.33σ as in gsplat's pure-torch
    ``_fully_fused_projection``. Gradients flow to ``means`` and ``covars`` through
    ``means2d``, ``conics`` and ``depths``; culled Gaussians get exactly zero gradient.
    """
    R = viewmat[..., :3, :3]
    t = viewmat[..., :3, 3]
    means_c = means @ R.T + t if viewmat.dim() == 2 else small_matmul(R, means[:, :, None])[..., 0] + t  # [N, 3]
    x, y, z = means_c.unbind(-1)
    in_range = (z >= near) & (z <= far)
    z = torch.where(in_range, z, torch.ones_like(z))  # safe denominator for culled rows

    fx, fy, cx, cy = K[..., 0, 0], K[..., 1, 1], K[..., 0, 2], K[..., 1, 2]
    lim_xn, lim_xp, lim_yn, lim_yp = fov_clamp_limits(K, width, height)
    rz = 1.0 / z
    tx = z * torch.clamp(x * rz, min=-lim_xn, max=lim_xp)
    ty = z * torch.clamp(y * rz, min=-lim_yn, max=lim_yp)
    # J = [[fx/z, 0, −fx·tx/z²], [0, fy/z, −fy·ty/z²]]; cov2d = (J R) S (J R)ᵀ with S the symmetric
    # part of Σ, as three products of tiny per-Gaussian matrices (:mod:`omg4.render.small_matmul`)
    zero = torch.zeros_like(z)
    J = torch.stack([fx * rz, zero, -fx * tx * rz * rz, zero, fy * rz, -fy * ty * rz * rz], dim=-1).reshape(-1, 2, 3)
    JR = small_matmul(J, R)  # [N, 2, 3]
    S = 0.5 * (covars + covars.transpose(-1, -2))
    cov2d = small_matmul(small_matmul(JR, S), JR.transpose(-1, -2))  # [N, 2, 2]
    c00 = cov2d[:, 0, 0] + eps2d
    c11 = cov2d[:, 1, 1] + eps2d
    c01 = cov2d[:, 0, 1]
    det = c00 * c11 - c01 * c01
    visible = in_range & (det > 0) & (c00 > 0) & (c11 > 0) & torch.isfinite(det)
    det = torch.where(visible, det, torch.ones_like(det))
    conics = torch.stack([c11 / det, -c01 / det, c00 / det], dim=-1)
    conics = torch.where(visible[:, None], conics, torch.zeros_like(conics))
    means2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], dim=-1)

    with torch.no_grad():
        cov_diag = torch.stack([c00, c11], dim=-1).clamp(min=0.0)
        extend = torch.full_like(z, BOX_EXTEND)
        if opacities is not None:
            o = opacities.detach().to(z.dtype)
            visible = visible & (o >= ALPHA_THRESHOLD)
            extend = opacity_extend(o)
        # a correctly rounded square root (torch's own may be one ulp off for float32), as the numba path's
        radius = torch.ceil(extend[:, None] * torch.sqrt(cov_diag.double()).to(z.dtype)).clamp(max=RADIUS_MAX)
        visible = visible & (radius > 0).any(dim=-1)
        m = means2d.detach()
        visible = visible & ((m[:, 0] + radius[:, 0] > 0) & (m[:, 0] - radius[:, 0] < width)
                    & (m[:, 1] + radius[:, 1] > 0) & (m[:, 1] - radius[:, 1] < height))
        radii = torch.where(visible[:, None], radius, torch.zeros_like(radius)).to(torch.int32)
    means2d = torch.where(visible[:, None], means2d, torch.zeros_like(means2d))
    return Projected(means2d=means2d, conics=conics, depths=means_c[:, 2], cov2d_diag=cov_diag, radii=radii,
                     visible=visible)


def opacity_extend(opacities: torch.Tensor) -> torch.Tensor:
    """[N] box half-width in standard deviations for ``opacities [N]``: 3.33 shrunk to ``sqrt(2 ln(255·o))``, where
    ``o·e^{−σ}`` falls to 1/255 (gsplat's opacity-aware bound; 0 at or below 1/255), in the opacities' dtype."""
    ratio = opacities.clamp(min=ALPHA_THRESHOLD) / ALPHA_THRESHOLD
    return torch.sqrt(2.0 * torch.log(ratio)).clamp(max=BOX_EXTEND)


def max_radius(radii: torch.Tensor) -> torch.Tensor:
    """Per-Gaussian radius ``[N]`` int32 from box half-widths ``[N, 2]`` (0 = not rendered)."""
    return radii.max(dim=-1).values.to(torch.int32)


