"""OMG4 Gaussian Sampling (paper §4.1): keep the top τ_GS fraction by SD score.

SD_i = minmax(S)_i · minmax(T)_i, min-max normalized over all Gaussians (T keeps its
sign, so the most negative dynamic score maps to 0; omg4 §4).
"""

from __future__ import annotations

import torch

from omg4.compress.score import SDScores
from omg4.errors import OMG4Error


def minmax(x: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """(x − min) / (max − min + eps) over all entries."""
    return (x - x.min()) / (x.max() - x.min() + eps)


def sd_score(scores: SDScores) -> torch.Tensor:
    """The combined score SD = minmax(S) · minmax(T) [N]."""
    return minmax(scores.static) * minmax(scores.dynamic)


def sampling_mask(scores: SDScores, ratio: float) -> torch.Tensor:
    """Bool [N]: exactly ``round(ratio · N)`` Gaussians with the highest SD score (ties by lower index)."""
    if not 0.0 < ratio <= 1.0:
        raise OMG4Error(f"sampling ratio τ_GS must be in (0, 1], got {ratio}")
    sd = sd_score(scores)
    n = sd.shape[0]
    k = max(1, int(round(ratio * n))) if n else 0
    # stable descending order: ties keep the lower index first
    order = torch.sort(-sd, stable=True).indices[:k]
    keep = torch.zeros(n, dtype=torch.bool, device=sd.device)
    keep[order] = True
    return keep
