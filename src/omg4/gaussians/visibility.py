"""Per-time-window visibility index: which Gaussians can pass the temporal cull inside a window.

A 4D Gaussian is shown at time τ only when its temporal marginal
p_t(τ) = exp(−½ (τ − μ_t)² / Σtt) exceeds the cull threshold (rt4dgs §1.4). Over a window
[a, b] the marginal peaks at τ* = clamp(μ_t, a, b), so a Gaussian whose peak there does not
pass can be skipped for every frame in the window (the idea of 4DGS-1K's temporal filter).
Built once when a model is loaded; a frame's temporal cull then looks at its window's rows only,
and the appearance MLP and the move to the frame's time see only the survivors (the time-independent
half of the conditioning is computed once per Gaussian at load, :class:`omg4.models.WindowedModel`). The test is
made against half the cull threshold, so float rounding can never drop a Gaussian the exact cull would keep.

This module is part of the render-only decoder: it imports no training or compression code.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import torch

DEFAULT_WINDOWS = 32
"""Windows over the model's time range (each a candidate list of Gaussian rows)."""


def peak_marginal(t: torch.Tensor, var_t: torch.Tensor, a: float, b: float) -> torch.Tensor:
    """[N] float64: the largest temporal marginal exp(−½ (τ − μ_t)² / Σtt) over τ ∈ [a, b] of Gaussians with time
    centres ``t`` and temporal variances ``var_t`` — at τ* = clamp(μ_t, a, b) (rt4dgs §1.4)."""
    mu = t.detach().double().reshape(-1)
    gap = mu - mu.clamp(a, b)
    return torch.exp(-0.5 * gap * gap / var_t.detach().double().reshape(-1))


def least_marginal(t: torch.Tensor, var_t: torch.Tensor, a: float, b: float) -> torch.Tensor:
    """[N] float64: the smallest temporal marginal over τ ∈ [a, b] — at the end farther from μ_t — of Gaussians with
    time centres ``t`` and temporal variances ``var_t`` (how much each lasts through the range; rt4dgs §1.4)."""
    mu = t.double().reshape(-1)
    farther = torch.maximum((mu - a).abs(), (mu - b).abs())
    return torch.exp(-0.5 * farther * farther / var_t.double().reshape(-1).clamp_min(1e-12))


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

    def windows_at(self, times: list[float]) -> list[int] | None:
        """The windows (sorted) that hold ``times``; None when a time lies outside the range (NaN too)."""
        edges, last = self._edge_list, len(self.rows) - 1
        if not all(edges[0] <= x <= edges[-1] for x in times):
            return None
        return sorted({min(bisect.bisect_right(edges, x) - 1, last) for x in times})

    def rows_at(self, timestamps: torch.Tensor) -> torch.Tensor | None:
        """The candidate rows for all of ``timestamps`` (sorted, unique); None when a time lies outside the range."""
        k = self.windows_at(timestamps.detach().reshape(-1).tolist())
        if k is None:
            return None
        if len(k) == 1:
            return self.rows[k[0]]
        return torch.cat([self.rows[i] for i in k]).unique()


__all__ = ["DEFAULT_WINDOWS", "VisibilityIndex", "least_marginal", "peak_marginal"]
