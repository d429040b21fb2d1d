"""Rendering a model at one camera and time.

Every model kind (the Real-Time4DGS baseline, the models of the OMG4 stages, the decoded
compact model) exposes ``slice_at(timestamp, camera_center) -> TimeSlice`` (and
``slice_views`` for several views in one pass, :func:`render_views`): the 3D
Gaussians it shows at that time (rt4dgs §1.4: conditional mean and covariance,
opacity × temporal marginal, culled where the marginal ≤ 0.05) with view-dependent colours.
:func:`render_view` rasterizes such a slice through :func:`omg4.render.rasterize`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from omg4.data.scene import Camera, View
from omg4.device import to_device
from omg4.errors import OMG4Error
from omg4.kernels import fused_kernels
from omg4.render.api import rasterize, rasterize_views, resolve_backend
from omg4.render.arrays import rasterize_arrays
from omg4.render.rendered import Rendered


@dataclass
class TimeSlice:
    """The 3D Gaussians a 4D model shows at one time, ready to rasterize.

    Attributes:
        means: [M, 3] conditional means.
        covars: [M, 3, 3] conditional covariances.
        colors: [M, C] colours (C = 3 for RGB).
        opacities: [M] opacity × temporal marginal, in (0, 1).
        index: [M] int64 index of each row in the model's full Gaussian set (the
            Gaussians that survived the temporal cull), so per-Gaussian statistics such
            as the SD score can be scattered back.
        num_total: N, the model's Gaussian count.
        views: [M] int64 view of each row when the slice serves several views at once
            (rows grouped by view, in order); None for a single view.
    """

    means: torch.Tensor
    covars: torch.Tensor
    colors: torch.Tensor
    opacities: torch.Tensor
    index: torch.Tensor
    num_total: int
    views: torch.Tensor | None = None


class SlicedModel(Protocol):
    """Anything that can show its 3D Gaussians at a time for a viewer at ``camera_center``."""

    def slice_at(self, timestamp: float, camera_center: torch.Tensor) -> TimeSlice: ...


class ViewSlicer:
    """Base of the models that slice several views in one pass: ``slice_at`` is one view of ``slice_views``."""

    def slice_views(self, timestamps: torch.Tensor, camera_centers: torch.Tensor) -> TimeSlice:
        raise NotImplementedError

    def slice_at(self, timestamp: float, camera_center: torch.Tensor) -> TimeSlice:
        """The 3D Gaussians shown at ``timestamp`` to a viewer at ``camera_center`` [3]."""
        return self.slice_views(torch.tensor([float(timestamp)], dtype=torch.float64, device="cpu"), camera_center)


class BatchSlicedModel(SlicedModel, Protocol):
    """A model that also slices several views in one pass (``timestamps [V]``, ``camera_centers [V, 3]``)."""

    def slice_views(self, timestamps: torch.Tensor, camera_centers: torch.Tensor) -> TimeSlice: ...


def camera_tensors(camera: Camera, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(viewmat [4, 4], K [3, 3], centre [3]) as float32 tensors on ``device``."""
    return tuple(to_device(torch.as_tensor(np.asarray(value), dtype=torch.float32, device="cpu"), device)
                 for value in (camera.viewmat, camera.K, camera.center))


def camera_arrays(cameras: list[Camera], name: str) -> np.ndarray:
    """The cameras' ``name`` (``viewmat``, ``K`` or ``center``) stacked, ``[V, …]`` float32 (as :func:`camera_tensors`
    gives them)."""
    return np.stack([np.asarray(getattr(c, name), dtype=np.float32) for c in cameras])


def render_view(model: SlicedModel, camera: Camera, timestamp: float, *, background: torch.Tensor | None = None,
                backend: str = "auto", device: torch.device | str = "cpu", **raster_kwargs):
    """Render ``model`` at ``camera`` and ``timestamp``.

    Returns ``(rendered, time_slice)``: the :class:`omg4.render.Rendered` of the slice and
    the slice itself (its ``index`` maps ``rendered.means2d`` rows to model Gaussians).

    A model made of segments (a long capture, :class:`omg4.models.sequence.SequenceModel`) offers
    ``parts_at(timestamp)``, the models shown at that time with weights summing to 1: each is rendered and the
    images, alphas and depths are blended by the weights (a crossfade across a boundary); the slice returned is
    the heaviest part's.
    """
    if hasattr(model, "parts_at"):
        return _render_blend(model.parts_at(timestamp), camera, timestamp, background=background, backend=backend,
                             device=device, **raster_kwargs)
    if _fused_frame(model, backend, device, background):
        return _render_arrays(model, [camera], [timestamp], background, batch=False, **raster_kwargs)
    viewmat, K, center = camera_tensors(camera, device)
    sl = model.slice_at(timestamp, center)
    rendered = rasterize(sl.means, sl.covars, sl.colors, sl.opacities, viewmat, K, camera.width, camera.height,
                         background=background, backend=backend, **raster_kwargs)
    return rendered, sl


