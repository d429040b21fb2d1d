"""The CPU rasterizer on numpy arrays: projection and binning, then compositing, each one numba launch.

:func:`omg4.render.api.rasterize_cpu` runs these two steps on the arrays of its tensors; :func:`rasterize_arrays`
runs the whole render on arrays for a render that needs no gradient and has its inputs as arrays already (a
render-only model's frame, :mod:`omg4.gaussians.slice_kernels`), so the frame dispatches no torch operation. The
rules are gsplat 1.5.3's, as :mod:`omg4.render.api` states them.
"""

from __future__ import annotations

import contextlib
from typing import Iterator

import numba
import numpy as np

from omg4.errors import OMG4Error
from omg4.kernels import keeping_torch_threads
from omg4.render.binning import SIGMA_MARGIN, tile_grid
from omg4.render.cpu_kernels import composite_forward
from omg4.render.forward_kernels import CONSTS, group_by_tile, project_forward
from omg4.render.projection import ALPHA_THRESHOLD, BOX_EXTEND, RADIUS_MAX


def project_bin_arrays(means: np.ndarray, covars: np.ndarray, extend: np.ndarray, cutoff: np.ndarray,
                       view_of: np.ndarray, viewmats: np.ndarray, Ks: np.ndarray, width: int, height: int, *,
                       near: float, far: float, eps2d: float, tile_size: int) -> dict[str, np.ndarray]:
    """The EWA projection of ``means [N, 3]``, ``covars [N, 3, 3]`` into views ``view_of [N]`` of ``viewmats [V, 4,
    4]`` and ``Ks [V, 3, 3]`` (one dtype, float32 or float64), each Gaussian's pixel box from its ``extend [N]`` (box
    half-width in σ) and ``cutoff [N]``, and the tile lists front to back: ``means2d, conics, depths, cov2d_diag,
    radii [N, 2], boxes [N, 4], gaussian_ids, tile_offsets``."""
    n, dtype = means.shape[0], means.dtype
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    consts = projection_consts(width, height, near, far, eps2d, dtype)
    out = {"means2d": np.empty((n, 2), dtype), "conics": np.empty((n, 3), dtype), "depths": np.empty(n, dtype),
           "cov2d_diag": np.empty((n, 2), dtype), "radii": np.empty((n, 2), np.int32),
           "boxes": np.empty((n, 4), np.int32)}
    tiles = np.empty((n, 4), np.int64)
    with keeping_torch_threads():
        project_forward(means, covars, extend, cutoff, view_of, viewmats, Ks, consts, width, height, tile_size,
                        tiles_x, tiles_y, out["means2d"], out["conics"], out["depths"], out["cov2d_diag"],
                        out["radii"], out["boxes"], tiles)
    out["gaussian_ids"], out["tile_offsets"] = tile_lists(tiles, out["depths"], view_of, viewmats.shape[0], tiles_x,
                                                          tiles_y)
    return out


def projection_consts(width: int, height: int, near: float, far: float, eps2d: float, dtype) -> np.ndarray:
    """The projection kernels' constants (:data:`omg4.render.forward_kernels.CONSTS`) in ``dtype``."""
    settings = dict(near=near, far=far, eps2d=eps2d, one=1.0, fov_margin=0.3, half_width=0.5 * width,
                    half_height=0.5 * height, width=width, height=height, radius_max=RADIUS_MAX)
    return np.array([settings[name] for name in CONSTS], dtype=dtype)


def tile_lists(tiles: np.ndarray, depths: np.ndarray, view_of: np.ndarray, num_views: int, tiles_x: int,
               tiles_y: int) -> tuple[np.ndarray, np.ndarray]:
    """``(gaussian_ids, tile_offsets)`` of the tile rectangles ``tiles [N, 4]`` of rows in views ``view_of [N]``,
    each tile's list ordered by the float32 ``depths``."""
    depth_bits = depths.astype(np.float32).view(np.uint32).astype(np.int64)
    return group_by_tile(tiles, view_of, depth_bits, tiles_x, tiles_x * tiles_y, tiles_x * tiles_y * num_views)


@contextlib.contextmanager
def kernel_launch() -> Iterator[None]:
    """Run a compositing kernel with tiles handed out one at a time (their costs differ widely)."""
    with keeping_torch_threads(), numba.parallel_chunksize(1):
        yield


