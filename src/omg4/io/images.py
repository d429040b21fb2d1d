"""Image files: 8-bit PNG and float32 ``.npy`` output, and loading either back.

Float images are ``[H, W, 3]`` in [0, 1]; a PNG stores ``rint(clip(x, 0, 1)·255)`` (ties to
even), and a ``.npy`` keeps the float32 values before that rounding, for exact comparisons
(docs/architecture.md §3 "Colour and background"). Every write is atomic.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError

from omg4.atomic import atomic_path
from omg4.errors import CorruptFileError, OMG4Error

ImageLike = torch.Tensor | np.ndarray


def _as_rgb_array(img: ImageLike) -> np.ndarray:
    """``img`` as a numpy ``[H, W, 3]`` array (torch tensors are detached and moved to CPU)."""
    arr = img.detach().cpu().numpy() if isinstance(img, torch.Tensor) else np.asarray(img)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ValueError(f"expected an RGB image [H, W, 3], got shape {arr.shape}")
    return arr


def to_float32(img: ImageLike) -> np.ndarray:
    """Float32 ``[H, W, 3]`` copy of an RGB image; uint8 input is divided by 255."""
    arr = _as_rgb_array(img)
    if arr.dtype == np.uint8:
        return arr.astype(np.float32) / 255.0
    out = arr.astype(np.float32)
    if not np.isfinite(out).all():
        raise OMG4Error("image contains NaN or Inf values")
    return out


def to_uint8(img: ImageLike) -> np.ndarray:
    """8-bit ``[H, W, 3]`` image: uint8 input as is, floats as ``rint(clip(x, 0, 1)·255)`` (ties to even,
    numpy's rounding, as :func:`omg4.data.points.write_ply` rounds colours)."""
    arr = _as_rgb_array(img)
    if arr.dtype == np.uint8:
        return np.ascontiguousarray(arr)
    return np.rint(np.clip(to_float32(arr), 0.0, 1.0) * 255.0).astype(np.uint8)


def save_png(path: str | os.PathLike, img: ImageLike) -> None:
    """Write ``img`` ([H, W, 3] float in [0, 1], or uint8) as an 8-bit RGB PNG, atomically."""
    pixels = Image.fromarray(to_uint8(img))
    with atomic_path(path) as tmp:
        pixels.save(tmp, format="PNG")


def save_npy(path: str | os.PathLike, img: ImageLike) -> None:
    """Write ``img`` as a float32 ``[H, W, 3]`` ``.npy`` (no rounding), atomically."""
    arr = to_float32(img)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, arr, allow_pickle=False)


def load_image(path: str | os.PathLike) -> np.ndarray:
    """Read a ``.npy`` (float ``[H, W, 3]``) or any image PIL reads (PNG, JPEG, ...) as float32 [H, W, 3] in [0, 1].

    Grayscale images are replicated to three channels; an alpha channel is dropped.
    Raises :class:`OMG4Error` for a missing file, :class:`CorruptFileError` for an
    unreadable one.
    """
    path = Path(path)
    if not path.is_file():
        raise OMG4Error(f"image file not found: {path}")
    if path.suffix.lower() == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise CorruptFileError(f"cannot read {path} as a .npy array: {exc}") from None
        if arr.ndim != 3 or arr.shape[2] != 3 or not np.issubdtype(arr.dtype, np.floating):
            raise CorruptFileError(f"{path} holds a {arr.dtype} array of shape {arr.shape}, "
                                   "not a float [H, W, 3] image")
        return to_float32(arr)
    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
    except (UnidentifiedImageError, OSError) as exc:
        raise CorruptFileError(f"cannot read image {path}: {exc}") from None
