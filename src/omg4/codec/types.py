"""The values an ``.omg4`` file holds, as the coders, the carried-Gaussians section and the readers share them
(omg4 §8): :class:`CompressedPayload`, its :class:`QuantizedAttribute` s, and :data:`REFERENCE`, the encoding of a
section a predicted segment takes from the segment before. Below every codec module: it imports none."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

REFERENCE = "reference"
"""The encoding of a section whose values are the reference segment's (a predicted segment, docs/file-format.md §8)."""


@dataclass
class QuantizedAttribute:
    """One sub-vector-quantized attribute (paper §4.4; omg4 §7).

    ``codebooks[j]: [K_j, s_j]`` (fp16) holds the centroids of sub-vector slot j and
    ``indices[j]: [N]`` (int) picks a row per Gaussian; the attribute is the concatenation
    of ``codebooks[j][indices[j]]`` over slots, ``[N, Σ s_j]``.
    """

    codebooks: list[np.ndarray]
    indices: list[np.ndarray]

    def reconstruct(self) -> np.ndarray:
        """The quantized attribute values, float32 ``[N, D]``."""
        return np.concatenate([cb.astype(np.float32)[ix] for cb, ix in zip(self.codebooks, self.indices)], axis=1)


@dataclass
class CompressedPayload:
    """Everything an ``.omg4`` file stores (omg4 §8).

    xyz: [N, 3] positions; t: [N] time centres; attributes: SVQ attribute name (scale,
    rotation, app, scale_t, rotation_r) → :class:`QuantizedAttribute`; mlp: weight name →
    array (any shape); meta: JSON-able settings; rotations: the attributes that are one rotation
    quaternion each, normalized at use (the backbone's ``quaternion_groups``; the "compact" codec
    may store them as unit quaternions). Floats are stored in fp16. carried: for a predicted segment about to be
    written, the rows of the reference segment's decoded Gaussians it also holds as they are (:mod:`omg4.codec.carry`;
    the arrays then hold only its own Gaussians); a decoded payload holds them in its arrays and carried is None.
    """

    xyz: np.ndarray
    t: np.ndarray
    attributes: dict[str, QuantizedAttribute] = field(default_factory=dict)
    mlp: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)
    rotations: tuple[str, ...] = ()
    log_scaled: tuple[str, ...] = ()
    carried: np.ndarray | None = None

    @property
    def num_gaussians(self) -> int:
        return int(self.xyz.shape[0])

    def permuted(self, order: np.ndarray) -> "CompressedPayload":
        """The same payload with Gaussians reordered: row i of the result is row ``order[i]``."""
        attrs = {a: QuantizedAttribute(list(q.codebooks), [ix[order] for ix in q.indices])
                 for a, q in self.attributes.items()}
        return CompressedPayload(self.xyz[order], self.t[order], attrs, dict(self.mlp), dict(self.meta), self.rotations,
                                 self.log_scaled, self.carried)

    def to_fp16(self) -> "CompressedPayload":
        """What a decoder returns: floats rounded to fp16 (float16 arrays), indices as int64."""
        attrs = {a: QuantizedAttribute([np.asarray(cb, np.float16) for cb in q.codebooks],
                                       [np.asarray(ix).astype(np.int64) for ix in q.indices])
                 for a, q in self.attributes.items()}
        return CompressedPayload(np.asarray(self.xyz, np.float16).reshape(-1, 3),
                                 np.asarray(self.t, np.float16).reshape(-1), attrs,
                                 {k: np.asarray(v, np.float16) for k, v in self.mlp.items()}, dict(self.meta),
                                 tuple(self.rotations), tuple(self.log_scaled), self.carried)


__all__ = ["REFERENCE", "CompressedPayload", "QuantizedAttribute"]
