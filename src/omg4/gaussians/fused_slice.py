"""A differentiable time slice of ``V`` views as one autograd function on the CPU (rt4dgs §1.4, §2; paper §4.4).

:func:`omg4.gaussians.model.slice_values` in torch operations is a few hundred operations forward and backward — the
cull, the rows' motion, the appearance MLPs and their frequency encoding, the 4D SH colours — each with its autograd
node; for the compact models of OMG4's later stages (a few thousand Gaussians) that bookkeeping costs more than the
arithmetic. Here the backbone's per-Gaussian motion terms (velocity, Σ_3D, Σtt; ``Backbone.motion``) stay in
torch, and everything per row is one function: the cull and the rows' motion, colour and opacity
(:mod:`omg4.gaussians.slice_kernels`, forward and backward), with the appearance
either stored per Gaussian (opacity logit, SH) or predicted by the MLPs (:mod:`omg4.gaussians.appearance_arrays`,
their products in torch on the arrays' memory). Values and gradients are the torch form's (the reference, tested
against it in float64).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from omg4.gaussians import appearance_arrays
from omg4.gaussians import slice_kernels as sk
from omg4.gaussians.sh import num_sh_coeffs
from omg4.kernels import as_numpy, keeping_torch_threads, runs_cpu_kernels
from omg4.render.view import TimeSlice


@dataclass
class SliceSpec:
    """What a slice computes besides its tensors: the views' times ``[V]`` (float64) and camera centres
    ``[V, 3]``, the model's settings and where its appearance comes from (``mlp``: the networks' frequency count
    and whether they take the time). ``rows`` (int64, ascending) limits the slice to those Gaussians (a merge round's
    rendered rows, paper §4.3); None: every Gaussian."""

    times: np.ndarray
    centers: np.ndarray
    time_range: tuple[float, float]
    time_cull: float
    band: int
    sh_degree: int
    sh_degree_t: int
    conditioned: bool
    mlp: tuple[int, bool] | None = None
    rows: np.ndarray | None = None

    @property
    def period(self) -> float:
        """T = t1 − t0, the SH time period."""
        return float(self.time_range[1] - self.time_range[0])

    @property
    def num_basis(self) -> int:
        """The active spatial basis functions, (degree + 1)²."""
        return num_sh_coeffs(self.sh_degree)


def _host(x) -> np.ndarray:
    """A float64 numpy copy of a tensor (any device) or array-like: the views' times and centres."""
    if torch.is_tensor(x):  # a CPU tensor without a gradient is viewed without an operation
        return x.numpy(force=x.requires_grad or x.device.type != "cpu").astype(np.float64)
    return np.asarray(x).astype(np.float64)


def _array(t: torch.Tensor, shape=None) -> np.ndarray:
    """The numpy view of a CPU tensor (:func:`omg4.kernels.as_numpy`), reshaped to ``shape`` if given."""
    a = as_numpy(t)
    return a if shape is None else a.reshape(shape)


