"""OMG4 Gaussian Merging, learnable proxies and baking (paper §4.3 Eq. 5, appendix Alg. 1).

Each disjoint group (built by :mod:`omg4.compress.merge_clusters`) renders as one proxy in the
slot of its representative r (smallest index; omg4 §6a):

    x̄ = Σ_i w_i^x x_i,   f̄_dc = Σ_i w_i^dc f_dc,i,   f̄_rest = Σ_i w_i^rest f_rest,i,   ā = a_r
    w_i = (σ(ℓ_i) + 1e-12) / (Σ_{j ∈ group} (σ(ℓ_j) + 1e-12) + 1e-12),   ℓ initialised to 0

(three logit vectors: position, base colour, other colour terms; Adam lr 0.01). At the end of
the round the proxy values are baked into the representatives and the other members removed.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from omg4.compress.merge_clusters import (MergeConfig, MergeGroups, StarClusters, build_merge_groups,
                                          build_star_clusters, make_disjoint)
from omg4.kernels import as_numpy, runs_cpu_kernels


class _ProxyRows(torch.autograd.Function):
    """One merged attribute's rows with each group's representative replaced by its proxy (Eq. 5), forward and
    backward in numpy on the CPU: the torch form of :meth:`MergeProxy.apply` is about 30 operations per attribute
    and as many again backward, for a few hundred members. (proxy, logits [M], values [N, ...]) → values [N, ...];
    the same arithmetic as the torch form, tested against it in float64."""

    @staticmethod
    def forward(ctx, proxy: "MergeProxy", logits: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        members, group_of, representative = (as_numpy(t) for t in (proxy.members, proxy.group_of,
                                                                   proxy.representative))
        sig = 1.0 / (1.0 + np.exp(-as_numpy(logits)))
        s = sig + np.asarray(1e-12, sig.dtype)
        total = np.bincount(group_of, s, minlength=proxy.num_groups).astype(s.dtype) + s.dtype.type(1e-12)
        w = s / total[group_of]  # the logits' dtype, the values' too (runs_cpu_kernels)
        values = as_numpy(v).reshape(v.shape[0], -1)
        rows = values[members]  # [M, D]
        proxies = np.zeros((proxy.num_groups, values.shape[1]), values.dtype)
        np.add.at(proxies, group_of, w[:, None] * rows)
        out = values.copy()
        out[representative] = proxies
        ctx.saved = (members, group_of, representative, sig, s, total, w, rows, tuple(v.shape))
        return torch.from_numpy(out).reshape(v.shape)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        members, group_of, representative, sig, s, total, w, rows, shape = ctx.saved
        g = as_numpy(grad_out.contiguous()).reshape(shape[0], -1)
        g_rep = g[representative][group_of]  # each member's proxy gradient [M, D]
        grad_v = grad_logits = None
        if ctx.needs_input_grad[2]:
            grad_v = g.copy()
            grad_v[representative] = 0.0
            grad_v[members] += w[:, None] * g_rep  # members are disjoint: each row once
            grad_v = torch.from_numpy(grad_v).reshape(shape)
        if ctx.needs_input_grad[1]:
            g_w = (rows * g_rep).sum(axis=1).astype(s.dtype)  # ∂L/∂w_i
            spread = np.bincount(group_of, g_w * s, minlength=total.shape[0]).astype(s.dtype) / (total * total)
            grad_logits = torch.from_numpy((g_w / total[group_of] - spread[group_of]) * sig * (1.0 - sig))
        return None, grad_logits, grad_v


class MergeProxy(torch.nn.Module):
    """Learnable per-member merge weights of one round (paper §4.3, Alg. 1).

    ``merged`` maps each averaged parameter to its logit vector (the backbone's
    :attr:`~omg4.gaussians.backbone.Backbone.merged`: position, base colour, other colour terms).
    ``apply`` deliberately shadows :meth:`torch.nn.Module.apply` (the API the pipeline calls);
    this module has no submodules, so the generic recursive ``apply(fn)`` is never needed.
    """

    def __init__(self, groups: MergeGroups, num_gaussians: int, merged: dict[str, str]):
        super().__init__()
        self.merged = dict(merged)
        self.num_gaussians = int(num_gaussians)
        self.register_buffer("members", groups.members)
        self.register_buffer("group_of", groups.group_of)
        self.register_buffer("representative", groups.representative)
        keep = torch.ones(self.num_gaussians, dtype=torch.bool, device=groups.members.device)
        keep[groups.members] = False
        keep[groups.representative] = True
        self.kept, self.rendered = keep, torch.nonzero(keep).squeeze(1)  # fixed for the round: made once
        m = groups.members.shape[0]
        dev = groups.members.device
        self.logits = torch.nn.ParameterDict(
            {logit: torch.nn.Parameter(torch.zeros(m, device=dev)) for logit in self.merged.values()})

    @property
    def num_groups(self) -> int:
        return int(self.representative.shape[0])

    def param_groups(self, lr: float) -> list[dict]:
        """Adam parameter groups ``{"params": [logits], "lr": lr, "name": "merge_xyz_logits"}``, ...."""
        return [{"params": [self.logits[name]], "lr": lr, "name": name} for name in self.merged.values()]

    def weights(self, name: str) -> torch.Tensor:
        """Normalized member weights w [M] of logit vector ``name`` (sums to 1 within each group)."""
        s = torch.sigmoid(self.logits[name]) + 1e-12
        total = torch.zeros(self.num_groups, dtype=s.dtype, device=s.device).index_add(0, self.group_of, s)
        return s / (total + 1e-12)[self.group_of]

    def keep_mask(self) -> torch.Tensor:
        """Bool [N]: False for the non-representative members (removed by the merge)."""
        return self.kept

    def apply(self, params: dict[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """Effective parameters with each group as its proxy, and the rows to render.

        params: name → [N, ...]. Returns (values, keep): ``values`` equals ``params`` except that the
        representatives' xyz / features_dc / features_rest are the weighted group means
        (differentiable w.r.t. the logits and all members' values); ``keep`` [K] int64 lists the
        rows to render (all but the non-representative members), ascending.
        """
        rows = params["xyz"].shape[0]
        if rows != self.num_gaussians:
            raise ValueError(f"merge proxy built for {self.num_gaussians} Gaussians, got {rows}")
        values = dict(params)
        for attr, logit in self.merged.items():
            if attr not in params:
                continue
            v = params[attr]
            if runs_cpu_kernels(v, self.logits[logit]):
                values[attr] = _ProxyRows.apply(self, self.logits[logit], v)
                continue
            w = self.weights(logit).to(v.dtype).reshape(-1, *([1] * (v.dim() - 1)))
            proxy = torch.zeros((self.num_groups, *v.shape[1:]), dtype=v.dtype, device=v.device)
            proxy = proxy.index_add(0, self.group_of, w * v[self.members])
            values[attr] = v.index_copy(0, self.representative, proxy)
        return values, self.rendered

    @torch.no_grad()
    def bake(self, params: dict[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """The proxy values written into the representatives (detached), and the bool keep mask [N].

        Rows selected by the mask are exactly the rows ``apply`` renders, with identical values.
        xyz / features_dc / features_rest are new tensors; the other entries are detached views
        of the inputs (unchanged).
        """
        values, _ = self.apply(params)
        return {k: v.detach() for k, v in values.items()}, self.keep_mask()


__all__ = ["MergeConfig", "MergeGroups", "MergeProxy", "StarClusters", "build_merge_groups",
           "build_star_clusters", "make_disjoint"]
