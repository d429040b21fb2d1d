"""Per-time-window visibility index: which Gaussians can pass the temporal cull inside a window.

A 4D Gaussian is shown at time τ only when its temporal marginal
p_t(τ) = exp(−½ (τ − μ_t)² / Σtt) exceeds the cull threshold (rt4dgs §1.4). Over a window
[a, b] the marginal peaks at τ* = clamp(μ_t, a, b), so a Gaussian whose peak there does not
pass can be skipped for every frame in the window (the idea of 4DGS-1K's temporal filter).
Built once when a model is loaded; a frame's temporal cull then looks at its window's rows only,
and the appearance MLP and the move to the frame's time see only the survivors (the time-independent
half of the conditioning is computed once per Gaussian at load, :class:`WindowedModel`). The test is
made against half the cull threshold, so float rounding can never drop a Gaussian the exact cull would keep.

This module is part of the render-only decoder: it imports no training or compression code.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import torch

from omg4.errors import CorruptFileError
from omg4.gaussians.covariance import condition_and_cull
from omg4.gaussians.model import GaussianConfig, slice_values
from omg4.render.view import TimeSlice, ViewSlicer

DEFAULT_WINDOWS = 32
"""Windows over the model's time range (each a candidate list of Gaussian rows)."""

MAX_CACHED_TERMS = 2**27
"""Largest cached MLP position part (N × hidden floats, 512 MiB); a bigger model encodes its rows per frame."""


def peak_marginal(t: torch.Tensor, var_t: torch.Tensor, a: float, b: float) -> torch.Tensor:
    """[N] float64: the largest temporal marginal exp(−½ (τ − μ_t)² / Σtt) over τ ∈ [a, b] of Gaussians with time
    centres ``t`` and temporal variances ``var_t`` — at τ* = clamp(μ_t, a, b) (rt4dgs §1.4)."""
    mu = t.detach().double().reshape(-1)
    gap = mu - mu.clamp(a, b)
    return torch.exp(-0.5 * gap * gap / var_t.detach().double().reshape(-1))


@dataclass
class VisibilityIndex:
    """Candidate rows per time window.

    Attributes:
        edges: [K + 1] window boundaries over the time range (float64, CPU).
        rows: K int64 tensors, the rows that may pass the cull somewhere in each window.
    """

    edges: torch.Tensor
    rows: list[torch.Tensor]

    @staticmethod
    def build(t: torch.Tensor, var_t: torch.Tensor, time_range: tuple[float, float], time_cull: float,
              windows: int = DEFAULT_WINDOWS) -> "VisibilityIndex":
        """The index of Gaussians with time centres ``t`` [N] and temporal variances ``var_t`` [N]."""
        edges = torch.linspace(time_range[0], time_range[1], windows + 1, dtype=torch.float64, device="cpu")
        mu, var = t.detach().double().reshape(-1), var_t.detach().double().reshape(-1)  # converted once, not per window
        rows = [(peak_marginal(mu, var, a, b) > 0.5 * time_cull).nonzero().squeeze(1).to(t.device)
                for a, b in zip(edges[:-1].tolist(), edges[1:].tolist())]
        return VisibilityIndex(edges, rows)

    def __post_init__(self):
        self._edge_list = self.edges.tolist()  # a frame looks its windows up in Python: no tensor operations

    def rows_at(self, timestamps: torch.Tensor) -> torch.Tensor | None:
        """The candidate rows for all of ``timestamps`` (sorted, unique); None when a time lies outside the range."""
        times, edges, last = timestamps.detach().reshape(-1).tolist(), self._edge_list, len(self.rows) - 1
        if not all(edges[0] <= x <= edges[-1] for x in times):  # NaN too
            return None
        k = sorted({min(bisect.bisect_right(edges, x) - 1, last) for x in times})
        if len(k) == 1:
            return self.rows[k[0]]
        return torch.cat([self.rows[i] for i in k]).unique()


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


__all__ = ["DEFAULT_WINDOWS", "MAX_CACHED_TERMS", "VisibilityIndex", "WindowedModel"]