class _SliceRows(torch.autograd.Function):
    """(xyz [N, 3], t [N, 1], gain [N, 3], Σ_3D [N, 3, 3], Σtt [N], appearance...) → (means [M, 3], covars [M, 3, 3],
    colors [M, 3], opacities [M]); the rows' ``index`` and ``views`` go to ``side``. The appearance is
    ``(opacity [N, 1], features_dc [N, 1, 3], features_rest [N, K − 1, 3])`` or ``(f_static [N, 3], f_view [N, 3],
    the MLPs' eight weights)``."""

    @staticmethod
    def forward(ctx, spec: SliceSpec, side: dict, xyz, t, gain, cov3, var_t, *appearance):
        n = xyz.shape[0]
        dtype = xyz.dtype
        a_xyz, a_t, a_gain, a_cov3, a_var = (_array(xyz), _array(t, (n,)), _array(gain), _array(cov3),
                                             _array(var_t, (n,)))
        np_dtype = a_xyz.dtype
        times = spec.times.astype(np_dtype)
        centers = spec.centers.astype(np_dtype)
        consts = sk.kernel_consts(spec.time_cull, np_dtype)
        rows = np.arange(n, dtype=np.int64) if spec.rows is None else spec.rows
        keep = np.empty((len(times), rows.shape[0]), dtype=np.bool_)
        with keeping_torch_threads():
            sk.cull(rows, a_t, a_var, times, consts, keep)
            views, index = np.nonzero(keep)
            if spec.rows is not None:
                index = rows[index]
            m = index.shape[0]
            means, covars = np.empty((m, 3), np_dtype), np.empty((m, 3, 3), np_dtype)
            colors, opacities, marginals = np.empty((m, 3), np_dtype), np.empty(m, np_dtype), np.empty(m, np_dtype)
            sk.move_rows(index, views, times, a_xyz, a_t, a_gain, a_cov3, a_var, consts, means, covars, marginals)
            saved_mlp = None
            if spec.mlp is None:
                logits = _array(appearance[0], (n,))
                dc, rest = _array(appearance[1], (n, 3)), _array(appearance[2])
            else:
                num_freqs, time_input = spec.mlp
                joined = appearance_arrays.joined_weights([_array(w) for w in appearance[2:]], 3 * 2 * num_freqs)
                dc, rest, logits, saved_mlp = appearance_arrays.forward(
                    joined, num_freqs, time_input, a_xyz, _array(appearance[0]), _array(appearance[1]), index,
                    views, (spec.times - spec.time_range[0]) / spec.period if time_input else None,
                    None if time_input else means)
            sk.color_rows(index, views, times, centers, a_xyz, a_t, means, marginals, spec.mlp is None, logits, dc,
                          rest, spec.num_basis, spec.band, spec.sh_degree_t + 1, spec.period, spec.conditioned, colors,
                          opacities)
        ctx.spec, ctx.dtype = spec, dtype
        ctx.arrays = (a_xyz, a_t, a_gain, a_var, index, views, times, centers, means, marginals, logits, dc, rest,
                      colors, saved_mlp)
        ctx.shapes = [tuple(a.shape) for a in appearance]
        side.update(index=torch.from_numpy(index), views=torch.from_numpy(views))
        return tuple(torch.from_numpy(a) for a in (means, covars, colors, opacities))

    @staticmethod
    @once_differentiable
    def backward(ctx, g_means, g_covars, g_colors, g_opacities):
        spec = ctx.spec
        (a_xyz, a_t, a_gain, a_var, index, views, times, centers, means, marginals, logits, dc, rest, colors,
         saved_mlp) = ctx.arrays
        n, m, dtype = a_xyz.shape[0], index.shape[0], a_xyz.dtype
        starts = appearance_arrays.view_ranges(views, len(times))

        def grad_array(g, shape):
            return np.zeros(shape, dtype) if g is None else _array(g.to(ctx.dtype))

        g_xyz, g_t, g_gain = np.zeros((n, 3), dtype), np.zeros(n, dtype), np.zeros((n, 3), dtype)
        g_cov3, g_var = np.zeros((n, 3, 3), dtype), np.zeros(n, dtype)
        by_gaussian = spec.mlp is None
        rows = n if by_gaussian else m
        g_logits, g_dc = np.zeros(rows, dtype), np.zeros((rows, 3), dtype)
        g_rest = np.zeros((rows,) + rest.shape[1:], dtype)
        with keeping_torch_threads():
            sk.slice_rows_backward(index, views, starts, times, centers, a_xyz, a_t, a_gain, a_var, means, marginals,
                                   by_gaussian, logits, dc, rest, colors, spec.num_basis, spec.band,
                                   spec.sh_degree_t + 1, spec.period, spec.conditioned, grad_array(g_means, (m, 3)),
                                   grad_array(g_covars, (m, 3, 3)), grad_array(g_colors, (m, 3)),
                                   grad_array(g_opacities, (m,)), g_xyz, g_t, g_gain, g_cov3, g_var, g_logits, g_dc,
                                   g_rest)
            if by_gaussian:
                appearance_grads = [g_logits.reshape(ctx.shapes[0]), g_dc.reshape(ctx.shapes[1]), g_rest]
            elif any(ctx.needs_input_grad[7:]):
                weight_grads, g_static, g_view = appearance_arrays.backward(saved_mlp, g_dc, g_rest, g_logits, index,
                                                                            starts, n)
                appearance_grads = [g_static, g_view, *weight_grads]
            else:
                appearance_grads = [None] * len(ctx.shapes)
        grads = [g_xyz, g_t.reshape(n, 1), g_gain, g_cov3, g_var, *appearance_grads]
        return (None, None, *(torch.from_numpy(g) if g is not None and needed else None
                              for g, needed in zip(grads, ctx.needs_input_grad[2:])))


def fused_slice(values: dict[str, torch.Tensor], config, sh_degree: int, sh_degree_t: int, timestamps,
                camera_centers, appearance=None, rows: torch.Tensor | None = None) -> TimeSlice:
    """:func:`omg4.gaussians.model.slice_values` (without a renderer's caches) as the fused function: the backbone's
    motion terms in torch, then :class:`_SliceRows`. ``values`` and the MLPs (if any) are CPU tensors of one dtype,
    float32 or float64 (:func:`runs`); ``rows`` as :func:`~omg4.gaussians.model.slice_values`'s, culled without a
    gather."""
    gain, cov3, var_t = config.schema.motion(values, config)
    spec = SliceSpec(times=_host(timestamps).reshape(-1), centers=_host(camera_centers).reshape(-1, 3),
                     time_range=tuple(config.time_range), time_cull=config.time_cull, band=config.band_size,
                     sh_degree=sh_degree, sh_degree_t=sh_degree_t, conditioned=config.sh_direction == "conditioned",
                     rows=None if rows is None else as_numpy(rows))
    if appearance is None:
        inputs = (values["opacity"], values["features_dc"], values["features_rest"])
    else:
        spec.mlp = (appearance.num_freqs, bool(config.schema.mlp_time_input))
        inputs = (values["f_static"], values["f_view"], *appearance_arrays.weights_of(appearance))
    side: dict = {}
    means, covars, colors, opacities = _SliceRows.apply(spec, side, values["xyz"], values["t"], gain, cov3, var_t,
                                                        *inputs)
    return TimeSlice(means=means, covars=covars, colors=colors, opacities=opacities, index=side["index"],
                     num_total=int(values["xyz"].shape[0]), views=side["views"])


def runs(values: dict[str, torch.Tensor], appearance=None) -> bool:
    """Whether :func:`fused_slice` serves these values: the fused kernels in use (:mod:`omg4.kernels`), every tensor
    on the CPU, all float32 or all float64."""
    tensors = list(values.values()) + ([] if appearance is None else appearance_arrays.weights_of(appearance))
    return runs_cpu_kernels(*tensors)


__all__ = ["SliceSpec", "fused_slice", "runs"]
