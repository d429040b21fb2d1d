"""What a predicted segment takes from the segment before (docs/file-format.md §8a): the decoded arrays it may take
as its own (:func:`reference_sections`), and, when reading, the arrays of the sections it took
(:func:`referenced`). A predicted segment's carried Gaussians are :mod:`omg4.codec.carry`'s."""

from __future__ import annotations

import numpy as np

from omg4.codec import carry
from omg4.codec.types import CompressedPayload, QuantizedAttribute
from omg4.errors import CorruptFileError


def reference_sections(p: CompressedPayload) -> dict[str, np.ndarray]:
    """The decoded arrays of ``p`` (a decoder's output) that a segment predicted from it may take as its own, by
    section name (docs/file-format.md §8a): every MLP weight (``mlp.NAME``) and every codebook of the
    sub-vector-quantized attributes that are not rotations (``svq.ATTR.codebookJ``; a rotation may be stored one
    quaternion per Gaussian, which is no codebook), and the per-Gaussian arrays it may carry
    (:func:`omg4.codec.carry.gaussian_sections`)."""
    out = {**{f"mlp.{name}": w for name, w in p.mlp.items()}, **carry.gaussian_sections(p)}
    for attr, qa in p.attributes.items():
        if attr not in p.rotations:
            out.update({f"svq.{attr}.codebook{j}": cb for j, cb in enumerate(qa.codebooks)})
    return out


def takes_codebooks(qa: QuantizedAttribute, attr: str, reference: dict[str, np.ndarray]) -> bool:
    """Whether every codebook of ``qa`` (fp16) is the reference's of the same slot, value for value."""
    names = [f"svq.{attr}.codebook{j}" for j in range(len(qa.codebooks))]
    return (f"svq.{attr}.codebook{len(names)}" not in reference and all(
        n in reference and reference[n].shape == cb.shape and np.array_equal(reference[n], cb)
        for n, cb in zip(names, qa.codebooks)))


def referenced(name: str, data: bytes, shape: tuple[int, ...] | None, reference: dict[str, np.ndarray] | None
                ) -> np.ndarray:
    """Section ``name`` of a predicted segment, taken from its reference (one-line errors on anything forged)."""
    if data:
        raise CorruptFileError(f"a section taken from the reference holds {len(data)} bytes of its own")
    return np.array(reference_array(name, shape, reference), np.float16)


def reference_array(name: str, shape: tuple[int, ...] | None, reference: dict[str, np.ndarray] | None
                     ) -> np.ndarray:
    """The reference's decoded array behind section ``name`` of a predicted segment, of the declared ``shape``."""
    if reference is None:
        raise CorruptFileError("a predicted segment takes its sections from the segment before: decode it through "
                               "its sequence file")
    if name not in reference:
        raise CorruptFileError("the reference segment has no such section")
    array = reference[name]
    if shape is None or tuple(array.shape) != tuple(shape):
        raise CorruptFileError(f"the reference's section has shape {tuple(array.shape)}, the header declares "
                               f"{None if shape is None else tuple(shape)}")
    return array


__all__ = ["reference_array", "reference_sections", "referenced", "takes_codebooks"]
