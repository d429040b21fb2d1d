"""The ``.omg4`` file: versioned container, index entropy coders, compressed-model payload.

Decoding needs nothing from training or compression code (docs/architecture.md, "Layers"):
the container, coders and payload depend only on numpy, numba, constriction, dahuffman and the
standard library. ``forge`` (hostile-file generation for tests and fuzzing) is the exception: it
runs files through the commands and is never imported by the decoder.
"""

from omg4.codec.container import FORMAT_VERSION, MAGIC, describe_container, read_container, write_container
from omg4.codec.entropy import decode_indices, decode_uints, encode_indices, encode_uints
from omg4.codec.payload import CompressedPayload, QuantizedAttribute, decode_payload, encode_payload
from omg4.codec.sections import canonical_order

__all__ = [
    "FORMAT_VERSION", "MAGIC", "describe_container", "read_container", "write_container",
    "decode_indices", "decode_uints", "encode_indices", "encode_uints",
    "CompressedPayload", "QuantizedAttribute", "canonical_order", "decode_payload", "encode_payload",
]
