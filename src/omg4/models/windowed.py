"""A render-only 4D model whose frames touch only their time window's Gaussians (the model every loaded file is).

Part of the render-only decoder: it imports no training or compression code.
"""

from __future__ import annotations

import torch

from omg4.errors import CorruptFileError
from omg4.gaussians.covariance import condition_and_cull
from omg4.gaussians.model import GaussianConfig, slice_values
from omg4.gaussians.visibility import DEFAULT_WINDOWS, VisibilityIndex
from omg4.models.frame_arrays import FrameKernel
from omg4.render.view import TimeSlice, ViewSlicer

MAX_CACHED_TERMS = 2**27
"""Largest cached MLP position part (N × hidden floats, 512 MiB); a bigger model encodes its rows per frame."""


class WindowedModel(ViewSlicer):
    """A render-only 4D model whose frames touch only their time window's Gaussians.

    Holds raw per-Gaussian ``values`` (the backbone's parameters, or its geometry plus
    ``f_static``/``f_view`` for a model whose appearance comes from ``appearance`` MLPs,
    paper §4.4), no gradients, and the :class:`VisibilityIndex` built from them at load.
    The time-independent half of every Gaussian's conditioning (its backbone's ``motion``: velocity,
    Σ_3D, Σtt; rt4dgs §1.4; 13 floats per Gaussian, about 100 MB for 2M Gaussians) is computed once
    here too, so a frame only culls its window's candidate rows by their temporal marginals, moves the
    survivors and evaluates the appearance for those (:func:`~omg4.gaussians.covariance.condition_and_cull`,
    :func:`omg4.gaussians.model.slice_values`). For time-conditioned
    MLPs the positions' share of the first layer is computed once here (beyond the paper:
    :meth:`~omg4.gaussians.appearance.AppearanceMLP.position_term`), so a frame encodes only its time.
    On the CPU a frame runs as numba kernels on arrays made here too (``frame_kernel``,
    :class:`~omg4.models.frame_arrays.FrameKernel`; :func:`omg4.render.view.render_view` uses it).
    The index and these caches are built from ``values`` and ``appearance`` at load: they must
    not change afterwards (load the model again instead).
    """

    def __init__(self, values: dict[str, torch.Tensor], config: GaussianConfig, active_sh_degree: int,
                 active_sh_degree_t: int, appearance=None, windows: int = DEFAULT_WINDOWS, meta: dict | None = None):
        self.values = {k: v.detach() for k, v in values.items()}
        self.meta = dict(meta or {})  # the file's metadata: scene, time range, normalization, ...
        self.config = config
        self.active_sh_degree = active_sh_degree
        self.active_sh_degree_t = active_sh_degree_t
        self.appearance = appearance
        v = self.values
        scales = torch.cat([v[a.name] for a in config.schema.attributes if a.activation == "exp"], dim=1).exp()
        # (velocity, Σ_3D, Σtt) of every Gaussian, from the detached values: a frame only culls and moves (§1.4)
        self.motion = config.schema.motion(v, config)
        var_t = self.motion[2]
        if not bool(torch.isfinite(scales).all() & torch.isfinite(var_t).all() & (var_t > 0).all()):
            raise CorruptFileError("the model's scales overflow or its temporal variances are not positive "
                                   "(damaged or diverged values)")
        self.visibility = VisibilityIndex.build(v["t"], var_t, config.time_range, config.time_cull, windows)
        self.position_term = None  # the MLPs' position part, fixed for a model that no longer trains (§4.4)
        if (appearance is not None and config.schema.mlp_time_input
                and self.num_gaussians * appearance.shared[0].weight.shape[0] <= MAX_CACHED_TERMS):
            with torch.no_grad():
                self.position_term = appearance.position_term(v["xyz"])
        # the same frame as one cull and one slice launch on numpy arrays, where the fused kernels serve the model
        # (a subclass that slices otherwise keeps its own slice)
        self.frame_kernel = FrameKernel.build(self) if type(self).slice_views is WindowedModel.slice_views else None

    @property
    def num_gaussians(self) -> int:
        return int(self.values["xyz"].shape[0])

    def slice_views(self, timestamps: torch.Tensor, camera_centers: torch.Tensor) -> TimeSlice:
        """The Gaussians shown to ``V`` views (``timestamps [V]``, ``camera_centers [V, 3]``): the candidates of
        their time windows moved and culled with the terms computed at load, then coloured."""
        xyz = self.values["xyz"]
        times = torch.as_tensor(timestamps, dtype=torch.float64).reshape(-1)
        rows = self.visibility.rows_at(times)  # before the times move to a GPU: no extra synchronization
        with torch.no_grad():
            times = times.to(xyz.device)
            geometry = condition_and_cull(xyz, self.values["t"], *self.motion, times.to(xyz.dtype),
                                          time_cull=self.config.time_cull, rows=rows)
            return slice_values(self.values, self.config, self.active_sh_degree, self.active_sh_degree_t, times,
                                camera_centers, appearance=self.appearance, position_term=self.position_term,
                                geometry=geometry)


__all__ = ["MAX_CACHED_TERMS", "WindowedModel"]
