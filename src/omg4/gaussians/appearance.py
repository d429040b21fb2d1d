"""OMG4's time-conditioned appearance MLPs (paper §4.4 "Attribute Compression"; omg4 §6b).

After merging, each Gaussian keeps only a 3-d static and a 3-d view feature; opacity and
all 4D SH coefficients are predicted by four tiny bias-free MLPs with one hidden layer of 64:

    shared  = MLP_cont(Freq16([contract(xyz), t_norm]))          [N, 13]  (ReLU hidden)
    dc      = MLP_dc([shared, f_static])                         [N, 3]   (LeakyReLU(0.01) hidden)
    opacity = sigmoid(MLP_opacity([shared, f_static]))           [N]
    rest    = MLP_view([shared, f_view]).reshape(N, 47, 3)       [N, 47, 3]

``xyz`` is the canonical (not time-shifted) mean, detached so the MLPs send no gradient into
positions; ``t_norm = (τ − t0) / (t1 − t0)`` is the camera time, the same for every Gaussian.
On FreeTimeGS (paper Table 3) the shared network has 3 inputs: the position at the view's
time, μx + v (τ − μt), detached, and no time.
The official code uses tiny-cuda-nn ``FullyFusedMLP``s; these are plain ``nn.Linear(bias=False)``
layers with tcnn's Xavier-uniform initialisation (over tcnn's 16-padded widths).

Size: without tcnn's output padding the four networks hold 21,376 parameters
(shared 9,024, dc 1,216, opacity 1,088, view 10,048), i.e. 42,752 bytes in fp16; the official
tcnn networks pad outputs to multiples of 16 and hold 23,552 (omg4 §6b).

This module is part of the render-only decoder: it imports no training or compression code.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor, nn

from omg4.errors import CorruptFileError

_TCNN_ALIGN = 16  # tiny-cuda-nn pads MLP widths to multiples of 16
MAX_FREQS = 24  # frequency bands a decoded network may declare (2^24·π keeps float32 phases meaningful)
MAX_WIDTH = 4096  # hidden and shared widths a decoded network may declare


def contract_to_unisphere(x: Tensor) -> Tensor:
    """Scene contraction of omg4 §6b (nerfacc's ``contract_to_unisphere``, aabb [-1, 1]^3).

    Inside the unit ball x is kept; outside it becomes ``(2 − 1/‖x‖) x/‖x‖`` (radius in (1, 2));
    the result is mapped by ``x/4 + 0.5`` into [0, 1]^3 (strictly inside the ball of radius 1/2
    around 0.5).

    x: [N, 3] → [N, 3]
    """
    mag = torch.linalg.vector_norm(x, dim=-1, keepdim=True)
    safe = mag.clamp_min(1.0)  # outside the ball mag > 1, so this only guards the unused branch
    contracted = torch.where(mag > 1.0, (2.0 - 1.0 / safe) * (x / safe), x)
    return contracted / 4.0 + 0.5


def frequency_encoding(x: Tensor, num_freqs: int = 16) -> Tensor:
    """tiny-cuda-nn ``Frequency`` encoding (omg4 §6b), no passthrough of the raw input.

    Output column ``j`` of input dimension ``d`` (``j`` in [0, 2F)) is ``sin(2^k π x_d)`` for even ``j``
    and ``cos(2^k π x_d)`` for odd ``j`` with ``k = j // 2``: per dimension
    ``sin(πx), cos(πx), sin(2πx), cos(2πx), …``, dimensions one after another.

    x: [N, D] → [N, D * 2 * num_freqs]
    """
    scales = math.pi * torch.exp2(torch.arange(num_freqs, dtype=x.dtype, device=x.device))  # [F]
    phase = x.unsqueeze(-1) * scales  # [N, D, F]
    enc = torch.stack((torch.sin(phase), torch.cos(phase)), dim=-1)  # [N, D, F, 2]
    return enc.reshape(x.shape[0], x.shape[1] * 2 * num_freqs)


def _tcnn_padded(n: int) -> int:
    """``n`` rounded up to tiny-cuda-nn's width alignment."""
    return -(-n // _TCNN_ALIGN) * _TCNN_ALIGN


def _tcnn_xavier_(weight: Tensor) -> None:
    """Xavier-uniform over tcnn's padded fan-in/fan-out (tcnn ``initialize_xavier_uniform``)."""
    fan_out, fan_in = weight.shape
    limit = math.sqrt(6.0 / (_tcnn_padded(fan_in) + _tcnn_padded(fan_out)))
    with torch.no_grad():
        weight.uniform_(-limit, limit)


def _two_layer(n_in: int, hidden: int, n_out: int, activation: nn.Module) -> nn.Sequential:
    """``Linear(n_in, hidden) → activation → Linear(hidden, n_out)``, no biases (a 1×64 FullyFusedMLP)."""
    net = nn.Sequential(nn.Linear(n_in, hidden, bias=False), activation, nn.Linear(hidden, n_out, bias=False))
    for layer in (net[0], net[2]):
        _tcnn_xavier_(layer.weight)
    return net


class AppearanceMLP(nn.Module):
    """The four OMG4 appearance networks (paper §4.4; omg4 §6b).

    ``shared`` (OMG4 ``mlp_cont``): Freq(contracted xyz, t_norm) [N, 4·2F] → [N, shared_dim]
    (``num_inputs = 3``: Freq(contracted xyz) only); ``dc``, ``opacity`` take ``[shared, f_static]``;
    ``rest`` (``mlp_view``) takes ``[shared, f_view]``. The opacity sigmoid is applied here:
    :meth:`forward` returns activated opacity.
    """

    def __init__(self, num_rest: int = 47, hidden: int = 64, num_freqs: int = 16, shared_dim: int = 13,
                 num_inputs: int = 4):
        super().__init__()
        self.num_rest = num_rest
        self.num_freqs = num_freqs
        self.num_inputs = num_inputs
        head_in = shared_dim + 3
        self.shared = _two_layer(num_inputs * 2 * num_freqs, hidden, shared_dim, nn.ReLU())
        self.dc = _two_layer(head_in, hidden, 3, nn.LeakyReLU(0.01))
        self.opacity = _two_layer(head_in, hidden, 1, nn.LeakyReLU(0.01))
        self.rest = _two_layer(head_in, hidden, 3 * num_rest, nn.LeakyReLU(0.01))

    def predict(self, xyz_canonical: Tensor, t_norm: float | Tensor | None, f_static: Tensor, f_view: Tensor
                ) -> tuple[Tensor, Tensor, Tensor]:
        """Appearance at normalized camera time ``t_norm`` with the opacity as a logit.

        xyz_canonical: [N, 3] means (normalized world; detached here): canonical, or the positions
        at the view's time for a 3-input network; t_norm: camera time mapped to [0, 1] by the time
        range, one for all rows or [N] (rows of several views), None for a 3-input network;
        f_static, f_view: [N, 3].
        Returns ``features_dc [N, 1, 3]``, ``features_rest [N, num_rest, 3]`` and the opacity
        logit ``[N]`` (the opacity is its sigmoid).
        """
        xyz = contract_to_unisphere(xyz_canonical.detach())
        if self.num_inputs == 3:
            inputs = xyz
        elif torch.is_tensor(t_norm):
            inputs = torch.cat((xyz, t_norm.reshape(-1, 1).to(xyz).expand(xyz.shape[0], 1)), dim=1)
        else:
            inputs = torch.cat((xyz, torch.full_like(xyz[:, :1], float(t_norm))), dim=1)
        shared = self.shared(frequency_encoding(inputs, self.num_freqs))  # [N, 13]
        return self._heads(shared, f_static, f_view)

    def position_term(self, xyz_canonical: Tensor, chunk: int = 65536) -> Tensor:
        """The shared network's first-layer response to the positions alone, ``[N, hidden]``.

        The frequency encoding acts on each input dimension separately, so the first layer splits:
        ``W1 · Freq([x, t]) = W1_x · Freq(x) + W1_t · Freq(t)``. For a model that no longer trains the
        position part is fixed; a renderer computes it once at load and a frame then encodes only
        its time (:meth:`predict_from_position_term`). Real-Time4DGS networks only (``num_inputs = 4``).

        xyz_canonical: [N, 3] canonical means (normalized world); computed in blocks of ``chunk`` rows.
        """
        if self.num_inputs != 4:
            raise ValueError("only a time-conditioned network (4 inputs) has a time-independent position term")
        weight = self.shared[0].weight[:, :3 * 2 * self.num_freqs]  # [hidden, 3·2F]
        blocks = [frequency_encoding(contract_to_unisphere(x), self.num_freqs) @ weight.T
                  for x in xyz_canonical.detach().split(chunk)]
        if len(blocks) == 1:  # the usual case: no copy
            return blocks[0]
        return torch.cat(blocks) if blocks else xyz_canonical.new_zeros(0, weight.shape[0])

    def predict_from_position_term(self, position_term: Tensor, t_norm: Tensor, views: Tensor, f_static: Tensor,
                                   f_view: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """:meth:`predict` for rows whose :meth:`position_term` is known: equal up to float rounding.

        position_term: [M, hidden] rows of :meth:`position_term`; t_norm: [V] normalized view times;
        views: [M] view of each row; f_static, f_view: [M, 3]. The time part of the first layer is
        computed once per view, so a frame evaluates no per-Gaussian encoding and no first layer.
        """
        weight = self.shared[0].weight[:, 3 * 2 * self.num_freqs:]  # [hidden, 2F]
        time_term = frequency_encoding(t_norm.reshape(-1, 1).to(weight), self.num_freqs) @ weight.T  # [V, hidden]
        hidden = self.shared[1](position_term + time_term.index_select(0, views))
        return self._heads(self.shared[2](hidden), f_static, f_view)

    def _heads(self, shared: Tensor, f_static: Tensor, f_view: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(dc [N, 1, 3], rest [N, num_rest, 3], opacity logit [N]) from the shared features [N, shared_dim]."""
        static_in = torch.cat((shared, f_static), dim=1)
        dc = self.dc(static_in).unsqueeze(1)  # [N, 1, 3]
        opacity_logit = self.opacity(static_in).squeeze(1)  # [N]
        rest = self.rest(torch.cat((shared, f_view), dim=1)).reshape(-1, self.num_rest, 3)
        return dc, rest, opacity_logit

    def forward(self, xyz_canonical: Tensor, t_norm: float, f_static: Tensor, f_view: Tensor
                ) -> tuple[Tensor, Tensor, Tensor]:
        """Like :meth:`predict` with the opacity in (0, 1): ``(features_dc, features_rest, opacity [N])``."""
        dc, rest, logit = self.predict(xyz_canonical, t_norm, f_static, f_view)
        return dc, rest, torch.sigmoid(logit)

    def num_parameters(self) -> int:
        """Number of weights (21,376 with the default sizes)."""
        return sum(p.numel() for p in self.parameters())

    def to_fp16_state(self) -> dict[str, np.ndarray]:
        """Weights for file storage: ``{state_dict key: fp16 [out, in] array}`` (2 bytes per parameter)."""
        return {k: v.detach().cpu().numpy().astype(np.float16) for k, v in self.state_dict().items()}

    @classmethod
    def from_fp16_state(cls, state: dict[str, np.ndarray], num_inputs: int = 4) -> "AppearanceMLP":
        """Rebuild the networks from :meth:`to_fp16_state` output; sizes are read from the weight shapes
        (``num_inputs``, the backbone's, is not: it fixes how the encoding width splits into bands).

        Raises :class:`~omg4.errors.CorruptFileError` on missing keys, wrong shapes or non-finite weights.
        """
        expected = ("shared.0.weight", "shared.2.weight", "dc.0.weight", "dc.2.weight",
                    "opacity.0.weight", "opacity.2.weight", "rest.0.weight", "rest.2.weight")
        if sorted(state) != sorted(expected):
            raise CorruptFileError(f"appearance MLP weights: expected keys {expected}, got {tuple(sorted(state))}")
        arrays = {k: np.asarray(state[k]) for k in expected}
        for k, a in arrays.items():
            if a.ndim != 2 or a.dtype != np.float16 or not np.isfinite(a).all():
                raise CorruptFileError(f"appearance MLP weight {k}: need a finite fp16 matrix, got {a.dtype} {a.shape}")
        hidden, enc_dim = arrays["shared.0.weight"].shape
        shared_dim = arrays["shared.2.weight"].shape[0]
        rest_out = arrays["rest.2.weight"].shape[0]
        bands = 2 * num_inputs
        if (enc_dim % bands or not 1 <= enc_dim // bands <= MAX_FREQS or rest_out % 3
                or not 1 <= hidden <= MAX_WIDTH or not 1 <= shared_dim <= MAX_WIDTH):
            raise CorruptFileError(f"appearance MLP: invalid sizes (encoding {enc_dim}, hidden {hidden}, "
                                   f"shared {shared_dim}, rest {rest_out})")
        head_in = shared_dim + 3
        expected_shapes = {"shared.0.weight": (hidden, enc_dim), "shared.2.weight": (shared_dim, hidden),
                           "dc.0.weight": (hidden, head_in), "dc.2.weight": (3, hidden),
                           "opacity.0.weight": (hidden, head_in), "opacity.2.weight": (1, hidden),
                           "rest.0.weight": (hidden, head_in), "rest.2.weight": (rest_out, hidden)}
        for k, a in arrays.items():  # checked before any network is built: sizes come from the file
            if tuple(a.shape) != expected_shapes[k]:
                raise CorruptFileError(f"appearance MLP weight {k}: shape {a.shape}, expected {expected_shapes[k]}")
        mlp = cls(num_rest=rest_out // 3, hidden=hidden, num_freqs=enc_dim // bands, shared_dim=shared_dim,
                  num_inputs=num_inputs)
        mlp.load_state_dict({k: torch.from_numpy(a.astype(np.float32)) for k, a in arrays.items()})
        return mlp


__all__ = ["AppearanceMLP", "contract_to_unisphere", "frequency_encoding"]

