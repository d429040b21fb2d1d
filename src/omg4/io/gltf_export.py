"""glTF 2.0 binary (``.glb``) export of a time slice as 3D Gaussian splats (``KHR_gaussian_splatting``), and its reader.

The extension (Khronos, ``extensions/2.0/Khronos/KHR_gaussian_splatting``) stores splats as a ``POINTS`` mesh
primitive whose attributes are, per Gaussian: ``POSITION`` (the mean), ``KHR_gaussian_splatting:ROTATION`` (a unit
quaternion in glTF's (x, y, z, w) order), ``KHR_gaussian_splatting:SCALE`` (linear σ along the principal axes),
``KHR_gaussian_splatting:OPACITY`` (linear, in [0, 1]) and the real SH coefficients
``KHR_gaussian_splatting:SH_DEGREE_l_COEF_n`` (RGB, n = m + l, the 3DGS basis and signs, colour = SH + 0.5 clamped at
zero) — the slice :mod:`omg4.io.ply_export` writes to ``.ply``: conditional means and covariances at τ, the
opacity times the temporal marginal, the 4D SH folded at τ (rt4dgs §1.4, §2). ``COLOR_0`` holds each splat's base
colour (SH degree 0) and opacity as normalized unsigned bytes, for viewers without the extension. The splat
attributes are float32, one buffer view each, in one binary chunk; ``kernel`` ``ellipse``, ``colorSpace``
``srgb_rec709_display`` (the training images' display-referred sRGB).

glTF is +Y up; omg4's normalized world is +Z up. The export turns the slice into glTF's convention
(:data:`omg4.io.worlds.GLTF`: (x, y, z) → (x, z, −y)), baked into the positions, covariances and SH coefficients
rather than set as a node rotation, because a splat reader that reads the primitive's attributes alone still shows
it upright. With a normalization (``--original-world``) the dataset's own world is written as it is, and
``asset.extras`` names its up direction.
"""

from __future__ import annotations

import json
import os
import struct
from importlib.metadata import PackageNotFoundError, version

import numpy as np

from omg4.atomic import atomic_path
from omg4.data.scene import Normalization
from omg4.errors import CorruptFileError, OMG4Error
from omg4.gaussians.sh import sh_to_rgb
from omg4.io import worlds
from omg4.io.ply_export import covariance_to_scale_rotation, original_up, world_slice

EXTENSION = "KHR_gaussian_splatting"
MAGIC, JSON_CHUNK, BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942
FLOAT, UNSIGNED_BYTE, ARRAY_BUFFER, POINTS = 5126, 5121, 34962, 0
SH_COUNTS = (1, 4, 9, 16)

def sh_semantic(k: int) -> str:
    """The attribute semantic of SH coefficient ``k`` (3DGS order: degree l holds k = l², …, l² + 2l)."""
    degree = int(np.sqrt(k))
    return f"{EXTENSION}:SH_DEGREE_{degree}_COEF_{k - degree * degree}"


def write_gltf_splats(path: str | os.PathLike, means: np.ndarray, covars: np.ndarray, opacities: np.ndarray,
                      sh: np.ndarray, *, extras: dict | None = None) -> None:
    """Write Gaussians as a ``.glb`` with ``KHR_gaussian_splatting`` (atomically).

    Args:
        means: [M, 3]; covars: [M, 3, 3] symmetric PSD; opacities: [M] in [0, 1];
        sh: [M, K, 3] coefficient-major SH (K = 1, 4, 9 or 16; DC first).
        extras: JSON-serializable facts kept in ``asset.extras`` (the source and time of the slice).
    Raises a one-line :class:`OMG4Error` when a value is not finite in float32 (nothing is written).
    """
    m, k = sh.shape[0], sh.shape[1]
    if k not in SH_COUNTS:
        raise ValueError(f"{k} SH coefficients is not a 3DGS layout")
    log_scales, quats = covariance_to_scale_rotation(np.asarray(covars, dtype=np.float64))
    columns = {"POSITION": np.asarray(means, np.float64),
               f"{EXTENSION}:ROTATION": quats[:, [1, 2, 3, 0]],  # (w, x, y, z) → glTF's (x, y, z, w)
               f"{EXTENSION}:SCALE": np.exp(log_scales),
               f"{EXTENSION}:OPACITY": np.clip(np.asarray(opacities, np.float64), 0.0, 1.0)}
    columns.update({sh_semantic(j): sh[:, j, :] for j in range(k)})
    with np.errstate(over="ignore", invalid="ignore"):
        arrays = {name: np.ascontiguousarray(a, dtype="<f4") for name, a in columns.items()}
    if not all(np.isfinite(a).all() for a in arrays.values()):
        raise OMG4Error(f"{path}: the model's values are not finite in float32 (NaN or beyond ±3.4e38); nothing written")
    rotation = arrays[f"{EXTENSION}:ROTATION"]
    rotation /= np.linalg.norm(rotation, axis=1, keepdims=True).astype("<f4")  # unit in float32 too
    rgba = np.concatenate([np.clip(sh_to_rgb(sh[:, 0, :]), 0.0, 1.0), columns[f"{EXTENSION}:OPACITY"][:, None]], 1)
    arrays["COLOR_0"] = np.round(rgba * 255.0).astype(np.uint8)  # the base colour, for viewers without the extension
    blob, views, accessors, attributes = bytearray(), [], [], {}
    for name, a in arrays.items():
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": a.nbytes, "target": ARRAY_BUFFER})
        accessor = {"bufferView": len(views) - 1, "componentType": FLOAT, "count": m,
                    "type": "SCALAR" if a.ndim == 1 else f"VEC{a.shape[1]}"}
        if a.dtype == np.uint8:
            accessor.update(componentType=UNSIGNED_BYTE, normalized=True)
        if name == "POSITION":  # glTF requires its bounds
            accessor.update(min=a.min(0).tolist() if m else [0.0] * 3, max=a.max(0).tolist() if m else [0.0] * 3)
        attributes[name] = len(accessors)
        accessors.append(accessor)
        blob += a.tobytes()
    document = {
        "asset": {"version": "2.0", "generator": _generator(), **({"extras": extras} if extras else {})},
        "extensionsUsed": [EXTENSION],
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"mode": POINTS, "attributes": attributes, "extensions": {
            EXTENSION: {"kernel": "ellipse", "colorSpace": "srgb_rec709_display"}}}]}],
        "buffers": [{"byteLength": len(blob)}], "bufferViews": views, "accessors": accessors,
    }
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    blob += b"\0" * (-len(blob) % 4)
    total = 12 + 8 + len(text) + 8 + len(blob)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(struct.pack("<III", MAGIC, 2, total))
            f.write(struct.pack("<II", len(text), JSON_CHUNK) + text)
            f.write(struct.pack("<II", len(blob), BIN_CHUNK) + bytes(blob))


