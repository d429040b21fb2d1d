"""A render-only model's frame on arrays: its per-Gaussian arrays made once at load, then per frame the kernels of
:mod:`omg4.gaussians.slice_kernels` (cull, move, colour; the appearance MLPs between them as a few torch products on
the arrays' memory), ready for :func:`omg4.render.arrays.rasterize_arrays`.

Part of the render-only decoder: it imports no training or compression code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from omg4.gaussians import slice_kernels as sk
from omg4.gaussians.sh import num_sh_coeffs


@dataclass
class FrameArrays:
    """The 3D Gaussians a frame shows, as numpy arrays (the fields of :class:`omg4.render.view.TimeSlice`)."""

    means: np.ndarray
    covars: np.ndarray
    colors: np.ndarray
    opacities: np.ndarray
    index: np.ndarray
    views: np.ndarray


class FrameKernel:
    """Every array a frame of a :class:`~omg4.models.windowed.WindowedModel` reads, as numpy views made at load.

    :meth:`build` gives None where the kernels do not serve the model: values off the CPU or of another dtype than
    float32/float64, or time-conditioned MLPs whose position term the model could not cache."""

    @classmethod
    def build(cls, model) -> "FrameKernel | None":
        v, config = model.values, model.config
        xyz = v["xyz"]
        if xyz.device.type != "cpu" or xyz.dtype not in (torch.float32, torch.float64):
            return None
        mlp = model.appearance
        if mlp is None:
            mode = sk.EXPLICIT
        elif config.schema.mlp_time_input:
            if model.position_term is None:
                return None
            mode = sk.MLP_POSITION_TERM
        else:
            mode = sk.MLP_CONDITIONED
        return cls(model, mode)

    def __init__(self, model, mode: int):
        v, config = model.values, model.config
        self.dtype = v["xyz"].dtype
        np_dtype = np.float64 if self.dtype == torch.float64 else np.float32
        self.np_dtype = np_dtype

        def array(t, shape=None):
            a = t.detach().to(self.dtype).contiguous().numpy()
            return a.reshape(shape) if shape is not None else a

        n = int(v["xyz"].shape[0])
        self.mode = mode
        self.xyz, self.t = array(v["xyz"]), array(v["t"], (n,))
        gain, cov3, var_t = model.motion
        self.gain, self.cov3, self.var_t = array(gain), array(cov3), array(var_t, (n,))
        self.rows = [r.numpy() for r in model.visibility.rows]
        self.visibility = model.visibility
        self.consts = sk.kernel_consts(config.time_cull, np_dtype)
        self.time_range = config.time_range
        self.period = float(config.period)
        self.band = int(config.band_size)
        self.conditioned = config.sh_direction == "conditioned"
        self.model = model  # its active SH degrees are read per frame, as the torch form reads them
        mlp = model.appearance
        if mode == sk.EXPLICIT:
            self.logits, self.dc = array(v["opacity"], (n,)), array(v["features_dc"], (n, 3))
            self.rest = array(v["features_rest"])
        else:
            self.f_static, self.f_view = array(v["f_static"]), array(v["f_view"])
            self.num_freqs = mlp.num_freqs
            self.layers = _joined_layers(mlp, self.dtype)
            if mode == sk.MLP_POSITION_TERM:  # the first layer's position part is the cached term
                self.position_term = array(model.position_term)
                self.w_time = array(mlp.shared[0].weight[:, 3 * 2 * mlp.num_freqs:])
            else:
                self.scales = np_dtype(math.pi) * np.exp2(np.arange(mlp.num_freqs, dtype=np_dtype))

    def candidates(self, times: list[float]) -> np.ndarray:
        """The rows of the time windows of ``times`` (every row when one lies outside the model's range)."""
        k = self.visibility.windows_at(times)
        if k is None:
            return np.arange(self.xyz.shape[0], dtype=np.int64)
        if len(k) == 1:
            return self.rows[k[0]]
        return np.unique(np.concatenate([self.rows[i] for i in k]))

    def frame(self, timestamps: np.ndarray, centers: np.ndarray) -> FrameArrays:
        """The slice at ``timestamps [V]`` (float64) for viewers at ``centers [V, 3]``."""
        times, d = timestamps.astype(self.np_dtype), self.np_dtype
        centers = centers.astype(d)
        rows = self.candidates(timestamps.tolist())
        keep = np.empty((len(times), len(rows)), dtype=np.bool_)
        sk.cull(rows, self.t, self.var_t, times, self.consts, keep)
        views, position = np.nonzero(keep)
        index, m = rows[position], len(position)
        out = FrameArrays(means=np.empty((m, 3), d), covars=np.empty((m, 3, 3), d), colors=np.empty((m, 3), d),
                          opacities=np.empty(m, d), index=index, views=views)
        marginals = np.empty(m, d)
        sk.move_rows(index, views, times, self.xyz, self.t, self.gain, self.cov3, self.var_t, self.consts, out.means,
                     out.covars, marginals)
        logits, dc, rest = (self.logits, self.dc, self.rest) if self.mode == sk.EXPLICIT else self._mlp(out, timestamps)
        sk.color_rows(index, views, times, centers, self.xyz, self.t, out.means, marginals,
                      self.mode == sk.EXPLICIT, logits, dc, rest, num_sh_coeffs(self.model.active_sh_degree), self.band, self.model.active_sh_degree_t + 1,
                      self.period, self.conditioned, out.colors, out.opacities)
        return out

    def _mlp(self, out: FrameArrays, timestamps: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(logits [M], dc [M, 3], rest [M, K − 1, 3])`` of the slice rows from the appearance MLPs (paper §4.4):
        the joined layers (:func:`_joined_layers`) on the rows' first-layer responses — the cached position term plus
        the view's time term, or the encoded moved positions."""
        index, (w1, w2, w_static, w_static2, w_rest, w_rest2) = out.index, self.layers
        if self.mode == sk.MLP_POSITION_TERM:
            t0, t1 = self.time_range
            time_term = sk.time_term((timestamps - t0) / (t1 - t0), self.w_time, self.num_freqs)
            first = torch.from_numpy(self.position_term[index] + time_term[out.views])
        else:
            encoded = np.empty((len(index), 3 * 2 * self.num_freqs), self.np_dtype)
            sk.encode_contracted(out.means, self.scales, self.consts, encoded)
            first = torch.from_numpy(encoded).mm(w1)
        shared = first.relu_().mm(w2)
        static = F.leaky_relu_(torch.cat([shared, torch.from_numpy(self.f_static[index])], dim=1).mm(w_static))
        rest = F.leaky_relu_(torch.cat([shared, torch.from_numpy(self.f_view[index])], dim=1).mm(w_rest)).mm(w_rest2)
        dc_logit = static.mm(w_static2).numpy()  # [M, 4]: the DC colour, then the opacity logit
        return dc_logit[:, 3], dc_logit[:, :3], rest.numpy().reshape(len(index), rest.shape[1] // 3, 3)


def _joined_layers(mlp, dtype: torch.dtype) -> tuple[torch.Tensor, ...]:
    """The appearance MLPs' weights (paper §4.4) as right-hand factors ``[in, out]`` for a frame's products: the
    shared network's two layers, the DC and opacity heads joined (their first layers side by side, their second
    layers block-diagonal: one product each for both) and the rest head's two layers."""
    with torch.no_grad():
        def right(layer):
            return layer.weight.detach().to(dtype).t().contiguous()

        w_dc, w_op = right(mlp.dc[2]), right(mlp.opacity[2])  # [H, 3], [H, 1]
        second = torch.zeros(w_dc.shape[0] + w_op.shape[0], 4, dtype=dtype)
        second[:w_dc.shape[0], :3], second[w_dc.shape[0]:, 3:] = w_dc, w_op
        first = torch.cat([right(mlp.dc[0]), right(mlp.opacity[0])], dim=1)
        return right(mlp.shared[0]), right(mlp.shared[2]), first, second, right(mlp.rest[0]), right(mlp.rest[2])


__all__ = ["FrameArrays", "FrameKernel"]
