"""OMG4 Gaussian Pruning (paper §4.2, Eq. 2): keep S ≥ Q_p(S) **or** T ≥ Q_p(T).

The raw scores computed once on the pretrained model are reused, restricted to the
sampled set (omg4 §5); quantiles use linear interpolation.
"""

from __future__ import annotations

import numpy as np
import torch

from omg4.compress.score import SDScores
from omg4.errors import OMG4Error


def quantile(x: torch.Tensor, q: float) -> float:
    """The q-quantile of ``x`` (linear interpolation; any size, unlike ``torch.quantile``)."""
    return float(np.quantile(x.double().cpu().numpy(), q))


def pruning_mask(scores: SDScores, p: float) -> torch.Tensor:
    """Bool [N]: Gaussians with S ≥ Q_p(S) or T ≥ Q_p(T)."""
    if not 0.0 <= p <= 1.0:
        raise OMG4Error(f"pruning quantile p must be in [0, 1], got {p}")
    if scores.static.numel() == 0:
        return torch.zeros(0, dtype=torch.bool, device=scores.static.device)
    return (scores.static >= quantile(scores.static, p)) | (scores.dynamic >= quantile(scores.dynamic, p))
