"""Dataset format detection and :func:`load_scene`, the one entry point to every reader."""

from __future__ import annotations

import fnmatch
import os
from pathlib import Path
from typing import Iterable

from omg4.data.blender import is_blender, read_blender
from omg4.data.n3dv import is_n3dv, read_n3dv
from omg4.data.options import FrameSelection, LoadOptions
from omg4.data.panoptic import is_panoptic, read_panoptic
from omg4.data.scene import Scene
from omg4.errors import DataError

READERS = {"n3dv": read_n3dv, "blender": read_blender, "panoptic": read_panoptic}
#: Name patterns of the files the readers take from the top of a dataset folder (N3DV videos, poses and
#: points; Blender transforms; Panoptic metadata), and of the images they take from its subfolders.
DATASET_FILES = ("poses_bounds.npy", "points3d.ply", "*.mp4", "transforms_*.json", "*_meta.json", "synth.json")
DATASET_IMAGES = ("*.png", "*.jpg", "*.jpeg")


def is_dataset_file(path: str | os.PathLike, folder: str | os.PathLike) -> bool:
    """Whether a file at ``path`` inside the dataset ``folder`` is one a reader takes (or would take, were it
    created: a new ``camXX.mp4`` becomes an N3DV camera) — :data:`DATASET_FILES` at the top level,
    :data:`DATASET_IMAGES` in subfolders."""
    rel = Path(os.path.relpath(os.path.realpath(os.path.abspath(path)), os.path.realpath(os.path.abspath(folder))))
    patterns = DATASET_FILES if len(rel.parts) == 1 else DATASET_IMAGES
    return any(fnmatch.fnmatch(rel.name.lower(), pattern) for pattern in patterns)


def detect_format(path: str | os.PathLike) -> str:
    """``"panoptic"`` (``train_meta.json``), ``"n3dv"`` (``*.mp4`` videos, or ``poses_bounds.npy``
    without Blender JSONs) or ``"blender"`` (``transforms_*.json``), checked in that order.

    A folder holding both N3DV videos and the official n3v2blender JSONs reads as N3DV (the
    videos go through the frame cache). Raises :class:`DataError` for a missing path, a
    file, an empty folder or a folder of none of these layouts.
    """
    folder = _existing_folder(path)
    if is_panoptic(folder):
        return "panoptic"
    if is_n3dv(folder):
        return "n3dv"
    if is_blender(folder):
        return "blender"
    if not any(folder.iterdir()):
        raise DataError(f"dataset folder {folder} is empty")
    raise DataError(f"no dataset found in {folder} (expected poses_bounds.npy + camXX.mp4, "
                    "transforms_*.json, or train_meta.json)")


def load_scene(path: str | os.PathLike, *, format: str | None = None, downscale: float = 1.0,
               width: int | None = None, frames: FrameSelection = None, cameras: Iterable[str] | None = None,
               background: tuple[float, float, float] = (0.0, 0.0, 0.0), cache_dir: str | os.PathLike | None = None,
               fps: float | None = None, normalize: bool | str = "auto", points_world: str = "auto",
               decode: bool = True, progress: bool = True) -> Scene:
    """Read the dynamic multi-view dataset in ``path`` into a :class:`Scene` in the normalized world.

    Args:
        path: dataset folder (N3DV, D-NeRF/Blender or Panoptic layout; see :func:`detect_format`).
        format: force a reader: ``"n3dv"``, ``"blender"`` or ``"panoptic"``.
        downscale: divide the image size by this factor (``round(W / downscale)``); intrinsics
            follow the actual output size.
        width: explicit output width in pixels (overrides ``downscale``; aspect kept).
        frames: frame indices to keep (``slice``, ``range`` or an iterable of ints; ``None``: all).
            N3DV/Panoptic: the time range becomes that of the kept frames; Blender keeps the
            dataset's time range.
        cameras: camera names to keep (N3DV ``cam05``, Panoptic ``5``, Blender ``train/r_000``);
            ``None``: all. The normalization never depends on this subset.
        background: RGB in [0, 1] that RGBA images are composited on.
        cache_dir: N3DV frame cache folder (default ``$OMG4_CACHE_DIR`` or ``~/.cache/omg4/frames``).
        fps: N3DV frame-rate override (default: the video stream's).
        normalize: ``True``, ``False`` (keep the dataset's world) or ``"auto"``: always for N3DV
            and Panoptic, for Blender only when its poses are not already normalized (see
            :class:`omg4.data.options.LoadOptions`).
        points_world: world of ``points3d.ply`` (see :class:`omg4.data.options.LoadOptions`).
        decode: N3DV: decode the needed video frames into the cache now; ``False`` defers it to
            the first image access (for summaries).
        progress: show progress bars.

    Test views: N3DV ``cam00`` (the first video), Blender ``transforms_test.json``, Panoptic
    ``test_meta.json``.
    """
    folder = _existing_folder(path)
    fmt = format or detect_format(folder)
    if fmt not in READERS:
        raise DataError(f"unknown dataset format '{fmt}' (choose n3dv, blender or panoptic)")
    if isinstance(cameras, str):
        cameras = [cameras]
    opts = LoadOptions(downscale=downscale, width=width, frames=frames,
                       cameras=None if cameras is None else tuple(str(c) for c in cameras), background=background,
                       cache_dir=None if cache_dir is None else Path(cache_dir), fps=fps, normalize=normalize,
                       points_world=points_world, decode=decode, progress=progress)
    scene = READERS[fmt](folder, opts)
    if not scene.train_views and not scene.test_views:
        raise DataError(f"the selection leaves no views in {folder}")
    return scene


def _existing_folder(path: str | os.PathLike) -> Path:
    folder = Path(path)
    if not folder.exists():
        raise DataError(f"dataset folder {folder} does not exist")
    if not folder.is_dir():
        raise DataError(f"{folder} is not a dataset folder")
    return folder