def _render_blend(parts: list, camera: Camera, timestamp: float, **kwargs):
    """The weighted blend of each part's render (see :func:`render_view`)."""
    renders = [(render_view(part, camera, timestamp, **kwargs), weight) for part, weight in parts]
    if len(renders) == 1:
        return renders[0][0]
    (first, first_slice), _ = max(renders, key=lambda r: r[1])
    blended = {name: sum(getattr(rendered, name) * weight for (rendered, _), weight in renders)
               for name in ("image", "alpha", "depth")}
    return dataclasses.replace(first, **blended), first_slice


def render_views(model: BatchSlicedModel, cameras: list[Camera], timestamps: list[float], *,
                 background: torch.Tensor | None = None, backend: str = "auto", device: torch.device | str = "cpu",
                 **raster_kwargs):
    """Render ``model`` at several (camera, time) views of one image size in one pass.

    One time slice serves every view (:meth:`slice_views`) and one rasterizer call renders
    them (:func:`omg4.render.api.rasterize_views`). Returns ``(rendered, time_slice)`` with
    ``rendered.image [V, H, W, C]`` and the slice's ``views`` mapping rows to views.

    Raises:
        ValueError: the cameras differ in image size.
    """
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"render_views needs cameras of one image size, got {sorted(sizes)}")
    if _fused_frame(model, backend, device, background):
        return _render_arrays(model, cameras, timestamps, background, batch=True, **raster_kwargs)
    viewmats, Ks, centers = (to_device(torch.from_numpy(camera_arrays(cameras, name)), device)
                             for name in ("viewmat", "K", "center"))
    times = to_device(torch.from_numpy(np.asarray(timestamps, dtype=np.float64)), device)
    sl = model.slice_views(times, centers)
    width, height = sizes.pop()
    views = sl.views if len(cameras) > 1 else None
    rendered = rasterize_views(sl.means, sl.covars, sl.colors, sl.opacities, views, viewmats, Ks, width, height,
                               background=background, backend=backend, **raster_kwargs)
    return rendered, sl


def _fused_frame(model, backend: str, device, background) -> bool:
    """Whether ``model``'s frames run as the fused CPU kernels on arrays (a render-only model's ``frame_kernel``, the
    cpu rasterizer, the fused kernels in use, :mod:`omg4.kernels`; no gradient asked of the background)."""
    return (getattr(model, "frame_kernel", None) is not None and fused_kernels()
            and not (background is not None and background.requires_grad)
            and resolve_backend(backend, torch.device(device)) == "cpu")


def _render_arrays(model, cameras: list[Camera], timestamps: list[float], background, *, batch: bool,
                   **raster_kwargs):
    """:func:`render_views` (``batch``: images with a leading view axis) or :func:`render_view` of a model with a
    ``frame_kernel``: its slice and the rasterizer on numpy arrays, no torch operation (the results wrap them)."""
    kernel = model.frame_kernel

    def stacked(name: str) -> np.ndarray:
        return camera_arrays(cameras, name).astype(kernel.np_dtype)

    sl = kernel.frame(np.asarray(timestamps, dtype=np.float64), stacked("center"))
    out = rasterize_arrays(sl.means, sl.covars, sl.colors, sl.opacities, sl.views, stacked("viewmat"), stacked("K"),
                           cameras[0].width, cameras[0].height,
                           background=None if background is None else background.detach().cpu().numpy(),
                           **raster_kwargs)
    first = slice(None) if batch else 0
    rendered = Rendered(**{k: torch.from_numpy(out[k][first]) for k in ("image", "alpha", "depth")},
                        means2d=torch.from_numpy(out["means2d"]), radii=torch.from_numpy(out["radii"]))
    time_slice = TimeSlice(means=torch.from_numpy(sl.means), covars=torch.from_numpy(sl.covars),
                           colors=torch.from_numpy(sl.colors), opacities=torch.from_numpy(sl.opacities),
                           index=torch.from_numpy(sl.index), num_total=kernel.xyz.shape[0],
                           views=torch.from_numpy(sl.views))
    return rendered, time_slice


def views_by_size(cameras: list[Camera]) -> list[list[int]]:
    """Positions of ``cameras`` grouped by image size (first-seen order), for :func:`render_views`."""
    groups: dict[tuple[int, int], list[int]] = {}
    for i, c in enumerate(cameras):
        groups.setdefault((c.width, c.height), []).append(i)
    return list(groups.values())


def view_image(view: View, device: torch.device | str = "cpu") -> torch.Tensor:
    """The ground-truth image of ``view`` as float32 [H, W, 3] on ``device``; NaN or Inf is a one-line error."""
    img = view.image()
    if not np.isfinite(img).all():
        raise OMG4Error(f"image of camera {view.camera.name} frame {view.frame_index} contains NaN or Inf")
    return to_device(torch.from_numpy(np.ascontiguousarray(img, dtype=np.float32)), device)


def render_image(model, view: View, background: torch.Tensor | None = None, backend: str = "auto",
                 device: torch.device | str = "cpu") -> torch.Tensor:
    """[H, W, 3] render of ``model`` (living on ``device``) at ``view``, clamped to [0, 1], no gradients."""
    with torch.no_grad():
        rendered, _ = render_view(model, view.camera, view.timestamp, background=background, backend=backend,
                                  device=device)
    return rendered.image.clamp(0.0, 1.0)
