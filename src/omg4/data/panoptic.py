"""Panoptic reader, Dynamic3DGaussians layout (data §1).

``train_meta.json`` / ``test_meta.json`` hold ``w``, ``h`` and, per frame ``t`` (outer list)
and camera (inner list), ``k`` (3×3 intrinsics), ``w2c`` (4×4 OpenCV world-to-camera),
``fn`` (``"<cam>/<frame>.jpg"`` under ``ims/``) and ``cam_id``. Cameras must be static (each
camera's calibration is the same at every frame, as in CMU Panoptic); they are named by
their id (``"10"``). Frame ``t`` of the lists has ``timestamp = t / 30`` s and the time
range of frames ``t0 … t1`` is ``[t0 / 30, (t1 + 1) / 30]``. The normalization is computed
from all cameras of both files (:mod:`omg4.data.normalize`). Foreground masks (``seg/``)
are not used.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np

from omg4.data.images import image_size, load_image
from omg4.data.normalize import official_normalization
from omg4.data.options import LoadOptions, select_cameras, select_frames
from omg4.data.points import load_initial_points
from omg4.data.scene import Camera, Normalization, Scene, View
from omg4.errors import DataError

PANOPTIC_FPS = 30.0


def is_panoptic(folder: Path) -> bool:
    return (folder / "train_meta.json").exists()


def load_meta(path: Path) -> dict:
    """One ``*_meta.json`` as arrays: ``k`` [T, C, 3, 3], ``w2c`` [T, C, 4, 4], ``fn`` [T][C], ``cam_id`` [C], w, h."""
    try:
        meta = json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError(f"missing {path.name} in {path.parent}") from None
    except (OSError, ValueError) as e:
        raise DataError(f"cannot parse {path}: {e}") from None
    if not isinstance(meta, dict) or not all(k in meta for k in ("k", "w2c", "fn", "cam_id")):
        raise DataError(f"{path} lacks one of the keys k, w2c, fn, cam_id")
    if not meta["fn"]:
        raise DataError(f"{path} has no frames")
    try:
        k = np.asarray(meta["k"], dtype=np.float64)
        w2c = np.asarray(meta["w2c"], dtype=np.float64)
        ids = np.asarray(meta["cam_id"])
        ids = ids[0] if ids.ndim == 2 else ids
    except (TypeError, ValueError) as e:
        raise DataError(f"{path}: k, w2c or cam_id is not a regular array: {e}") from None
    T, C = len(meta["fn"]), len(ids)
    if k.shape != (T, C, 3, 3) or w2c.shape != (T, C, 4, 4) or any(len(f) != C for f in meta["fn"]):
        raise DataError(f"{path}: expected k [T, C, 3, 3], w2c [T, C, 4, 4], fn [T][C] with T={T}, C={C}; "
                        f"got k {k.shape}, w2c {w2c.shape}")
    if not (np.isfinite(k).all() and np.isfinite(w2c).all()):
        raise DataError(f"{path}: camera parameters contain NaN or Inf")
    if not (np.allclose(k, k[:1], rtol=0, atol=1e-6) and np.allclose(w2c, w2c[:1], rtol=0, atol=1e-6)):
        raise DataError(f"{path}: cameras move between frames; only static camera rigs are supported")
    return {"k": k[0], "w2c": w2c[0], "fn": meta["fn"], "cam_id": [str(int(i)) for i in ids],
            "w": meta.get("w"), "h": meta.get("h")}


def read_panoptic(folder: Path, opts: LoadOptions) -> Scene:
    """The Panoptic scene in ``folder`` (see the module docstring)."""
    splits = {"train": load_meta(folder / "train_meta.json")}
    if (folder / "test_meta.json").exists():
        splits["test"] = load_meta(folder / "test_meta.json")
    all_w2c = np.concatenate([m["w2c"] for m in splits.values()])
    norm = Normalization.identity() if opts.normalize is False else official_normalization(np.linalg.inv(all_w2c))
    num_available = min(len(m["fn"]) for m in splits.values())
    frame_ids = select_frames(opts.frames, num_available)
    names = [n for m in splits.values() for n in m["cam_id"]]
    chosen = set(select_cameras(names, opts.cameras))

    views: dict[str, list[View]] = {"train": [], "test": []}
    for split, meta in splits.items():
        for c, name in enumerate(meta["cam_id"]):
            if name not in chosen:
                continue
            files = [folder / "ims" / meta["fn"][f][c] for f in frame_ids]
            missing = [p for p in files if not p.is_file()]
            if missing:
                raise DataError(f"missing image file {missing[0]} ({len(missing)} of camera {name} missing)")
            camera = _camera(name, meta, c, files[0], norm, opts)
            views[split].extend(
                View(camera=camera, timestamp=float(f) / PANOPTIC_FPS, frame_index=int(f),
                     loader=functools.partial(load_image, path, camera.width, camera.height, opts.background))
                for f, path in zip(frame_ids, files))
    points_world = "original" if opts.points_world == "auto" else opts.points_world
    return Scene(train_views=views["train"], test_views=views["test"],
                 time_range=(float(frame_ids[0]) / PANOPTIC_FPS, float(frame_ids[-1] + 1) / PANOPTIC_FPS),
                 normalization=norm, format="panoptic", name=folder.name,
                 initial_points=load_initial_points(folder, norm, points_world), num_frames=len(frame_ids))


def _camera(name: str, meta: dict, c: int, first_image: Path, norm: Normalization, opts: LoadOptions) -> Camera:
    """Camera ``c`` of ``meta`` in the normalized world at the output resolution.

    The intrinsics are at the size of the image files (the first frame's header); if the
    meta's ``w, h`` differ from the files, ``k`` is scaled from ``w, h`` to the files.
    """
    width, height = image_size(first_image)
    meta_w, meta_h = meta["w"] or width, meta["h"] or height
    cam = Camera(K=meta["k"][c].copy(), viewmat=norm.apply_viewmat(meta["w2c"][c]), width=int(meta_w),
                 height=int(meta_h), name=name)
    if (cam.width, cam.height) != (width, height):
        cam = cam.resized(width, height)
    out_w, out_h = opts.output_size(width, height)
    return cam.resized(out_w, out_h) if (out_w, out_h) != (width, height) else cam