def composite_arrays(params: np.ndarray, feats: np.ndarray, boxes: np.ndarray, gaussian_ids: np.ndarray,
                     tile_offsets: np.ndarray, width: int, height: int, tile_size: int, alpha_max: float,
                     num_views: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple]:
    """Front-to-back compositing of ``params [N, 7]`` (means2d, conic, opacity, cutoff) and ``feats [N, D]``:
    ``(Σ f·α·T [V·H, W, D], T_final [V·H, W] float64, last index [V·H, W], the grid arguments)``."""
    dtype = params.dtype
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    grid = (tile_offsets, tiles_x, tiles_x * tiles_y, tile_size, np.arange(width, dtype=dtype) + 0.5,
            np.arange(height, dtype=dtype) + 0.5, np.array([0.5, alpha_max, ALPHA_THRESHOLD], dtype=dtype))
    rows = num_views * height
    out_feat = np.empty((rows, width, feats.shape[1]), dtype=dtype)
    out_t = np.empty((rows, width), dtype=np.float64)
    out_last = np.empty((rows, width), dtype=np.int32)
    with kernel_launch():
        composite_forward(params, feats, boxes, gaussian_ids, *grid, out_feat, out_t, out_last)
    return out_feat, out_t, out_last, grid


def rasterize_arrays(means: np.ndarray, covars: np.ndarray, colors: np.ndarray, opacities: np.ndarray,
                     view_of: np.ndarray, viewmats: np.ndarray, Ks: np.ndarray, width: int, height: int, *,
                     background: np.ndarray | None = None, near: float = 0.2, far: float = 1e10, eps2d: float = 0.3,
                     alpha_max: float = 0.999, tile_size: int = 16) -> dict[str, np.ndarray]:
    """:func:`omg4.render.api.rasterize_views` on numpy arrays of one dtype, without gradients:
    ``image [V, H, W, C]``, ``alpha``, ``depth [V, H, W, 1]``, ``means2d [N, 2]``, ``radii [N]`` int32.
    Settings, the background's shape and non-finite inputs are refused as :func:`~omg4.render.api.rasterize_views`
    refuses them."""
    dtype = means.dtype
    if background is not None and background.shape != (colors.shape[1],):
        raise ValueError(f"background must be [{colors.shape[1]}], got {list(background.shape)}")
    if width < 1 or height < 1 or tile_size < 1 or not 0 < near <= far or not ALPHA_THRESHOLD < alpha_max < 1:
        raise ValueError(f"invalid rasterizer settings: {width}x{height}, tile {tile_size}, near {near}, far {far}, "
                         f"alpha_max {alpha_max}")
    named = {"means": means, "covars": covars, "colors": colors, "opacities": opacities, "viewmat": viewmats,
             "K": Ks, **({"background": background} if background is not None else {})}
    bad = next((name for name, value in named.items() if not np.isfinite(value).all()), None)
    if bad is not None:
        raise OMG4Error(f"rasterize: {bad} contains NaN or infinite values")
    o = np.maximum(opacities.astype(np.float64), 1e-30)
    cutoff = np.log(o / ALPHA_THRESHOLD) + SIGMA_MARGIN
    ratio = np.maximum(opacities, dtype.type(ALPHA_THRESHOLD)) / dtype.type(ALPHA_THRESHOLD)
    extend = np.minimum(np.sqrt(dtype.type(2.0) * np.log(ratio)), dtype.type(BOX_EXTEND))
    num_views = viewmats.shape[0]
    p = project_bin_arrays(means, covars, extend, cutoff, view_of, viewmats.astype(dtype), Ks.astype(dtype), width,
                           height, near=near, far=far, eps2d=eps2d, tile_size=tile_size)
    params = np.concatenate([p["means2d"], p["conics"], opacities[:, None], cutoff.astype(dtype)[:, None]], axis=1)
    feats = np.concatenate([colors, p["depths"][:, None]], axis=1)
    acc, trans, _, _ = composite_arrays(params, feats, p["boxes"], p["gaussian_ids"], p["tile_offsets"], width,
                                        height, tile_size, alpha_max, num_views)
    c = colors.shape[1]
    acc = acc.reshape(num_views, height, width, -1)
    trans = trans.astype(dtype).reshape(num_views, height, width, 1)
    image = acc[..., :c] + (trans * background.astype(dtype) if background is not None else 0.0)
    return {"image": image, "alpha": 1.0 - trans, "depth": acc[..., c:], "means2d": p["means2d"],
            "radii": p["radii"].max(axis=1).astype(np.int32)}


__all__ = ["composite_arrays", "kernel_launch", "project_bin_arrays", "projection_consts", "rasterize_arrays", "tile_lists"]
