"""The Static–Dynamic score of OMG4 Gaussian Sampling (paper §4.1, Eq. 1).

For every training view j of the pretrained model, with L_j the photometric loss of that
view:

* static score  S_i = Σ_j ‖∂L_j/∂u_ij‖₂, u_ij the projected 2D mean of Gaussian i in view j;
* dynamic score T_i = Σ_j ∂L_j/∂t_i, the **signed** gradient w.r.t. the temporal centre.

The time gradient is zeroed for every view. The official release never zeroes it, so its
stored T is Σ_k Σ_{j≤k} g_j (omg4 §3); ``official_quirk=True`` reproduces that
for parity. A Gaussian culled or off-screen in a view contributes nothing for that view.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from omg4.data.scene import View
from omg4.train.step import view_losses


@dataclass
class SDScores:
    """Raw (unnormalized) per-Gaussian scores: ``static`` [N] ≥ 0 and signed ``dynamic`` [N], float64 on the CPU."""

    static: torch.Tensor
    dynamic: torch.Tensor

    def select(self, keep: torch.Tensor) -> "SDScores":
        """The scores of the kept Gaussians (bool mask or index)."""
        return SDScores(self.static[keep], self.dynamic[keep])

    def save(self, path: str | Path) -> None:
        """Write both scores as float64 ``.npz`` (atomically)."""
        from omg4.atomic import atomic_path

        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, static=self.static.double().cpu().numpy(), dynamic=self.dynamic.double().cpu().numpy())

    @staticmethod
    def load(path: str | Path, num_gaussians: int) -> "SDScores":
        """Read scores saved by :meth:`save`; checks they belong to a model of ``num_gaussians``."""
        from omg4.errors import CorruptFileError

        try:
            with np.load(path, allow_pickle=False) as z:
                s, d = torch.from_numpy(z["static"]), torch.from_numpy(z["dynamic"])
        except Exception as e:
            raise CorruptFileError(f"{path}: not a score file ({type(e).__name__})") from None
        if s.shape != (num_gaussians,) or d.shape != (num_gaussians,):
            raise CorruptFileError(f"{path}: scores for {s.shape[0]} Gaussians, the model has {num_gaussians}")
        return SDScores(s, d)


def compute_sd_scores(model, views: list[View], *, background: torch.Tensor | None = None, backend: str = "auto",
                      lambda_dssim: float = 0.2, official_quirk: bool = False, progress: bool = True,
                      device: torch.device | str = "cpu", batch_size: int = 4) -> SDScores:
    """One pass over ``views`` (in order) accumulating S and T for every Gaussian of ``model``.

    ``model`` exposes ``params`` (with a ``"t"`` tensor [N, 1]) and ``slice_views``; it and
    ``background`` live on ``device``, where the scores are accumulated before moving to the CPU.

    ``batch_size`` views are rendered and back-propagated together: every row of a batched
    slice belongs to one view, so its 2D-mean gradient is that view's ∂L_j/∂u_ij, and the
    time gradient of Σ_j w_j L_j is Σ_j w_j ∂L_j/∂t. With w_j = 1 that is T; the release's
    running sum (``official_quirk``) equals Σ_j (n − j) ∂L_j/∂t over the n views in order,
    so the quirk weights view j by n − j and divides its rows' 2D gradients by the same.

    In a distributed job each rank scores its share of the batches and the sums are combined, so every rank
    holds the scores of all the views.
    """
    from omg4 import distributed

    world = distributed.world()
    n = model.params["t"].shape[0]
    static = torch.zeros(n, dtype=torch.float64, device=device)
    dynamic = torch.zeros(n, dtype=torch.float64, device=device)
    saved_flags = {k: p.requires_grad for k, p in model.params.items()}
    t_param = model.params["t"]
    for p in model.params.values():
        p.requires_grad_(False)
        p.grad = None
    t_param.requires_grad_(True)
    try:
        starts = world.shard(list(range(0, len(views), max(1, batch_size))))
        bar = tqdm(total=sum(len(views[i:i + max(1, batch_size)]) for i in starts), desc="SD score",
                   disable=not (progress and world.main), dynamic_ncols=True)
        for start in starts:
            chunk = views[start:start + max(1, batch_size)]
            for group, rendered, sl, _, losses in view_losses(model, chunk, background=background, backend=backend,
                                                              lambda_dssim=lambda_dssim, device=device):
                weights = torch.tensor([float(len(views) - start - i) if official_quirk else 1.0 for i in group],
                                       dtype=torch.float64, device=device)
                (losses * weights.to(losses.dtype)).sum().backward()
                if rendered.means2d.grad is not None:
                    g2d = rendered.means2d.grad.double().norm(dim=-1) / weights.index_select(0, sl.views)
                    static.index_add_(0, sl.index, g2d)
                if t_param.grad is not None:
                    dynamic += t_param.grad.double().squeeze(1)
                t_param.grad = None
            bar.update(len(chunk))
        bar.close()
    finally:
        for k, p in model.params.items():
            p.requires_grad_(saved_flags[k])
    distributed.all_reduce_([static, dynamic], "sum", "combining the SD scores")
    return SDScores(static.cpu(), dynamic.cpu())
