"""Sub-vector quantization (paper §4.4, "Attribute Compression"; omg4 §7).

An attribute ``[N, D]`` is split into ``D / s`` contiguous sub-vectors of length ``s``;
each sub-vector slot gets its own codebook fitted by k-means on all N Gaussians. The
indices are then fixed forever (no reassignment, no straight-through estimator) and only
the codebooks are fine-tuned: the reconstruction ``codebooks[j][indices[:, j]]`` is
differentiable with respect to the codebooks alone.

Codebook sizes, sub-vector lengths, τ_GS and the pruning quantile p per size preset
(L / M / S / T, paper appendix "Additional Implementation Details") live in one table,
:attr:`omg4.gaussians.backbone.Backbone.size_presets` (``size_preset(name, backbone).codebook(attribute)``).
What the paper states: M (the official N3DV config) has b_s = 2^9, b_r = 2^13, b_f = 2^10,
2^9 for the time scale s_t and 2^13 for the additional quaternion q^l (omg4's ``rotation_r``),
with τ_GS = 0.2, p = 0.8 (the sub-vector lengths, 1 for scales and 2 for the others, are OMG's and
the official code's; the paper does not state them); L has τ_GS = 0.4, p = 0.8 and no codebook
sizes of its own (the paper names changes only for S and T), so M's; S and T use b_s = 2^8 (3D rotation and appearance codebooks unchanged, 4D
unchanged) with τ_GS = 0.3, p = 0.9. The paper gives no setting in which S and T differ
(its Table 1 nevertheless lists T with fewer Gaussians than S); the presets module
documents how omg4 separates them.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit
from torch import nn
from torch.autograd.function import once_differentiable

from omg4.codec.payload import QuantizedAttribute
from omg4.compress.kmeans import kmeans
from omg4.kernels import as_numpy, runs_cpu_kernels


class SubVectorQuantizer(nn.Module):
    """Fixed indices ``[N, slots]`` into one learnable codebook ``[K_j, s]`` per sub-vector slot."""

    def __init__(self, codebooks: list[torch.Tensor], indices: torch.Tensor):
        super().__init__()
        if indices.ndim != 2 or indices.shape[1] != len(codebooks):
            raise ValueError(f"indices must be [N, {len(codebooks)}], got {tuple(indices.shape)}")
        self.codebooks = nn.ParameterList([nn.Parameter(cb.detach().clone().float()) for cb in codebooks])
        self.register_buffer("indices", indices.to(torch.int64))
        self.register_buffer("table_rows", None, persistent=False)  # moves with the module
        self._table_rows()

    @classmethod
    def fit(cls, values: torch.Tensor, sub_len: int, codebook_size: int, seed: int = 0,
            iters: int = 100, rate_weight: float = 0.0) -> "SubVectorQuantizer":
        """k-means codebooks for ``values: [N, D]`` split into ``D / sub_len`` slots (omg4 §7).

        A slot's codebook has ``min(codebook_size, #distinct sub-vectors)`` rows — fewer with a rate term
        (``rate_weight`` > 0, beyond the paper: entropy-constrained k-means, :func:`omg4.compress.kmeans.kmeans`).
        k-means runs on the CPU; the quantizer is returned on ``values``' device.
        """
        if values.ndim != 2 or values.shape[1] % sub_len:
            raise ValueError(f"values [N, D] with D divisible by sub_len={sub_len}, got {tuple(values.shape)}")
        x = values.detach().float().cpu()
        with torch.device("cpu"):  # k-means runs on the CPU whatever the default device
            fits = [kmeans(x[:, j * sub_len:(j + 1) * sub_len], codebook_size, iters=iters, seed=seed + j,
                           rate_weight=rate_weight)
                    for j in range(x.shape[1] // sub_len)]
        codebooks, labels = zip(*fits)
        return cls(list(codebooks), torch.stack(labels, dim=1)).to(values.device)

    @classmethod
    def assign(cls, values: torch.Tensor, codebooks: list[torch.Tensor]) -> "SubVectorQuantizer":
        """Quantizer of ``values: [N, D]`` with the given codebooks (a predicted segment's, its reference's): each
        sub-vector takes its nearest codeword (squared distance; ties the first row)."""
        x = values.detach().float()
        labels, start = [], 0
        for cb in codebooks:
            cb = cb.to(x.device, torch.float32)
            part = x[:, start:start + cb.shape[1]]
            labels.append(torch.cat([torch.cdist(chunk, cb).argmin(dim=1) for chunk in part.split(65536)]))
            start += cb.shape[1]
        return cls([cb.float() for cb in codebooks], torch.stack(labels, dim=1)).to(values.device)

    @property
    def num_gaussians(self) -> int:
        return int(self.indices.shape[0])

    def _table_rows(self) -> None:
        """Each index's row in the codebooks stacked along their rows (``table_rows [N · slots]``), where every slot's
        sub-vectors have one length; else None (a decoded file may mix lengths)."""
        widths = {cb.shape[1] for cb in self.codebooks}
        if len(widths) != 1:
            self.table_rows = None
            return
        sizes = np.array([cb.shape[0] for cb in self.codebooks], np.int64)
        offsets = torch.as_tensor(np.cumsum(sizes) - sizes, device=self.indices.device)
        self.table_rows = (self.indices + offsets).reshape(-1)

    def forward(self) -> torch.Tensor:
        """Reconstruction ``[N, D]``: ``cat_j codebooks[j][indices[:, j]]``, as one gather from the stacked codebooks
        where the slots share a sub-vector length. A gather's backward adds into the codebook rows (``index_add``);
        indexing's would sort each slot's indices first (on CUDA a radix sort per slot and step)."""
        if self.table_rows is None:
            return torch.cat([cb.index_select(0, self.indices[:, j]) for j, cb in enumerate(self.codebooks)], dim=1)
        table = torch.cat(list(self.codebooks)) if len(self.codebooks) > 1 else self.codebooks[0]
        return table.index_select(0, self.table_rows).reshape(self.indices.shape[0], -1)

    def values(self) -> torch.Tensor:
        """Same as ``forward()``: the quantized attribute ``[N, D]``."""
        return self()

    def select(self, keep: torch.Tensor) -> None:
        """Keep the Gaussians where ``keep: bool [N]`` (or the rows listed in it); codebooks are untouched."""
        self.indices = self.indices[keep.to(self.indices.device)]
        self._table_rows()

    def to_quantized(self) -> QuantizedAttribute:
        """The payload form: fp16 codebooks ``[K_j, s]`` and int64 indices ``[N]`` per slot."""
        return QuantizedAttribute([cb.detach().cpu().numpy().astype(np.float16) for cb in self.codebooks],
                                  [self.indices[:, j].cpu().numpy().astype(np.int64)
                                   for j in range(len(self.codebooks))])

    @classmethod
    def from_quantized(cls, q: QuantizedAttribute) -> "SubVectorQuantizer":
        """Inverse of :meth:`to_quantized` (codebooks as float32 parameters)."""
        return cls([torch.from_numpy(np.asarray(cb, np.float32)) for cb in q.codebooks],
                   torch.from_numpy(np.stack([np.asarray(ix, np.int64) for ix in q.indices], axis=1)))


@njit(cache=True)
def _gather(codebooks_rows, rows, out):
    """``out[g, j·s:(j+1)·s] = codebooks_rows[rows[g, j]]``: every slot's codeword of every Gaussian."""
    sub = codebooks_rows.shape[1]
    for g in range(rows.shape[0]):
        for j in range(rows.shape[1]):
            r = rows[g, j]
            for c in range(sub):
                out[g, j * sub + c] = codebooks_rows[r, c]


