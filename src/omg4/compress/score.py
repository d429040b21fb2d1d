"""The Static–Dynamic score of OMG4 Gaussian Sampling (paper §4.1, Eq. 1).

For every training view j of the pretrained model, with L_j the photometric loss of that
view:

* static score  S_i = Σ_j ‖∂L_j/∂u_ij‖₂, u_ij the projected 2D mean of Gaussian i in view j;
* dynamic score T_i = Σ_j ∂L_j/∂t_i, the **signed** gradient w.r.t. the temporal centre.

The time gradient is zeroed for every view. The official release never zeroes it, so its
stored T is Σ_k Σ_{j≤k} g_j (omg4 §3); ``official_quirk=True`` reproduces that
for parity. A Gaussian culled or off-screen in a view contributes nothing for that view.

Beyond the paper, sampling and pruning rank by *lifetime-weighted* scores by default (:func:`lifetime_weights`;
``score_weighting="paper"`` ranks as the paper does): a sum over the clip's views favours the Gaussians that live
inside it, and the clip's first and last frames are carried by Gaussians it cuts short, which then lose most in
sampling and pruning. Weighted, every frame keeps about the same share of its visible Gaussians. Together with the
deficit draw of the fine-tuning's views (:mod:`omg4.compress.time_balance`) it keeps every frame of basketball
within 0.63 dB of its baseline where the paper's selection and draw lose up to 1.35 dB (docs/results.md, "Every
frame").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from omg4 import distributed
from omg4.atomic import atomic_path
from omg4.data.scene import View
from omg4.errors import CorruptFileError
from omg4.gaussians.covariance import temporal_marginal
from omg4.optimize.step import view_losses


@dataclass
class SDScores:
    """Raw (unnormalized) per-Gaussian scores: ``static`` [N] ≥ 0 and signed ``dynamic`` [N], float64 on the CPU;
    ``frame_rank`` [N] (int64, or None where not computed): the Gaussian's best place, over the clip's frames, in a
    frame's own static score (0: some frame's largest; :data:`UNRANKED` where no frame's score holds it), which the
    frame floor of pruning protects by (:func:`omg4.compress.pruning.pruning_mask`)."""

    static: torch.Tensor
    dynamic: torch.Tensor
    frame_rank: torch.Tensor | None = None

    def select(self, keep: torch.Tensor) -> "SDScores":
        """The scores of the kept Gaussians (bool mask or index)."""
        return SDScores(self.static[keep], self.dynamic[keep],
                        None if self.frame_rank is None else self.frame_rank[keep])

    def weighted(self, weights: torch.Tensor) -> "SDScores":
        """Both scores times per-Gaussian ``weights`` [N] (≥ 0); the frame ranks as they are."""
        w = weights.to(self.static.dtype)
        return SDScores(self.static * w, self.dynamic * w, self.frame_rank)

    def save(self, path: str | Path) -> None:
        """Write the scores as float64 ``.npz`` (the frame ranks as int64), atomically."""
        ranks = {} if self.frame_rank is None else {"frame_rank": self.frame_rank.long().cpu().numpy()}
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, static=self.static.double().cpu().numpy(), dynamic=self.dynamic.double().cpu().numpy(),
                         **ranks)

    @staticmethod
    def load(path: str | Path, num_gaussians: int) -> "SDScores":
        """Read scores saved by :meth:`save` (a file without frame ranks, as older versions wrote, reads with
        ``frame_rank`` None); checks they belong to a model of ``num_gaussians``."""
        try:
            with np.load(path, allow_pickle=False) as z:
                s, d = torch.from_numpy(z["static"]), torch.from_numpy(z["dynamic"])
                r = torch.from_numpy(z["frame_rank"]) if "frame_rank" in z.files else None
        except Exception as e:
            raise CorruptFileError(f"{path}: not a score file ({type(e).__name__})") from None
        if s.shape != (num_gaussians,) or d.shape != (num_gaussians,) or (r is not None and r.shape != s.shape):
            raise CorruptFileError(f"{path}: scores for {s.shape[0]} Gaussians, the model has {num_gaussians}")
        if r is not None and (r.dtype != torch.int64 or bool((r < 0).any())):
            raise CorruptFileError(f"{path}: frame ranks must be non-negative integers")
        return SDScores(s, d, r)


UNRANKED = np.iinfo(np.int64).max
"""The frame rank of a Gaussian no frame's static score holds (it never projects into a training view)."""


