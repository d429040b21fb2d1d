"""The render-only decoder: an ``.omg4`` file → a compact model that renders (paper §4.4).

Imports the container, the Real-Time4DGS math and the appearance MLP definition only — no
training or compression code (docs/architecture.md §2: a compressed file must be decodable by
code that does not import them). Sub-vector-quantized attributes are looked up and a per-time-window
visibility index is built once at load; the MLPs run per frame, as in the paper's FPS
measurements, but only on the Gaussians that pass the temporal cull, and the positions' share of
their first layer is computed at load (it does not change with time).
"""

from __future__ import annotations

import os

import numpy as np
import torch

from omg4.codec.payload import CompressedPayload, decode_payload
from omg4.errors import CorruptFileError
from omg4.gaussians.appearance import AppearanceMLP
from omg4.gaussians.model import GaussianConfig
from omg4.models.windowed import WindowedModel


class CompactModel(WindowedModel):
    """A decoded OMG4 model: positions, time centres, codebook lookups and the appearance MLPs, on ``device``.

    The header's backbone (``gaussian_config.backbone``) says which quantized attributes fill which
    parameters (:class:`omg4.gaussians.backbone.Backbone`); files that name none are Real-Time4DGS.
    """

    def __init__(self, payload: CompressedPayload, device: torch.device | str = "cpu"):
        meta = payload.meta
        config, active_sh_degree, active_sh_degree_t = model_settings(meta)
        schema = config.schema
        values = payload_values(payload, schema)
        appearance = AppearanceMLP.from_fp16_state(payload.mlp, schema.mlp_inputs).eval().to(device)
        if appearance.num_rest < config.num_coeffs - 1:
            raise CorruptFileError(f"appearance MLP predicts {appearance.num_rest} SH coefficients, the model "
                                   f"config needs {config.num_coeffs - 1}")
        super().__init__({k: v.to(device) for k, v in values.items()}, config, active_sh_degree, active_sh_degree_t,
                         appearance, meta=meta)


def payload_values(payload: CompressedPayload, schema) -> dict[str, torch.Tensor]:
    """The per-Gaussian parameters of a decoded payload, float32 CPU tensors by the backbone ``schema``'s names:
    positions, time centres and every quantized attribute looked up in its codebooks (one-line CorruptFileError where
    an attribute is missing or of the wrong width)."""
    n = payload.num_gaussians
    values = {"xyz": torch.from_numpy(np.asarray(payload.xyz, np.float32).reshape(n, 3)),
              "t": torch.from_numpy(np.asarray(payload.t, np.float32).reshape(n, 1))}
    for attr in (g.name for g in schema.svq_groups):
        targets = schema.svq_widths(attr)
        if attr not in payload.attributes:
            raise CorruptFileError(f"compressed model lacks the quantized attribute '{attr}'")
        quantized = payload.attributes[attr]
        width, stored = sum(w for _, w in targets), sum(cb.shape[1] for cb in quantized.codebooks)
        if stored != width:
            raise CorruptFileError(f"quantized attribute '{attr}' has width {stored}, expected {width}")
        recon = torch.from_numpy(quantized.reconstruct())
        start = 0
        for name, w in targets:
            values[name] = recon[:, start:start + w]
            start += w
    return values


def model_settings(meta: dict) -> tuple[GaussianConfig, int, int]:
    """The model config and active SH degrees a payload's ``meta`` declares, validated (types, ranges,
    finiteness); anything else raises a one-line :class:`CorruptFileError`."""
    try:
        config = GaussianConfig.from_json(meta["gaussian_config"])
        degrees = meta["active_sh_degree"], meta["active_sh_degree_t"]
    except (KeyError, TypeError, ValueError) as e:
        raise CorruptFileError(f"compressed model metadata is incomplete or invalid ({e})") from None
    limits = (config.sh_degree, config.sh_degree_t)
    if not all(type(d) is int and 0 <= d <= hi for d, hi in zip(degrees, limits)):
        raise CorruptFileError(f"compressed model metadata: active SH degrees {degrees!r} must be integers "
                               f"within the maximum {limits}")
    return config, degrees[0], degrees[1]


def load_omg4(path: str | os.PathLike, device: torch.device | str = "cpu") -> CompactModel:
    """Decode an ``.omg4`` file into a :class:`CompactModel` on ``device`` (one-line :class:`CorruptFileError`
    if damaged)."""
    return CompactModel(decode_payload(path), device)


__all__ = ["CompactModel", "load_omg4", "model_settings", "payload_values"]
