"""The appearance MLPs (paper §4.4; :class:`omg4.gaussians.appearance.AppearanceMLP`) on the arrays of a time slice's
rows, forward and backward: a handful of matrix products in torch on the arrays' memory and numba kernels for the
gathers, activations and scatters between them.

For the rows ``m`` (Gaussian ``index[m]``, view ``views[m]``) of a slice:

    first[m]  = W1_x·Freq(contract(xyz[g])) + W1_t·Freq(t_v)       (Real-Time4DGS: position part once per Gaussian)
              = W1·Freq(contract(μ_m))                               (FreeTimeGS: the position at the view's time)
    shared[m] = W2·ReLU(first[m])
    (dc, logit)[m] = blockdiag(W_dc2, W_op2)·LeakyReLU([W_dc1; W_op1]·[shared, f_static[g]])
    rest[m]   = W_r2·LeakyReLU(W_r1·[shared, f_view[g]])              (LeakyReLU slope 0.01)

The DC and opacity heads run as one pair of products (their first layers stacked, their second layers
block-diagonal). :func:`forward` keeps what :func:`backward` needs (:class:`Activations`); the backward returns the
gradients of the eight weight matrices, of ``f_static`` and ``f_view`` (per Gaussian) — the inputs' positions get
none: the networks see them detached (paper §4.4). Rows of one view hold distinct Gaussians, so the per-Gaussian
scatters run in parallel within a view.

Part of the render-only decoder (its forward serves :mod:`omg4.models.frame_arrays`): no training code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from numba import njit, prange

from omg4.kernels import FAST_MATH  # also points numba's cache where it can write

LEAKY_SLOPE = 0.01
"""LeakyReLU's slope of the heads' hidden layers (tiny-cuda-nn's default, as :class:`AppearanceMLP`)."""

WEIGHT_NAMES = ("shared.0.weight", "shared.2.weight", "dc.0.weight", "dc.2.weight", "opacity.0.weight",
                "opacity.2.weight", "rest.0.weight", "rest.2.weight")
"""The networks' weights, in the order :func:`weights_of` gives them and :func:`backward` returns their gradients."""


def weights_of(mlp) -> list[torch.Tensor]:
    """The networks' eight weight tensors ``[out, in]`` in :data:`WEIGHT_NAMES` order."""
    return [mlp.shared[0].weight, mlp.shared[2].weight, mlp.dc[0].weight, mlp.dc[2].weight, mlp.opacity[0].weight,
            mlp.opacity[2].weight, mlp.rest[0].weight, mlp.rest[2].weight]


def view_ranges(views: np.ndarray, num_views: int) -> np.ndarray:
    """``[V + 1]`` start of each view's rows (rows are grouped by view in order)."""
    return np.searchsorted(views, np.arange(num_views + 1)).astype(np.int64)


def contracted(x: np.ndarray) -> np.ndarray:
    """:func:`omg4.gaussians.appearance.contract_to_unisphere` of ``x [N, 3]``, to the bit (the norm is torch's: the
    encoding's high frequencies turn its last bit into visible colour)."""
    norm = torch.linalg.vector_norm(torch.from_numpy(x), dim=-1, keepdim=True).numpy()
    safe = np.maximum(norm, x.dtype.type(1.0))
    out = np.where(norm > 1.0, (x.dtype.type(2.0) - x.dtype.type(1.0) / safe) * (x / safe), x)
    return out / x.dtype.type(4.0) + x.dtype.type(0.5)


def frequency_encoding(x: np.ndarray, num_freqs: int) -> torch.Tensor:
    """:func:`omg4.gaussians.appearance.frequency_encoding` of ``x [N, D]``: ``[N, D·2F]`` (sin, cos interleaved)."""
    dtype = x.dtype.type
    scales = dtype(math.pi) * np.exp2(np.arange(num_freqs, dtype=x.dtype))
    phase = torch.from_numpy(x[:, :, None] * scales)  # [N, D, F]
    # torch's sine and cosine, as the torch form takes them (numpy's differ in the last bits)
    return torch.stack((phase.sin(), phase.cos()), dim=-1).view(x.shape[0], x.shape[1] * 2 * num_freqs)


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def _first_rows(position, time, slot, index, views, out):
    """``out[m] = ReLU(position[slot[index[m]]] + time[views[m]])`` (hidden width H; ``slot`` None: position has a
    row per Gaussian)."""
    for m in prange(index.shape[0]):
        p = index[m] if slot is None else slot[index[m]]
        v = views[m]
        for j in range(out.shape[1]):
            out[m, j] = max(position[p, j] + time[v, j], 0.0)


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def _head_inputs(shared, f_static, f_view, index, out_static, out_view):
    """``[shared, f_static[g]]`` and ``[shared, f_view[g]]`` of every row."""
    width = shared.shape[1]
    for m in prange(index.shape[0]):
        g = index[m]
        for j in range(width):
            out_static[m, j] = shared[m, j]
            out_view[m, j] = shared[m, j]
        for j in range(3):
            out_static[m, width + j] = f_static[g, j]
            out_view[m, width + j] = f_view[g, j]


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def _leaky_(x, slope):
    """LeakyReLU in place on a 2-D array."""
    for m in prange(x.shape[0]):
        row = x[m]
        for j in range(row.shape[0]):
            row[j] = row[j] if row[j] >= 0 else row[j] * slope


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def _activation_grad_(grad, out, slope):
    """``grad *= f'`` in place, from the activation's output ``out`` (positive exactly where its input is): 1 there,
    ``slope`` elsewhere (0 for ReLU)."""
    for m in prange(grad.shape[0]):
        g, o = grad[m], out[m]
        for j in range(g.shape[0]):
            g[j] = g[j] if o[j] > 0 else g[j] * slope


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def _scatter_features(g_static_in, g_view_in, width, index, starts, g_static, g_view):
    """``g_static[g] += g_static_in[m, width:]`` and the same for the view features, rows of one view at a time
    (distinct Gaussians within a view: no two tasks write one row)."""
    for v in range(starts.shape[0] - 1):
        for m in prange(starts[v], starts[v + 1]):
            g = index[m]
            for j in range(3):
                g_static[g, j] += g_static_in[m, width + j]
                g_view[g, j] += g_view_in[m, width + j]


@njit(parallel=True, cache=True, fastmath=FAST_MATH)
def _first_grads(g_first, index, slot, starts, g_position, g_time):
    """``g_position[slot[g]] += g_first[m]`` per row and ``g_time[v] = Σ_{m in v} g_first[m]`` (float64 sums)."""
    hidden = g_first.shape[1]
    for v in range(starts.shape[0] - 1):
        for m in prange(starts[v], starts[v + 1]):
            p = slot[index[m]]
            for j in range(hidden):
                g_position[p, j] += g_first[m, j]
    for v in prange(starts.shape[0] - 1):
        for j in range(hidden):
            acc = 0.0
            for m in range(starts[v], starts[v + 1]):
                acc += g_first[m, j]
            g_time[v, j] = acc


@dataclass
class Activations:
    """What :func:`backward` needs of a :func:`forward`: the encodings, hidden activations, head inputs and the
    joined weights (tensors on the arrays' memory: the products run in torch, faster than numpy's for these shapes,
    and their ``.numpy()`` views feed the kernels, dispatching nothing); ``slot``/``encoded`` are the Gaussians whose
    position part was computed (Real-Time4DGS)."""

    encoded: torch.Tensor
    time_encoded: torch.Tensor | None
    slot: np.ndarray | None
    hidden: torch.Tensor
    static_in: torch.Tensor
    view_in: torch.Tensor
    head_hidden: torch.Tensor
    rest_hidden: torch.Tensor
    weights: tuple


def joined_weights(weights: list[np.ndarray], position_width: int) -> tuple:
    """The eight ``[out, in]`` weight arrays as the right-hand factors ``[in, out]`` of the products, as tensors:
    (first layer's position part, its time part or None, shared second layer, DC+opacity first layer, DC+opacity
    second layer (block-diagonal), rest first, rest second)."""
    w1, w2, wd1, wd2, wo1, wo2, wr1, wr2 = weights
    dtype = w1.dtype
    hidden = wd1.shape[0]
    second = np.zeros((2 * hidden, wd2.shape[0] + wo2.shape[0]), dtype)
    second[:hidden, :wd2.shape[0]] = wd2.T
    second[hidden:, wd2.shape[0]:] = wo2.T
    first_time = np.ascontiguousarray(w1[:, position_width:].T) if w1.shape[1] > position_width else None
    arrays = (w1[:, :position_width].T, first_time, w2.T, np.concatenate([wd1, wo1]).T, second, wr1.T, wr2.T)
    return tuple(None if a is None else torch.from_numpy(np.ascontiguousarray(a)) for a in arrays)


def forward(joined: tuple, num_freqs: int, time_input: bool, xyz: np.ndarray, f_static: np.ndarray,
            f_view: np.ndarray, index: np.ndarray, views: np.ndarray, t_norm: np.ndarray | None,
            moved: np.ndarray | None, keep: bool = True, position_term: np.ndarray | None = None):
    """``(dc [M, 3], rest [M, R, 3], logit [M], activations or None)`` of the rows ``(index, views)``.

    ``joined``: the networks' weights as :func:`joined_weights` gives them; ``time_input``: a Real-Time4DGS network
    (canonical ``xyz`` [N, 3] and the views' normalized times ``t_norm [V]``), else FreeTimeGS's (``moved [M, 3]``:
    the rows' positions at their view's time). ``keep``: keep the activations for :func:`backward`.
    ``position_term [N, H]``: a render-only model's cached first-layer position part of every Gaussian (it does not
    train: nothing to keep)."""
    dtype = xyz.dtype
    first_pos, first_time, w2, w_head1, w_head2, w_rest1, w_rest2 = joined
    m = index.shape[0]
    if time_input:
        time_encoded = frequency_encoding(t_norm.astype(dtype)[:, None], num_freqs)
        hidden = torch.empty((m, w2.shape[0]), dtype=first_pos.dtype, device="cpu")
        if position_term is None:  # the position part of every Gaussian the rows show, once each
            present = np.zeros(xyz.shape[0], np.bool_)
            present[index] = True
            gaussians = np.flatnonzero(present)
            slot = np.zeros(xyz.shape[0], np.int64)
            slot[gaussians] = np.arange(gaussians.size)
            encoded = frequency_encoding(contracted(xyz[gaussians]), num_freqs)
            position_term = (encoded @ first_pos).numpy()
        else:
            slot, encoded = None, None
        _first_rows(position_term, (time_encoded @ first_time).numpy(), slot, index, views, hidden.numpy())
    else:
        slot, time_encoded = None, None
        encoded = frequency_encoding(contracted(moved), num_freqs)
        hidden = (encoded @ first_pos).relu_()
    shared = (hidden @ w2).numpy()
    width = shared.shape[1]
    static_in = torch.empty((m, width + 3), dtype=first_pos.dtype, device="cpu")
    view_in = torch.empty((m, width + 3), dtype=first_pos.dtype, device="cpu")
    _head_inputs(shared, f_static, f_view, index, static_in.numpy(), view_in.numpy())
    head_hidden = static_in @ w_head1
    _leaky_(head_hidden.numpy(), LEAKY_SLOPE)
    rest_hidden = view_in @ w_rest1
    _leaky_(rest_hidden.numpy(), LEAKY_SLOPE)
    head = (head_hidden @ w_head2).numpy()  # [M, 4]: DC colour, opacity logit
    rest = (rest_hidden @ w_rest2).numpy()
    saved = (Activations(encoded, time_encoded, slot, hidden, static_in, view_in, head_hidden, rest_hidden, joined)
             if keep else None)
    return (np.ascontiguousarray(head[:, :3]), rest.reshape(m, w_rest2.shape[1] // 3, 3),
            np.ascontiguousarray(head[:, 3]), saved)


def backward(saved: Activations, g_dc: np.ndarray, g_rest: np.ndarray, g_logit: np.ndarray, index: np.ndarray,
             starts: np.ndarray, num_gaussians: int):
    """``(weight gradients [out, in] in :data:`WEIGHT_NAMES` order, g_f_static [N, 3], g_f_view [N, 3])`` from the
    rows' gradients ``g_dc [M, 3]``, ``g_rest [M, R, 3]``, ``g_logit [M]`` (``starts``: :func:`view_ranges`)."""
    first_pos, first_time, w2, w_head1, w_head2, w_rest1, w_rest2 = saved.weights
    m, dtype = index.shape[0], g_dc.dtype
    n_dc = 3
    g_head = torch.from_numpy(np.concatenate([g_dc, g_logit[:, None]], axis=1))
    g_head2 = saved.head_hidden.t() @ g_head  # [2H, 4]
    g_head_hidden = g_head @ w_head2.t()
    _activation_grad_(g_head_hidden.numpy(), saved.head_hidden.numpy(), LEAKY_SLOPE)
    g_head1 = saved.static_in.t() @ g_head_hidden  # [S + 3, 2H]
    g_static_in = (g_head_hidden @ w_head1.t()).numpy()
    g_rest_flat = torch.from_numpy(g_rest.reshape(m, g_rest.shape[1] * 3))
    g_rest2 = saved.rest_hidden.t() @ g_rest_flat
    g_rest_hidden = g_rest_flat @ w_rest2.t()
    _activation_grad_(g_rest_hidden.numpy(), saved.rest_hidden.numpy(), LEAKY_SLOPE)
    g_rest1 = saved.view_in.t() @ g_rest_hidden
    g_view_in = (g_rest_hidden @ w_rest1.t()).numpy()
    width = w2.shape[1]
    g_shared = torch.from_numpy(g_static_in[:, :width] + g_view_in[:, :width])
    g_f_static = np.zeros((num_gaussians, 3), dtype)
    g_f_view = np.zeros((num_gaussians, 3), dtype)
    _scatter_features(g_static_in, g_view_in, width, index, starts, g_f_static, g_f_view)
    g_w2 = saved.hidden.t() @ g_shared  # [H, S]
    g_hidden = g_shared @ w2.t()
    _activation_grad_(g_hidden.numpy(), saved.hidden.numpy(), 0.0)
    if saved.slot is not None:
        g_position = torch.zeros((saved.encoded.shape[0], g_hidden.shape[1]), dtype=g_hidden.dtype, device="cpu")
        g_time = torch.empty((len(starts) - 1, g_hidden.shape[1]), dtype=g_hidden.dtype, device="cpu")
        _first_grads(g_hidden.numpy(), index, saved.slot, starts, g_position.numpy(), g_time.numpy())
        g_w1 = np.concatenate([(g_position.t() @ saved.encoded).numpy(),
                               (g_time.t() @ saved.time_encoded).numpy()], axis=1)
    else:
        g_w1 = (g_hidden.t() @ saved.encoded).numpy()
    hidden = w_head1.shape[1] // 2
    g_head1, g_head2 = g_head1.numpy(), g_head2.numpy()
    g_wd1, g_wo1 = g_head1[:, :hidden].T, g_head1[:, hidden:].T
    g_wd2, g_wo2 = g_head2[:hidden, :n_dc].T, g_head2[hidden:, n_dc:].T
    grads = [g_w1, g_w2.numpy().T, g_wd1, g_wd2, g_wo1, g_wo2, g_rest1.numpy().T, g_rest2.numpy().T]
    return [np.ascontiguousarray(g) for g in grads], g_f_static, g_f_view


__all__ = ["Activations", "LEAKY_SLOPE", "WEIGHT_NAMES", "backward", "contracted", "forward", "frequency_encoding",
           "joined_weights", "view_ranges", "weights_of"]