def frame_ranks(per_frame: torch.Tensor) -> torch.Tensor:
    """Each Gaussian's best place [N] (int64) over the rows of ``per_frame`` [F, N] (a frame's static scores): 0 for a
    frame's largest, ties by lower index; :data:`UNRANKED` where every row holds 0."""
    n = per_frame.shape[1]
    best = torch.full((n,), UNRANKED, dtype=torch.int64, device="cpu")
    places = torch.arange(n, dtype=torch.int64, device="cpu")
    for row in per_frame.cpu():
        order = torch.sort(-row, stable=True).indices
        place = torch.empty(n, dtype=torch.int64, device="cpu")
        place[order] = places
        best = torch.minimum(best, torch.where(row > 0, place, UNRANKED))
    return best


SCORE_WEIGHTINGS = ("paper", "lifetime")
"""How sampling and pruning weight the SD scores: ``paper`` (as they are) or ``lifetime`` (:func:`lifetime_weights`)."""


def lifetime_weights(model, times: list[float]) -> torch.Tensor:
    """Per-Gaussian weights ``w_i = max(1, L_i / n_i)`` [N] (float64, CPU) of the lifetime-weighted SD score.

    ``n_i`` counts the ``times`` at which Gaussian i passes the temporal cull (p_t > ``time_cull``, rt4dgs §1.4),
    ``L_i`` those it would pass on an unbounded time axis sampled at the clip's mean frame spacing,
    ``2 √(2 ln(1/cull) Σtt) / spacing``. A score summed over the clip's views, times ``L_i / n_i``, is the score of
    the Gaussian's whole life at its mean rate: a Gaussian the clip's ends cut short, or one that outlives the clip,
    is no longer ranked below one the clip holds whole (for those ``w_i`` = 1, as for one it never shows). ``model`` exposes ``params`` and
    ``config`` (its backbone's ``motion`` gives Σtt).
    """
    t = model.params["t"].detach()[:, 0]
    n = t.shape[0]
    if len(times) < 2 or n == 0:
        return torch.ones(n, dtype=torch.float64)
    cull = model.config.time_cull
    with torch.no_grad():
        _, _, var_t = model.config.schema.motion(model.params, model.config)
        var_t = var_t.detach().double()
        t = t.double()
        inside = torch.zeros(n, dtype=torch.float64, device=t.device)
        for tau in times:  # one time at a time: [N] memory whatever the clip's length
            inside += (temporal_marginal(tau - t, var_t) > cull).double()
        spacing = (max(times) - min(times)) / (len(times) - 1)
        lifetime = 2.0 * torch.sqrt(2.0 * math.log(1.0 / cull) * var_t) / spacing
    weights = torch.where(inside > 0, lifetime / inside.clamp_min(1.0), 1.0)  # never shown: nothing to scale
    return weights.clamp_min(1.0).cpu()


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

    The static score is also summed per frame (the views of one timestamp), [F, N] float32 (4·F·N bytes: 14 MB for
    60 frames of 60k Gaussians), and reduced to each Gaussian's best place in a frame (:func:`frame_ranks`).
    """
    world = distributed.world()
    n = model.params["t"].shape[0]
    static = torch.zeros(n, dtype=torch.float64, device=device)
    dynamic = torch.zeros(n, dtype=torch.float64, device=device)
    frame_of = {t: i for i, t in enumerate(sorted({v.timestamp for v in views}))}
    per_frame = torch.zeros(len(frame_of), n, dtype=torch.float32, device=device)
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
            for group, rendered, sl, _, losses, _ in view_losses(model, chunk, background=background,
                                                                 backend=backend, lambda_dssim=lambda_dssim,
                                                                 device=device):
                weights = torch.tensor([float(len(views) - start - i) if official_quirk else 1.0 for i in group],
                                       dtype=torch.float64, device=device)
                (losses * weights.to(losses.dtype)).sum().backward()
                if rendered.means2d.grad is not None:
                    g2d = rendered.means2d.grad.double().norm(dim=-1) / weights.index_select(0, sl.views)
                    static.index_add_(0, sl.index, g2d)
                    frames = torch.tensor([frame_of[chunk[i].timestamp] for i in group], device=device)
                    per_frame.index_put_((frames.index_select(0, sl.views), sl.index), g2d.float(), accumulate=True)
                if t_param.grad is not None:
                    dynamic += t_param.grad.double().squeeze(1)
                t_param.grad = None
            bar.update(len(chunk))
        bar.close()
    finally:
        for k, p in model.params.items():
            p.requires_grad_(saved_flags[k])
    distributed.all_reduce_([static, dynamic, per_frame], "sum", "combining the SD scores")
    return SDScores(static.cpu(), dynamic.cpu(), frame_ranks(per_frame))
