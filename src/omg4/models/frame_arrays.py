"""A render-only model's frame on arrays: its per-Gaussian arrays made once at load, then per frame the kernels of
:mod:`omg4.gaussians.slice_kernels` (cull, move, colour; the appearance MLPs between them,
:mod:`omg4.gaussians.appearance_arrays`), ready for :func:`omg4.render.arrays.rasterize_arrays`.

Part of the render-only decoder: it imports no training or compression code.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from omg4.gaussians import appearance_arrays
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
            self.joined = appearance_arrays.joined_weights([array(w) for w in appearance_arrays.weights_of(mlp)],
                                                           3 * 2 * mlp.num_freqs)
            # the first layer's position part: the model's cached term (Real-Time4DGS)
            self.position_term = array(model.position_term) if mode == sk.MLP_POSITION_TERM else None

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
        sk.color_rows(index, views, times, centers, self.xyz, self.t, out.means, marginals, self.mode == sk.EXPLICIT,
                      logits, dc, rest, num_sh_coeffs(self.model.active_sh_degree), self.band,
                      self.model.active_sh_degree_t + 1, self.period, self.conditioned, out.colors, out.opacities)
        return out

    def _mlp(self, out: FrameArrays, timestamps: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(logits [M], dc [M, 3], rest [M, K − 1, 3])`` of the slice rows from the appearance MLPs (paper §4.4,
        :func:`omg4.gaussians.appearance_arrays.forward`): on the cached position term plus the view's time term, or
        on the encoded moved positions."""
        t0, t1 = self.time_range
        time_input = self.mode == sk.MLP_POSITION_TERM
        dc, rest, logits, _ = appearance_arrays.forward(
            self.joined, self.num_freqs, time_input, self.xyz, self.f_static, self.f_view, out.index, out.views,
            (timestamps - t0) / (t1 - t0) if time_input else None, None if time_input else out.means, keep=False,
            position_term=self.position_term)
        return logits, dc, rest


__all__ = ["FrameArrays", "FrameKernel"]
