"""Test support: a dense pure-torch reference rasterizer and random test scenes.

The reference applies gsplat 1.5.3's rules (docs/paper-map.md "Rasterizer backends")
with no tiles, boxes or kernels: every pixel sees every Gaussian, sorted by depth;
``α = min(α_max, o·e^{−σ})`` is dropped where ``σ < 0`` or ``α < 1/255``; everything from the
first Gaussian whose inclusive transmittance is ≤ 1e-4 on is masked; compositing uses an
exclusive cumulative product. The projection is written independently of
``omg4.render.projection`` (2×2 inverse by ``torch.linalg.inv``, clamped Jacobian in the
form ``−f·clamp(x/z)/z``). Memory grows as H·W·N: small sizes only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch


@dataclass
class DenseResult:
    image: torch.Tensor  # [H, W, C]
    alpha: torch.Tensor  # [H, W, 1]
    depth: torch.Tensor  # [H, W, 1]
    means2d: torch.Tensor  # [N, 2], retains grad when differentiable
    n_terminated: int  # pixels where early termination dropped at least one Gaussian


def dense_rasterize(means, covars, colors, opacities, viewmat, K, width, height, *, background=None, near=0.2,
                    far=1e10, eps2d=0.3, alpha_max=0.999) -> DenseResult:
    """Reference render with the arguments of :func:`omg4.render.rasterize`."""
    dtype = means.dtype
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    p = torch.einsum("ij,nj->ni", R, means) + t
    z = p[:, 2]
    ok = (z >= near) & (z <= far) & (opacities >= 1.0 / 255.0)
    zs = torch.where(ok, z, torch.ones_like(z))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = fx * p[:, 0] / zs + cx
    v = fy * p[:, 1] / zs + cy
    means2d = torch.where(ok[:, None], torch.stack([u, v], -1), torch.zeros(1, dtype=dtype))
    if means2d.requires_grad:
        means2d.retain_grad()
    tanx, tany = width / (2 * fx), height / (2 * fy)
    xz = torch.clamp(p[:, 0] / zs, -(cx / fx + 0.3 * tanx), (width - cx) / fx + 0.3 * tanx)
    yz = torch.clamp(p[:, 1] / zs, -(cy / fy + 0.3 * tany), (height - cy) / fy + 0.3 * tany)
    J = torch.zeros(len(z), 2, 3, dtype=dtype)
    J[:, 0, 0] = fx / zs
    J[:, 0, 2] = -fx * xz / zs
    J[:, 1, 1] = fy / zs
    J[:, 1, 2] = -fy * yz / zs
    cov2d = J @ (R @ covars @ R.T) @ J.transpose(1, 2) + eps2d * torch.eye(2, dtype=dtype)
    det = torch.linalg.det(cov2d)
    ok = ok & (det > 0)
    inv = torch.linalg.inv(torch.where(ok[:, None, None], cov2d, torch.eye(2, dtype=dtype)))

    idx = torch.nonzero(ok).squeeze(1)
    idx = idx[torch.argsort(z[idx].detach(), stable=True)]
    ys, xs = torch.meshgrid(torch.arange(height, dtype=dtype) + 0.5, torch.arange(width, dtype=dtype) + 0.5,
                            indexing="ij")
    d = means2d[idx][None, None] - torch.stack([xs, ys], -1)[:, :, None]  # [H, W, M, 2]
    sigma = 0.5 * torch.einsum("hwmi,mij,hwmj->hwm", d, inv[idx], d)
    alpha = torch.clamp(opacities[idx] * torch.exp(-sigma), max=alpha_max)
    keep = ((sigma >= 0) & (alpha >= 1.0 / 255.0)).detach()
    alpha = alpha * keep
    live = (torch.cumprod(1 - alpha.detach(), dim=-1) > 1e-4)
    n_terminated = int((keep & ~live).any(-1).sum())
    alpha = alpha * live
    one_minus = 1 - alpha
    t_excl = torch.cat([torch.ones_like(one_minus[..., :1]), torch.cumprod(one_minus, -1)[..., :-1]], -1)
    t_final = torch.prod(one_minus, -1)[..., None]  # [H, W, 1]
    w = alpha * t_excl  # [H, W, M]
    feats = torch.cat([colors[idx], z[idx, None]], 1)
    out = torch.einsum("hwm,mc->hwc", w, feats)
    n_col = colors.shape[1]
    bg = torch.zeros(n_col, dtype=dtype) if background is None else background
    return DenseResult(image=out[..., :n_col] + t_final * bg, alpha=1 - t_final, depth=out[..., n_col:],
                       means2d=means2d, n_terminated=n_terminated)


def rotation(axis_angle) -> torch.Tensor:
    """[3, 3] float64 rotation (Rodrigues)."""
    a = torch.as_tensor(axis_angle, dtype=torch.float64)
    theta = a.norm()
    k = a / theta
    Kx = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(theta) * Kx + (1 - math.cos(theta)) * Kx @ Kx


@dataclass
class Scene:
    means: torch.Tensor
    covars: torch.Tensor
    colors: torch.Tensor
    opacities: torch.Tensor
    viewmat: torch.Tensor
    K: torch.Tensor
    width: int
    height: int
    background: torch.Tensor

    def tensors(self, dtype=torch.float64, requires_grad=True) -> dict:
        """Fresh leaf copies of the differentiable inputs (keyword arguments of ``rasterize``)."""
        out = {}
        for name in ("means", "covars", "colors", "opacities", "background"):
            out[name] = getattr(self, name).to(dtype).clone().requires_grad_(requires_grad)
        out.update(viewmat=self.viewmat.to(dtype), K=self.K.to(dtype), width=self.width, height=self.height)
        return out


def random_scene(seed: int, n: int, width: int, height: int, *, channels: int = 3, scale: float = 0.08,
                 opacity=(0.05, 0.95), pixel_grid: int | None = None, pixel_centres: bool = False,
                 depth=(2.0, 5.0)) -> Scene:
    """Random Gaussians in front of a randomly rotated camera (float64).

    Means are drawn in pixel space (10 % beyond the image on each side) and depth; with
    ``pixel_grid`` they sit exactly on multiples of it (tile borders), with ``pixel_centres``
    on pixel centres (σ = 0 there, so alpha = opacity and the alpha cap bites). Covariances are
    arbitrary SPD matrices ``A·Aᵀ + 1e-4·I`` with ``A ~ scale·N(0, 1)``.
    """
    g = torch.Generator().manual_seed(seed)
    f = 1.1 * max(width, height)
    K = torch.tensor([[f, 0, width / 2 + 1.3], [0, f * 1.05, height / 2 - 0.7], [0, 0, 1]], dtype=torch.float64)
    uv = torch.rand(n, 2, generator=g, dtype=torch.float64) * 1.2 - 0.1
    uv = uv * torch.tensor([width, height], dtype=torch.float64)
    if pixel_grid is not None:
        uv = torch.round(uv / pixel_grid) * pixel_grid
    if pixel_centres:
        uv = torch.floor(uv) + 0.5
    zc = depth[0] + (depth[1] - depth[0]) * torch.rand(n, generator=g, dtype=torch.float64)
    pc = torch.stack([(uv[:, 0] - K[0, 2]) / K[0, 0] * zc, (uv[:, 1] - K[1, 2]) / K[1, 1] * zc, zc], -1)
    R = rotation(torch.randn(3, generator=g, dtype=torch.float64))
    t = torch.randn(3, generator=g, dtype=torch.float64)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3], viewmat[:3, 3] = R, t
    means = (pc - t) @ R  # R^T (pc - t)
    A = torch.randn(n, 3, 3, generator=g, dtype=torch.float64) * scale
    covars = A @ A.transpose(1, 2) + 1e-4 * torch.eye(3, dtype=torch.float64)
    colors = torch.rand(n, channels, generator=g, dtype=torch.float64)
    lo, hi = opacity
    opacities = lo + (hi - lo) * torch.rand(n, generator=g, dtype=torch.float64)
    background = torch.rand(channels, generator=g, dtype=torch.float64)
    return Scene(means, covars, colors, opacities, viewmat, K, width, height, background)
