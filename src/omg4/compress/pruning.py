"""OMG4 Gaussian Pruning (paper §4.2, Eq. 2): keep S ≥ Q_p(S) **or** T ≥ Q_p(T).

The raw scores computed once on the pretrained model are reused, restricted to the
sampled set (omg4 §5); quantiles use linear interpolation.

Beyond the paper, a **frame floor** (``frame_floor`` f > 0, the default 0.02) also keeps the Gaussians that rank among
the ``f·n`` largest static scores of some single frame (:attr:`~omg4.compress.score.SDScores.frame_rank`), and raises
the quantile until the kept count is the paper's rule's again, so the file does not grow. Scores summed over the clip
rank a Gaussian that a few frames need (a fast event, the clip's last frames) below one every frame uses a little;
pruning by them alone opened every dip of the demo's per-frame curve (docs/results.md, "Which stage opens a dip, and
pruning's frame floor").
"""

from __future__ import annotations

import numpy as np
import torch

from omg4.compress.score import SDScores
from omg4.errors import OMG4Error


def check_frame_floor(frame_floor: float) -> None:
    """One-line :class:`OMG4Error` unless the frame floor's share is in [0, 1)."""
    if not 0.0 <= frame_floor < 1.0:
        raise OMG4Error(f"pruning's frame floor must be in [0, 1), got {frame_floor}")


def pruning_mask(scores: SDScores, p: float, frame_floor: float = 0.0) -> torch.Tensor:
    """Bool [N]: Gaussians with S ≥ Q_p(S) or T ≥ Q_p(T) (Eq. 2); with ``frame_floor`` f > 0 also those of frame rank
    < f·N, at the lowest quantile p' ≥ p that keeps no more than Eq. 2 at p does (one or two fewer where a step of
    p' drops one Gaussian of each score; more only where the floor alone holds more). ``scores.frame_rank`` needed."""
    if not 0.0 <= p <= 1.0:
        raise OMG4Error(f"pruning quantile p must be in [0, 1], got {p}")
    check_frame_floor(frame_floor)
    device = scores.static.device
    if scores.static.numel() == 0:
        return torch.zeros(0, dtype=torch.bool, device=device)
    S, T = scores.static.double().cpu().numpy(), scores.dynamic.double().cpu().numpy()

    def eq2(q: float) -> np.ndarray:
        return (S >= np.quantile(S, q)) | (T >= np.quantile(T, q))  # linear interpolation, any size

    keep = eq2(p)
    if frame_floor > 0.0:
        if scores.frame_rank is None:
            raise OMG4Error("pruning's frame floor needs the scores' frame ranks (computed by this version's SD score)")
        floor = (scores.frame_rank < round(frame_floor * len(S))).cpu().numpy()
        if (floor & ~keep).any():  # what Eq. 2 does not keep already
            target = int(keep.sum())
            lo, hi = p, 1.0  # bisect the quantile: the union's count falls as it rises
            for _ in range(BISECTIONS):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if int((eq2(mid) | floor).sum()) > target else (lo, mid)
            keep = eq2(hi) | floor
    return torch.from_numpy(keep).to(device)


BISECTIONS = 30
"""Halvings of the quantile's interval in the frame floor's search (to 1e-9 of the range)."""
