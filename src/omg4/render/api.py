"""The rendering entry points, :func:`rasterize` (one view) and :func:`rasterize_views` (a batch), and the CPU backend.

One differentiable call with two backends that follow
gsplat 1.5.3's rules. The CPU backend runs the EWA projection in torch (:mod:`omg4.render.projection`;
in numba when no input needs a gradient, :func:`project_and_bin`), bins tiles in numba
(:mod:`omg4.render.forward_kernels`) and composites in numba (:mod:`omg4.render.cpu_kernels`) behind a
custom autograd function whose backward gives ∂L/∂means2d (pixels) and ∂L/∂conic; autograd carries them on
to the 3D means and covariances. View depth is composited as one more feature channel
(``depth = Σ z·α·T``, rt4dgs §1.5), so its gradient reaches the means too.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from omg4.errors import OMG4Error
from omg4.kernels import as_numpy, keeping_torch_threads, runs_cpu_kernels
from omg4.render.arrays import composite_arrays, kernel_launch, project_bin_arrays, projection_consts, tile_lists
from omg4.render.rendered import BACKENDS, Rendered
from omg4.render.binning import TileBins, sigma_cutoff, tile_grid
from omg4.render.cpu_kernels import composite_backward
from omg4.render.forward_kernels import bin_projected
from omg4.render.projection_kernels import project_backward
from omg4.render.projection import (ALPHA_THRESHOLD, Projected, max_radius, opacity_extend,
                                    project_gaussians)

def rasterize(means: torch.Tensor, covars: torch.Tensor, colors: torch.Tensor, opacities: torch.Tensor,
              viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int, *,
              background: torch.Tensor | None = None, near: float = 0.2, far: float = 1e10, eps2d: float = 0.3,
              alpha_max: float = 0.999, tile_size: int = 16, backend: str = "auto") -> Rendered:
    """Render 3D Gaussians through a pinhole camera; differentiable w.r.t. every tensor input.

    Args:
        means: [N, 3] world positions.
        covars: [N, 3, 3] symmetric positive definite covariances.
        colors: [N, C] colours or features, C ≥ 1.
        opacities: [N] opacities in [0, 1].
        viewmat: [4, 4] world-to-camera (OpenCV).
        K: [3, 3] intrinsics in pixels.
        width, height: image size in pixels.
        background: [C] colour behind the Gaussians (default black).
        near, far: view-depth range kept (``near ≤ z ≤ far``, near > 0).
        eps2d: added to both diagonal entries of every 2D covariance.
        alpha_max: per-Gaussian alpha cap (gsplat 0.999; the original 3DGS uses 0.99).
        tile_size: tile side in pixels.
        backend: "cpu", "gsplat" (CUDA, alpha_max 0.999 only) or "auto" (gsplat for CUDA
            tensors when it imports, else cpu).

    Raises:
        OMG4Error: an input holds NaN or infinity.
        ValueError: shapes or settings are inconsistent.
    """
    if viewmat.shape != (4, 4) or K.shape != (3, 3):
        raise ValueError(f"viewmat must be [4, 4] and K [3, 3], got {list(viewmat.shape)} and {list(K.shape)}")
    out = rasterize_views(means, covars, colors, opacities, None, viewmat[None], K[None], width, height,
                          background=background, near=near, far=far, eps2d=eps2d, alpha_max=alpha_max,
                          tile_size=tile_size, backend=backend)
    return Rendered(image=out.image[0], alpha=out.alpha[0], depth=out.depth[0], means2d=out.means2d, radii=out.radii)


def rasterize_views(means: torch.Tensor, covars: torch.Tensor, colors: torch.Tensor, opacities: torch.Tensor,
                    views: torch.Tensor | None, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int, *,
                    background: torch.Tensor | None = None, near: float = 0.2, far: float = 1e10, eps2d: float = 0.3,
                    alpha_max: float = 0.999, tile_size: int = 16, backend: str = "auto") -> Rendered:
    """Render ``V`` views of the same size at once; each Gaussian row belongs to one view.

    The CPU backend projects, bins and composites every view's Gaussians in one pass (one
    kernel launch forward, one backward); gsplat renders view by view. Arguments as
    :func:`rasterize`, plus:

    Args:
        views: [N] int64 view of each row (None: every row belongs to view 0 of one view).
        viewmats: [V, 4, 4] world-to-camera matrices; Ks: [V, 3, 3] intrinsics.
    Returns:
        :class:`Rendered` with ``image [V, H, W, C]``, ``alpha``/``depth [V, H, W, 1]``,
        ``means2d [N, 2]`` and ``radii [N]``.
    """
    _check_inputs(means, covars, colors, opacities, views, viewmats, Ks, width, height, background, near, far,
                  alpha_max, tile_size)
    chosen = resolve_backend(backend, means.device)
    kwargs = dict(background=background, near=near, far=far, eps2d=eps2d, alpha_max=alpha_max, tile_size=tile_size)
    if chosen == "gsplat":
        from omg4.render.gsplat_backend import rasterize_gsplat_views  # gsplat needs CUDA: imported where a GPU renders

        return rasterize_gsplat_views(means, covars, colors, opacities, views, viewmats, Ks, width, height, **kwargs)
    return rasterize_cpu(means, covars, colors, opacities, views, viewmats, Ks, width, height, **kwargs)


def resolve_backend(backend: str, device: torch.device) -> str:
    """"cpu" or "gsplat" for ``backend`` on tensors living on ``device``.

    Raises:
        ValueError: an unknown backend name.
        OMG4Error: the cpu backend asked to render CUDA tensors, or CUDA tensors with
            backend "auto" when gsplat does not import (one-line messages).
    """
    if backend not in BACKENDS:
        raise ValueError(f"unknown rasterizer backend {backend!r}; expected one of {', '.join(BACKENDS)}")
    if backend == "cpu" and device.type == "cuda":
        raise OMG4Error(f"the cpu rasterizer backend cannot render tensors on {device}; "
                        "use backend 'auto' or 'gsplat' there, or device 'cpu'")
    if backend != "auto":
        return backend
    if device.type == "cuda":
        try:
            import gsplat  # noqa: F401  (importable: its CUDA kernels build on first use)
        except ImportError:
            raise OMG4Error(f"rendering on {device} needs gsplat, which does not import here "
                            "(pip install gsplat), or use device 'cpu'") from None
        return "gsplat"
    return "cpu"


def _check_inputs(means, covars, colors, opacities, views, viewmats, Ks, width, height, background, near, far,
                  alpha_max, tile_size) -> None:
    n = means.shape[0] if means.dim() == 2 else -1
    if means.dim() != 2 or means.shape[1] != 3:
        raise ValueError(f"means must be [N, 3], got {list(means.shape)}")
    if covars.shape != (n, 3, 3):
        raise ValueError(f"covars must be [{n}, 3, 3], got {list(covars.shape)}")
    if colors.dim() != 2 or colors.shape[0] != n or colors.shape[1] < 1:
        raise ValueError(f"colors must be [{n}, C] with C >= 1, got {list(colors.shape)}")
    if opacities.shape != (n,):
        raise ValueError(f"opacities must be [{n}], got {list(opacities.shape)}")
    v = viewmats.shape[0] if viewmats.dim() == 3 else -1
    if viewmats.shape != (v, 4, 4) or Ks.shape != (v, 3, 3) or v < 1:
        raise ValueError(f"viewmats must be [V, 4, 4] and Ks [V, 3, 3], got {list(viewmats.shape)} and "
                         f"{list(Ks.shape)}")
    if views is None and v != 1:
        raise ValueError(f"{v} views need the view of each Gaussian row")
    if views is not None and (views.shape != (n,) or views.dtype != torch.int64):
        raise ValueError(f"views must be int64 [{n}], got {views.dtype} {list(views.shape)}")
    if background is not None and background.shape != (colors.shape[1],):
        raise ValueError(f"background must be [{colors.shape[1]}], got {list(background.shape)}")
    if width < 1 or height < 1 or tile_size < 1:
        raise ValueError(f"image size {width}x{height} and tile size {tile_size} must be positive")
    if not 0 < near <= far:
        raise ValueError(f"need 0 < near <= far, got near={near}, far={far}")
    if not ALPHA_THRESHOLD < alpha_max < 1:
        raise ValueError(f"alpha_max must lie in (1/255, 1), got {alpha_max}")
    named = {"means": means, "covars": covars, "colors": colors, "opacities": opacities, "viewmat": viewmats, "K": Ks}
    if background is not None:
        named["background"] = background
    # one float64 sum per tensor: NaN or ±inf in a tensor makes its sum non-finite, and float32 values cannot
    # overflow it; a non-finite sum is confirmed element by element (float64 values can overflow the sum)
    with torch.no_grad():
        ok = torch.stack([value.sum(dtype=torch.float64) for value in named.values()]).isfinite()
        if views is not None:
            ok = torch.cat([ok, ((views >= 0) & (views < v)).all()[None]])
    passed = ok.tolist()  # one host synchronization for every check
    bad = next((name for name, fine, value in zip(named, passed, named.values())
                if not fine and not bool(torch.isfinite(value).all())), None)
    if bad is not None:
        raise OMG4Error(f"rasterize: {bad} contains NaN or infinite values")
    if views is not None and not passed[-1]:
        raise ValueError(f"views must lie in [0, {v})")


def rasterize_cpu(means, covars, colors, opacities, views, viewmats, Ks, width, height, *, background=None, near=0.2,
                  far=1e10, eps2d=0.3, alpha_max=0.999, tile_size=16) -> Rendered:
    """CPU backend of :func:`rasterize_views` (same arguments).

    Computes in float64 when ``means`` is float64, else in float32; all tensors must be on the CPU. The projection and
    binning run in numba (:func:`project_and_bin`); when an input needs a gradient, through :class:`_Projection`, whose
    backward is numba too — or, with the reference kernels (:mod:`omg4.kernels`) or a camera that needs a gradient,
    the torch projection then :func:`bin_gaussians`.
    """
    if means.device.type != "cpu":
        raise ValueError(f"the cpu rasterizer backend needs CPU tensors, got {means.device}")
    dtype = torch.float64 if means.dtype == torch.float64 else torch.float32
    means, covars, colors, opacities = (t.to(dtype) for t in (means, covars, colors, opacities))
    num_views = viewmats.shape[0]
    row_views = None if num_views == 1 else views
    grads = torch.is_grad_enabled() and any(t.requires_grad for t in (means, covars, colors, opacities, viewmats, Ks))
    if grads and runs_cpu_kernels(means, covars) and not (viewmats.requires_grad or Ks.requires_grad):
        side: dict = {}  # the projection's results that carry no gradient
        settings = (width, height, near, far, eps2d, tile_size)
        means2d, conics, depths = _Projection.apply(means, covars, opacities, row_views, viewmats, Ks, settings, side)
        proj, bins, cutoff, boxes = side["projected"], side["bins"], side["cutoff"], side["boxes"]
        proj = Projected(means2d=means2d, conics=conics, depths=depths, cov2d_diag=proj.cov2d_diag, radii=proj.radii,
                         visible=proj.visible)
        if means2d.requires_grad:
            means2d.retain_grad()
    elif grads:
        viewmat, K = (viewmats[0], Ks[0]) if num_views == 1 else (viewmats[views], Ks[views])
        proj = project_gaussians(means, covars, viewmat.to(dtype), K.to(dtype), width, height,
                                 opacities=opacities, near=near, far=far, eps2d=eps2d)
        if proj.means2d.requires_grad:
            proj.means2d.retain_grad()
        cutoff = sigma_cutoff(opacities)
        bins, boxes = bin_gaussians(proj, cutoff, row_views, num_views, width, height, tile_size)
    else:
        proj, bins, cutoff, boxes = project_and_bin(means, covars, opacities, row_views, viewmats, Ks, width, height,
                                                    near=near, far=far, eps2d=eps2d, tile_size=tile_size)
    means2d = proj.means2d
    n_colors = colors.shape[1]
    feats = torch.cat([colors, proj.depths[:, None]], dim=1)
    acc, trans = _Composite.apply(means2d, proj.conics, feats, opacities, cutoff.to(dtype), boxes, bins,
                                  (width, height, alpha_max, num_views))
    acc = acc.reshape(num_views, height, width, -1)
    trans = trans.reshape(num_views, height, width, 1)
    bg = torch.zeros(n_colors, dtype=dtype, device=means.device) if background is None else background.to(dtype)
    image = acc[..., :n_colors] + trans * bg
    return Rendered(image=image, alpha=1.0 - trans, depth=acc[..., n_colors:], means2d=means2d,
                    radii=max_radius(proj.radii))


def project_and_bin(means: torch.Tensor, covars: torch.Tensor, opacities: torch.Tensor, views: torch.Tensor | None,
                    viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int, *, near: float, far: float,
                    eps2d: float, tile_size: int) -> tuple[Projected, TileBins, torch.Tensor, torch.Tensor]:
    """``(projected, bins, σ cutoff [N] float64, pixel boxes [N, 4] int32)`` for a render that needs no gradient:
    what ``project_gaussians`` (with opacities), ``sigma_cutoff`` and :func:`bin_gaussians` give, with the projection
    from the numba kernel :func:`omg4.render.forward_kernels.project_forward`. ``means``, ``covars`` and
    ``opacities`` are float32 or float64 CPU tensors of one dtype; ``views`` as :func:`rasterize_views` (None: one
    view)."""
    dtype = means.dtype
    cutoff = sigma_cutoff(opacities)
    view_of = _row_views(views, means.shape[0])
    p = project_bin_arrays(as_numpy(means), as_numpy(covars), as_numpy(opacity_extend(opacities)), as_numpy(cutoff),
                           view_of, as_numpy(viewmats.to(dtype)), as_numpy(Ks.to(dtype)), width, height, near=near,
                           far=far, eps2d=eps2d, tile_size=tile_size)
    radii_t = torch.from_numpy(p["radii"])
    projected = Projected(means2d=torch.from_numpy(p["means2d"]), conics=torch.from_numpy(p["conics"]),
                          depths=torch.from_numpy(p["depths"]), cov2d_diag=torch.from_numpy(p["cov2d_diag"]),
                          radii=radii_t, visible=(radii_t > 0).any(dim=-1))
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    bins = TileBins(gaussian_ids=torch.from_numpy(p["gaussian_ids"]), tile_offsets=torch.from_numpy(p["tile_offsets"]),
                    tiles_x=tiles_x, tiles_y=tiles_y, tile_size=tile_size)
    return projected, bins, cutoff, torch.from_numpy(p["boxes"])


def bin_gaussians(projected: Projected, cutoff: torch.Tensor, views: torch.Tensor | None, num_views: int, width: int,
                  height: int, tile_size: int = 16) -> tuple[TileBins, torch.Tensor]:
    """Intersect projected Gaussians with the tile grid, each tile's list front to back, and give each its pixel box:
    ``(bins, boxes [N, 4] int32)`` (numba kernels of :mod:`omg4.render.forward_kernels`; gsplat 1.5.3's
    ``isect_tiles``/``isect_offset_encode`` rules).

    A Gaussian with box half-widths ``(rx, ry)`` around ``(mx, my)`` covers tiles ``floor(m/ts − r/ts) …
    ceil(m/ts + r/ts) − 1`` (clamped to the grid, none unless both are positive); intersections are sorted by
    tile, then by the float32 bit pattern of the depth (front to back), ties in Gaussian order. With ``views [N]``
    (each row's view) the rows of ``num_views`` views are binned at once, view ``v``'s tiles numbered after those
    of views ``0 … v − 1``. The box ``[x0, x1) × [y0, y1)`` holds every pixel whose σ is within ``cutoff [N]``
    (:func:`~omg4.render.binning.sigma_cutoff`), so the compositing kernels visit only pixels where the Gaussian
    can pass gsplat's ``alpha ≥ 1/255`` test.
    """
    n = projected.radii.shape[0]
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    boxes, tiles = np.empty((n, 4), np.int32), np.empty((n, 4), np.int64)
    with keeping_torch_threads():
        bin_projected(as_numpy(projected.means2d), as_numpy(projected.radii), as_numpy(projected.cov2d_diag),
                      as_numpy(cutoff), width, height, tile_size, tiles_x, tiles_y, boxes, tiles)
    ids, offsets = tile_lists(tiles, as_numpy(projected.depths), _row_views(views, n), num_views, tiles_x, tiles_y)
    bins = TileBins(gaussian_ids=torch.from_numpy(ids), tile_offsets=torch.from_numpy(offsets), tiles_x=tiles_x,
                    tiles_y=tiles_y, tile_size=tile_size)
    return bins, torch.from_numpy(boxes)


def _row_views(views: torch.Tensor | None, n: int) -> np.ndarray:
    """Each row's view as int64 numpy (all 0 for one view)."""
    return np.zeros(n, np.int64) if views is None else as_numpy(views).astype(np.int64, copy=False)


class _Projection(torch.autograd.Function):
    """(means [N, 3], covars [N, 3, 3]) → (means2d [N, 2], conics [N, 3], depths [N]) by the numba projection
    (:func:`project_and_bin`, which also leaves the boxes, tile lists and σ cutoffs in ``side``) and its numba
    backward (:func:`omg4.render.projection_kernels.project_backward`): the torch projection's values and gradients,
    without its hundred-odd operations each way."""

    @staticmethod
    def forward(ctx, means, covars, opacities, views, viewmats, Ks, settings, side):
        width, height, near, far, eps2d, tile_size = settings
        proj, bins, cutoff, boxes = project_and_bin(means.detach(), covars.detach(), opacities.detach(), views,
                                                    viewmats, Ks, width, height, near=near, far=far, eps2d=eps2d,
                                                    tile_size=tile_size)
        side.update(projected=proj, bins=bins, cutoff=cutoff, boxes=boxes)
        dtype = means.dtype
        ctx.save_for_backward(means, covars)  # autograd's version check guards them until the backward
        ctx.arrays = (_row_views(views, means.shape[0]), as_numpy(viewmats.detach().to(dtype)),
                      as_numpy(Ks.detach().to(dtype)), projection_consts(width, height, near, far, eps2d,
                                                                          as_numpy(means).dtype),
                      as_numpy(proj.visible))
        return proj.means2d, proj.conics, proj.depths

    @staticmethod
    @once_differentiable
    def backward(ctx, g_means2d, g_conics, g_depths):
        means, covars = (as_numpy(t) for t in ctx.saved_tensors)
        g_means, g_covars = np.empty_like(means), np.empty_like(covars)
        n, dtype = len(means), means.dtype
        grads = [np.zeros(shape, dtype) if g is None else as_numpy(g)
                 for g, shape in ((g_means2d, (n, 2)), (g_conics, (n, 3)), (g_depths, (n,)))]
        with keeping_torch_threads():
            project_backward(means, covars, *ctx.arrays, *grads, g_means, g_covars)
        return torch.from_numpy(g_means), torch.from_numpy(g_covars), None, None, None, None, None, None


class _Composite(torch.autograd.Function):
    """(means2d [N,2], conics [N,3], feats [N,D], opacities [N]) → (Σ f·α·T [V·H,W,D], T_final [V·H,W,1])."""

    @staticmethod
    def forward(ctx, means2d, conics, feats, opacities, cutoff, boxes, bins: TileBins, settings):
        width, height, alpha_max, num_views = settings
        params = torch.cat([means2d, conics, opacities[:, None], cutoff[:, None]], dim=1)
        gauss = (as_numpy(params), as_numpy(feats), as_numpy(boxes), as_numpy(bins.gaussian_ids))
        out_feat, out_t, out_last, grid = composite_arrays(*gauss, as_numpy(bins.tile_offsets), width, height,
                                                           bins.tile_size, alpha_max, num_views)
        ctx.gauss, ctx.grid, ctx.out_t, ctx.out_last = gauss, grid, out_t, out_last
        ctx.ids = bins.gaussian_ids
        return torch.from_numpy(out_feat), torch.from_numpy(out_t).to(feats.dtype)[..., None]

    @staticmethod
    def backward(ctx, grad_feat, grad_t):
        params, feats = ctx.gauss[0], ctx.gauss[1]
        n_isect = ctx.ids.shape[0]
        g_params = np.zeros((n_isect, 6), dtype=params.dtype)
        g_feats = np.zeros((n_isect, feats.shape[1]), dtype=feats.dtype)
        with kernel_launch():
            composite_backward(*ctx.gauss, *ctx.grid, ctx.out_t, ctx.out_last, as_numpy(grad_feat),
                               as_numpy(grad_t[..., 0]), g_params, g_feats)
        n, dtype = params.shape[0], grad_feat.dtype
        per_gauss = torch.zeros(n, 6, dtype=dtype).index_add_(0, ctx.ids, torch.from_numpy(g_params))
        per_feat = torch.zeros(n, feats.shape[1], dtype=dtype).index_add_(0, ctx.ids, torch.from_numpy(g_feats))
        return per_gauss[:, 0:2], per_gauss[:, 2:5], per_feat, per_gauss[:, 5], None, None, None, None