@njit(cache=True)
def _scatter(grad, rows, out):
    """The adjoint of :func:`_gather`: ``out[rows[g, j]] += grad[g, j·s:(j+1)·s]``."""
    sub = out.shape[1]
    for g in range(rows.shape[0]):
        for j in range(rows.shape[1]):
            r = rows[g, j]
            for c in range(sub):
                out[r, c] += grad[g, j * sub + c]


class _QuantizedValues(torch.autograd.Function):
    """Every quantizer's reconstruction ``[N, D]`` at once from its codebooks (the inputs, quantizer after
    quantizer): one numba gather forward, one scatter into the codebooks' rows backward — the CPU form of
    :meth:`SubVectorQuantizer.forward` for all of them, without an operation per codebook."""

    @staticmethod
    def forward(ctx, layout, *codebooks):
        outputs, start = [], 0
        ctx.layout, ctx.books = layout, []
        for rows, count, _ in layout:
            books = [as_numpy(cb) for cb in codebooks[start:start + count]]
            table = books[0] if count == 1 else np.concatenate(books)
            out = np.empty((rows.shape[0], rows.shape[1] * table.shape[1]), table.dtype)
            _gather(table, rows, out)
            outputs.append(torch.from_numpy(out))
            ctx.books.append((table.shape[1], table.dtype))  # the codewords' length and dtype, for the backward
            start += count
        return tuple(outputs)

    @staticmethod
    @once_differentiable
    def backward(ctx, *grads):
        result = []
        for (rows, _, sizes), (sub, dtype), grad in zip(ctx.layout, ctx.books, grads):
            acc = np.zeros((sum(sizes), sub), dtype)
            if grad is not None:
                _scatter(np.ascontiguousarray(grad.numpy()), rows, acc)
            result.extend(torch.from_numpy(part) for part in np.split(acc, np.cumsum(sizes)[:-1]))
        return (None, *(g if needed else None for g, needed in zip(result, ctx.needs_input_grad[1:])))


def quantized_values(quantizers: dict[str, SubVectorQuantizer]) -> dict[str, torch.Tensor]:
    """``{attribute: [N, D] reconstruction}`` of every quantizer, differentiable in the codebooks: one autograd
    function for all of them on the CPU (float32 codebooks of one sub-vector length per quantizer, the fused kernels
    in use), else each quantizer's own :meth:`~SubVectorQuantizer.forward`."""
    books = [cb for q in quantizers.values() for cb in q.codebooks]
    if not books or not runs_cpu_kernels(*books) or any(q.table_rows is None for q in quantizers.values()):
        return {attr: q() for attr, q in quantizers.items()}
    layout = [(q.table_rows.numpy().reshape(q.indices.shape), len(q.codebooks),
               tuple(int(cb.shape[0]) for cb in q.codebooks)) for q in quantizers.values()]
    return dict(zip(quantizers, _QuantizedValues.apply(layout, *books)))
