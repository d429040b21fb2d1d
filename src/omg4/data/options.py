"""Reader options shared by every dataset reader, and the rules that interpret them."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from omg4.data.scene import MAX_IMAGE_SIDE, MAX_PIXELS, fits_render_limits
from omg4.errors import DataError

FrameSelection = slice | range | Iterable[int] | None


@dataclass(frozen=True)
class LoadOptions:
    """What :func:`omg4.data.load_scene` asks of a reader.

    Attributes:
        downscale: divide both image dimensions by this factor (``round(W / downscale)``,
            the Real-Time4DGS ``resolution`` rule, rt4dgs §4.2).
        width: explicit target width in pixels; overrides ``downscale`` (height keeps the
            aspect ratio, rounded).
        frames: frame indices to keep (slice, range or iterable), ``None`` for all.
        cameras: camera names to keep, ``None`` for all. Never changes the normalization.
        background: RGB in [0, 1] that RGBA images are composited on.
        cache_dir: N3DV frame-cache folder (``None``: ``$OMG4_CACHE_DIR`` or ``~/.cache/omg4/frames``).
        fps: N3DV frame rate override (``None``: the video stream's rate).
        normalize: ``True``: map the dataset into the normalized world (official N3DV
            normalization); ``False``: keep the dataset's world (identity transform);
            ``"auto"``: ``True`` for N3DV and Panoptic, and for Blender only when its poses are
            not already in a normalized world (:func:`omg4.data.normalize.already_normalized`),
            so that D-NeRF and n3v2blender exports keep the world official checkpoints use.
        points_world: world of ``points3d.ply``: ``"original"`` (the dataset's own pose world,
            as ``omg4 synth`` writes it), ``"normalized"`` (already normalized), or ``"auto"``:
            ``"normalized"`` for an N3DV folder that also holds the official n3v2blender output
            (``transforms_train.json``: its COLMAP points are in the normalized world), else
            ``"original"``.
        decode: N3DV: decode the selected videos into the frame cache now (progress bar);
            ``False`` defers decoding to the first image access (``omg4 info`` never decodes).
        progress: show progress bars.
    """

    downscale: float = 1.0
    width: int | None = None
    frames: FrameSelection = None
    cameras: tuple[str, ...] | None = None
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    cache_dir: Path | None = None
    fps: float | None = None
    normalize: bool | str = "auto"
    points_world: str = "auto"
    decode: bool = True
    progress: bool = True

    def __post_init__(self) -> None:
        if not (self.downscale > 0 and np.isfinite(self.downscale)):
            raise DataError(f"downscale must be a positive number, got {self.downscale}")
        if self.width is not None and int(self.width) <= 0:
            raise DataError(f"width must be positive, got {self.width}")
        if self.normalize not in (True, False, "auto"):
            raise DataError(f"normalize must be True, False or 'auto', got {self.normalize!r}")
        if self.points_world not in ("auto", "original", "normalized"):
            raise DataError(f"points_world must be 'auto', 'original' or 'normalized', got '{self.points_world}'")
        bg = tuple(float(x) for x in self.background)
        if len(bg) != 3 or not all(0.0 <= x <= 1.0 for x in bg):
            raise DataError(f"background must be three values in [0, 1], got {self.background}")
        object.__setattr__(self, "background", bg)

    def output_size(self, width: int, height: int) -> tuple[int, int]:
        """(width, height) of images of native size ``width × height`` after resizing; a size beyond the
        rendering limits (:data:`~omg4.data.scene.MAX_IMAGE_SIDE` a side, :data:`~omg4.data.scene.MAX_PIXELS` in
        all) is a :class:`DataError`."""
        if self.width is not None:
            w = int(self.width)
            size = w, max(1, int(round(height * w / width)))
        else:
            size = max(1, int(round(width / self.downscale))), max(1, int(round(height / self.downscale)))
        if not fits_render_limits(*size):
            raise DataError(f"{width}x{height} images resized to {size[0]}x{size[1]} exceed {MAX_IMAGE_SIDE} pixels "
                            f"a side or {MAX_PIXELS} pixels: choose a larger --downscale")
        return size

    def frame_cache_dir(self) -> Path:
        """The frame-cache folder: ``cache_dir``, else ``$OMG4_CACHE_DIR``, else ``~/.cache/omg4/frames``."""
        if self.cache_dir is not None:
            return Path(self.cache_dir)
        env = os.environ.get("OMG4_CACHE_DIR")
        return Path(env) if env else Path.home() / ".cache" / "omg4" / "frames"


def select_frames(selection: FrameSelection, num_frames: int) -> np.ndarray:
    """Sorted unique frame indices [F] picked by ``selection`` out of ``range(num_frames)``.

    A slice is clipped like Python slicing; a range or list must lie inside the sequence.
    """
    if selection is None:
        idx = np.arange(num_frames)
    elif isinstance(selection, slice):
        idx = np.arange(num_frames)[selection]
    else:
        idx = np.asarray(list(selection), dtype=np.int64).reshape(-1)
        bad = idx[(idx < 0) | (idx >= num_frames)]
        if len(bad):
            raise DataError(f"frame {int(bad[0])} is out of range: the sequence has {num_frames} frames")
    idx = np.unique(idx)
    if len(idx) == 0:
        raise DataError(f"the frame selection {selection!r} picks no frame of {num_frames}")
    return idx


def select_cameras(names: list[str], wanted: tuple[str, ...] | None) -> list[str]:
    """``names`` restricted to ``wanted`` (dataset order); unknown names are an error."""
    if wanted is None:
        return list(names)
    unknown = [w for w in wanted if w not in names]
    if unknown:
        raise DataError(f"unknown camera '{unknown[0]}' (available: {', '.join(names[:8])}"
                        f"{', ...' if len(names) > 8 else ''})")
    keep = set(wanted)
    return [n for n in names if n in keep]
