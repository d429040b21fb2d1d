"""Image files → uint8 RGB arrays: alpha compositing and resizing shared by the readers.

Images stay uint8 until a :class:`~omg4.data.scene.View` asks for them; only then are they
converted to float32 in [0, 1] (:func:`to_float`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from omg4.errors import DataError


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header, without decoding the pixels."""
    try:
        with Image.open(path) as im:
            return im.size
    except FileNotFoundError:
        raise DataError(f"missing image file {path}") from None
    except (UnidentifiedImageError, OSError) as e:
        raise DataError(f"cannot read image {path}: {e}") from None


def read_rgb(path: Path, background: tuple[float, float, float]) -> np.ndarray:
    """uint8 [H, W, 3] of an image file; RGBA is composited as ``rgb·a + bg·(1 − a)``.

    The Blender-reader composite of Real-Time4DGS (rt4dgs §4.2), without its quirk of
    multiplying by alpha a second time.
    """
    try:
        with Image.open(path) as im:
            has_alpha = im.mode in ("RGBA", "LA", "PA") or (im.mode == "P" and "transparency" in im.info)
            arr = np.asarray(im.convert("RGBA" if has_alpha else "RGB"))
    except FileNotFoundError:
        raise DataError(f"missing image file {path}") from None
    except (UnidentifiedImageError, OSError) as e:
        raise DataError(f"cannot read image {path}: {e}") from None
    if not has_alpha:
        return arr
    rgb = arr[..., :3].astype(np.float32) / 255.0
    a = arr[..., 3:4].astype(np.float32) / 255.0
    out = rgb * a + np.asarray(background, dtype=np.float32) * (1.0 - a)
    return np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8)


def resize_rgb(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """uint8 [h, w, 3] → uint8 [height, width, 3] with PIL's bicubic filter (antialiased).

    PIL maps the image extent onto the new extent (pixel centres at +0.5 in both), so
    intrinsics scale by ``width / w`` and ``height / h`` (:meth:`Camera.resized`). Returns the
    input unchanged when the size already matches.
    """
    if img.shape[1] == width and img.shape[0] == height:
        return img
    return np.asarray(Image.fromarray(img).resize((width, height), Image.Resampling.BICUBIC))


def to_float(img: np.ndarray) -> np.ndarray:
    """uint8 [H, W, 3] → float32 [H, W, 3] in [0, 1]."""
    return np.asarray(img, dtype=np.float32) * np.float32(1.0 / 255.0)


def load_image(path: Path, width: int, height: int, background: tuple[float, float, float]) -> np.ndarray:
    """float32 [height, width, 3] in [0, 1] of one image file, composited on ``background`` and resized."""
    return to_float(resize_rgb(read_rgb(path, background), width, height))
