"""The render-only decoder: an ``.omg4`` file → a compact model that renders (paper §4.4).

Imports the container, the Real-Time4DGS math and the appearance MLP definition only — no
training or compression code (DESIGN.md: a compressed file must be decodable by code that
does not import them). Sub-vector-quantized attributes are looked up once at load; the
MLPs run per frame, as in the paper's FPS measurements.
"""

from __future__ import annotations

import os

import numpy as np
import torch

from omg4.codec.payload import CompressedPayload, decode_payload
from omg4.errors import CorruptFileError
from omg4.gaussians.appearance import AppearanceMLP, realtime4dgs_values
from omg4.gaussians.model import GaussianConfig, Gaussians4D
from omg4.render.view import TimeSlice

#: SVQ attribute → the parameters its reconstruction fills, with their widths
QUANTIZED_PARAMS: dict[str, tuple[tuple[str, int], ...]] = {
    "scale": (("scaling", 3),),
    "rotation": (("rotation", 4),),
    "app": (("f_static", 3), ("f_view", 3)),
    "scale_t": (("scaling_t", 1),),
    "rotation_r": (("rotation_r", 4),),
}


class CompactModel:
    """A decoded OMG4 model: positions, time centres, codebook lookups and the appearance MLPs, on ``device``."""

    def __init__(self, payload: CompressedPayload, device: torch.device | str = "cpu"):
        meta = payload.meta
        try:
            self.config = GaussianConfig.from_json(meta["gaussian_config"])
            self.active_sh_degree = int(meta["active_sh_degree"])
            self.active_sh_degree_t = int(meta["active_sh_degree_t"])
        except (KeyError, TypeError, ValueError) as e:
            raise CorruptFileError(f"compressed model metadata is incomplete ({e})") from None
        n = payload.num_gaussians
        values = {"xyz": torch.from_numpy(np.asarray(payload.xyz, np.float32).reshape(n, 3)),
                  "t": torch.from_numpy(np.asarray(payload.t, np.float32).reshape(n, 1))}
        for attr, targets in QUANTIZED_PARAMS.items():
            if attr not in payload.attributes:
                raise CorruptFileError(f"compressed model lacks the quantized attribute '{attr}'")
            recon = torch.from_numpy(payload.attributes[attr].reconstruct())
            width = sum(w for _, w in targets)
            if recon.shape != (n, width):
                raise CorruptFileError(f"quantized attribute '{attr}' has shape {tuple(recon.shape)}, "
                                       f"expected ({n}, {width})")
            start = 0
            for name, w in targets:
                values[name] = recon[:, start:start + w]
                start += w
        self.values = {k: v.to(device) for k, v in values.items()}
        self.appearance = AppearanceMLP.from_fp16_state(payload.mlp).eval().to(device)
        self.meta = meta

    @property
    def num_gaussians(self) -> int:
        return int(self.values["xyz"].shape[0])

    def gaussians_at(self, timestamp: float) -> Gaussians4D:
        """The Real-Time4DGS parameters at ``timestamp`` (MLP appearance evaluated)."""
        t0, t1 = self.config.time_range
        with torch.no_grad():
            base = realtime4dgs_values(self.values, self.appearance, (timestamp - t0) / (t1 - t0))
        return Gaussians4D(base, self.config, self.active_sh_degree, self.active_sh_degree_t)

    def slice_at(self, timestamp: float, camera_center: torch.Tensor) -> TimeSlice:
        with torch.no_grad():
            return self.gaussians_at(timestamp).slice_at(timestamp, camera_center)


def load_omg4(path: str | os.PathLike, device: torch.device | str = "cpu") -> CompactModel:
    """Decode an ``.omg4`` file into a :class:`CompactModel` on ``device`` (one-line :class:`CorruptFileError`
    if damaged)."""
    return CompactModel(decode_payload(path), device)