def _generator() -> str:
    """``omg4 <installed version>`` (the package's metadata: this module sits below the package's top)."""
    try:
        return f"omg4 {version('omg4')}"
    except PackageNotFoundError:
        return "omg4"


def read_gltf_splats(path: str | os.PathLike) -> dict[str, np.ndarray | dict]:
    """The splats of a ``.glb`` written by :func:`write_gltf_splats` (the first primitive with the extension):
    ``means`` [M, 3], ``rotations`` [M, 4] (x, y, z, w), ``scales`` [M, 3], ``opacities`` [M], ``sh`` [M, K, 3] and
    the ``document`` (the JSON chunk). Float32 accessors without stride only; anything else is a one-line
    :class:`CorruptFileError`."""
    data = open(path, "rb").read()
    if len(data) < 20 or struct.unpack_from("<I", data)[0] != MAGIC:
        raise CorruptFileError(f"{path}: not a binary glTF (.glb) file")
    _, version, total = struct.unpack_from("<III", data)
    json_len, json_type = struct.unpack_from("<II", data, 12)
    if version != 2 or total != len(data) or json_type != JSON_CHUNK or 20 + json_len + 8 > total:
        raise CorruptFileError(f"{path}: a damaged .glb header (version {version}, {total} of {len(data)} bytes)")
    document = json.loads(data[20:20 + json_len])
    bin_len, bin_type = struct.unpack_from("<II", data, 20 + json_len)
    blob = data[28 + json_len:28 + json_len + bin_len]
    if bin_type != BIN_CHUNK or len(blob) != bin_len:
        raise CorruptFileError(f"{path}: the .glb's binary chunk is missing or cut short")
    try:
        primitive = next(p for mesh in document["meshes"] for p in mesh["primitives"]
                         if EXTENSION in p.get("extensions", {}))
    except (KeyError, StopIteration):
        raise CorruptFileError(f"{path}: no mesh primitive with {EXTENSION}") from None

    def column(name: str) -> np.ndarray:
        accessor = document["accessors"][primitive["attributes"][name]]
        view = document["bufferViews"][accessor["bufferView"]]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[accessor["type"]]
        start, count = view.get("byteOffset", 0) + accessor.get("byteOffset", 0), accessor["count"]
        if accessor["componentType"] != FLOAT or "byteStride" in view or start + 4 * width * count > len(blob):
            raise CorruptFileError(f"{path}: attribute {name} is not a packed float32 array within the buffer")
        a = np.frombuffer(blob, "<f4", width * count, start).astype(np.float64)
        return a if width == 1 else a.reshape(count, width)

    sh_names = [sh_semantic(j) for j in range(16) if sh_semantic(j) in primitive["attributes"]]
    if len(sh_names) not in SH_COUNTS or sh_names != [sh_semantic(j) for j in range(len(sh_names))]:
        raise CorruptFileError(f"{path}: the SH attributes do not make whole degrees ({len(sh_names)} coefficients)")
    try:
        return {"means": column("POSITION"), "rotations": column(f"{EXTENSION}:ROTATION"),
                "scales": column(f"{EXTENSION}:SCALE"), "opacities": column(f"{EXTENSION}:OPACITY"),
                "sh": np.stack([column(n) for n in sh_names], axis=1), "document": document}
    except (KeyError, IndexError) as exc:
        raise CorruptFileError(f"{path}: a splat attribute is missing or points nowhere ({exc})") from None


def export_gltf(path: str | os.PathLike, model, timestamp: float, *, normalization: Normalization | None = None) -> int:
    """Write the time slice of ``model`` at ``timestamp`` as a ``.glb`` (``KHR_gaussian_splatting``): the slice
    :func:`omg4.io.ply_export.export_ply` writes, the same arguments; the time and world are recorded in
    ``asset.extras``. Returns the number of Gaussians written."""
    means, covars, opacities, sh = world_slice(model, timestamp, normalization, worlds.GLTF)
    if normalization is None:  # glTF's +Y up (module docstring)
        extras = {"time": float(timestamp), "world": "normalized", "up": [0.0, 1.0, 0.0],
                  "from_omg4_world": worlds.GLTF.tolist()}
    else:
        extras = {"time": float(timestamp), "world": "original", "up": original_up(normalization).tolist()}
    write_gltf_splats(path, means, covars, opacities, sh, extras=extras)
    return len(means)


__all__ = ["EXTENSION", "export_gltf", "read_gltf_splats", "sh_semantic", "write_gltf_splats"]
