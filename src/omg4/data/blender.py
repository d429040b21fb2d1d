"""D-NeRF / Blender reader: ``transforms_{train,val,test}.json`` (rt4dgs §4.2, §4.4).

* Frames: ``file_path`` (``.png`` appended when it has no suffix), ``transform_matrix``
  (OpenGL camera-to-world; columns 1, 2 are negated to OpenCV), ``time``  (0 when absent).
* Intrinsics, per frame or top level (per frame wins): ``fl_x``, ``fl_y``, ``cx``, ``cy``
  (``cx, cy`` default to the image centre), with ``w, h`` (default: the image file's size);
  else ``camera_angle_x``: ``fx = fy = W / (2 tan(angle / 2))``, ``cx = W / 2``, ``cy = H / 2``.
* RGBA images are composited on the chosen background (without the official code's second
  multiplication by alpha).
* Splits: train = ``transforms_train.json``; test = ``transforms_test.json``, else
  ``transforms_val.json`` when there is no test file (val is otherwise unused, as in D-NeRF).
* Frames: the distinct timestamps of train and test, sorted, numbered 0 … F−1
  (``frame_index``; ``num_frames = F``). Time range: ``(0, 1)`` when every time lies in
  [0, 1] (D-NeRF); otherwise ``(min(0, t_min), t_max + step)`` with ``step`` the median gap
  between distinct times (seconds-valued N3DV exports give ``(0, 10)``).
* Normalization (``normalize="auto"``): none when the poses already are in a normalized
  world (D-NeRF, n3v2blender exports: Real-Time4DGS trains in that world), else the
  official N3DV normalization (:mod:`omg4.data.normalize`).
* Cameras are named by ``file_path`` without suffix (``train/r_000``), one per frame.
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import numpy as np

from omg4.data.images import image_size, load_image
from omg4.data.normalize import already_normalized, official_normalization
from omg4.data.options import LoadOptions, select_cameras, select_frames
from omg4.data.points import load_initial_points
from omg4.data.scene import Camera, Normalization, Scene, View, is_orthonormal
from omg4.errors import DataError

SPLIT_FILES = {"train": "transforms_train.json", "val": "transforms_val.json", "test": "transforms_test.json"}
_OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def is_blender(folder: Path) -> bool:
    return any((folder / f).exists() for f in SPLIT_FILES.values())


def load_transforms(path: Path) -> dict:
    """One ``transforms_*.json``, checked to hold a non-empty ``frames`` list."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise DataError(f"cannot parse {path}: {e}") from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise DataError(f"{path} has no frames")
    return data


def frame_records(folder: Path, data: dict, json_name: str) -> list[dict]:
    """Per frame: ``name``, ``path``, ``c2w`` [4, 4] OpenCV, ``time``, native ``K`` [3, 3], ``w``, ``h``."""
    records = []
    for k, frame in enumerate(data["frames"]):
        try:
            rel = str(frame["file_path"])
            c2w = np.asarray(frame["transform_matrix"], dtype=np.float64).reshape(4, 4) @ _OPENGL_TO_OPENCV
            time = float(frame.get("time", 0.0))
        except (KeyError, TypeError, ValueError) as e:
            raise DataError(f"{json_name}: frame {k} lacks a valid file_path or transform_matrix ({e})") from None
        if not (np.isfinite(c2w).all() and math.isfinite(time)):
            raise DataError(f"{json_name}: frame {k} has NaN or Inf in its pose or time")
        if not is_orthonormal(c2w[:3, :3]) or not np.allclose(c2w[3], [0, 0, 0, 1]):
            raise DataError(f"{json_name}: frame {k}'s transform_matrix is not a rigid camera pose")
        path = folder / rel
        if not path.suffix:
            path = path.with_name(path.name + ".png")
        w, h = image_size(path)
        try:
            K = _intrinsics(frame, data, w, h, json_name, k)
        except (TypeError, ValueError) as e:
            raise DataError(f"{json_name}: frame {k} has non-numeric intrinsics ({e})") from None
        name = rel[2:] if rel.startswith("./") else rel
        records.append({"name": str(Path(name).with_suffix("")), "path": path, "c2w": c2w, "time": time,
                        "K": K, "w": w, "h": h})
    return records


def _intrinsics(frame: dict, top: dict, w: int, h: int, json_name: str, k: int) -> np.ndarray:
    """[3, 3] K at the image file's size ``w × h`` (see the module docstring)."""
    def get(key):
        return frame.get(key, top.get(key))

    meta_w, meta_h = float(get("w") or w), float(get("h") or h)
    if get("fl_x") is not None:
        fx = float(get("fl_x"))
        fy = float(get("fl_y") if get("fl_y") is not None else fx)
        cx = float(get("cx") if get("cx") is not None else meta_w / 2)
        cy = float(get("cy") if get("cy") is not None else meta_h / 2)
    elif get("camera_angle_x") is not None:
        angle = float(get("camera_angle_x"))
        if not 0.0 < angle < math.pi:
            raise DataError(f"{json_name}: frame {k}'s camera_angle_x {angle} is not an angle in (0, π)")
        fx = fy = 0.5 * meta_w / math.tan(0.5 * angle)
        cx, cy = meta_w / 2, meta_h / 2
    else:
        raise DataError(f"{json_name}: frame {k} has no intrinsics (fl_x/fl_y/cx/cy or camera_angle_x)")
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy, meta_w, meta_h)) or min(fx, fy, meta_w, meta_h) <= 0:
        raise DataError(f"{json_name}: frame {k} has invalid intrinsics (focal lengths and sizes must be positive)")
    sx, sy = w / meta_w, h / meta_h
    return np.array([[fx * sx, 0.0, cx * sx], [0.0, fy * sy, cy * sy], [0.0, 0.0, 1.0]])


def time_range_of(times: np.ndarray) -> tuple[float, float]:
    """``(0, 1)`` for times in [0, 1], else ``(min(0, t_min), t_max + median step)``."""
    if times.min() >= 0.0 and times.max() <= 1.0:
        return 0.0, 1.0
    step = float(np.median(np.diff(times))) if len(times) > 1 else 1.0
    return float(min(0.0, times.min())), float(times.max() + step)


def read_blender(folder: Path, opts: LoadOptions) -> Scene:
    """The Blender / D-NeRF scene in ``folder`` (see the module docstring)."""
    if not (folder / SPLIT_FILES["train"]).exists():
        raise DataError(f"missing {SPLIT_FILES['train']} in {folder}")
    test_file = SPLIT_FILES["test"] if (folder / SPLIT_FILES["test"]).exists() else SPLIT_FILES["val"]
    records = {"train": frame_records(folder, load_transforms(folder / SPLIT_FILES["train"]), SPLIT_FILES["train"])}
    if (folder / test_file).exists():
        records["test"] = frame_records(folder, load_transforms(folder / test_file), test_file)
    all_recs = [r for recs in records.values() for r in recs]
    c2w = np.stack([r["c2w"] for r in all_recs])
    if opts.normalize is True or (opts.normalize == "auto" and not already_normalized(c2w)):
        norm = official_normalization(c2w)
    else:
        norm = Normalization.identity()
    times = np.unique([r["time"] for r in all_recs])
    frame_ids = select_frames(opts.frames, len(times))
    names = [r["name"] for r in all_recs]
    chosen = set(select_cameras(names, opts.cameras))
    kept_frames = set(frame_ids.tolist())

    views: dict[str, list[View]] = {"train": [], "test": []}
    for split, recs in records.items():
        for r in recs:
            f = int(np.searchsorted(times, r["time"]))
            if r["name"] not in chosen or f not in kept_frames:
                continue
            cam = Camera(K=r["K"], viewmat=norm.apply_viewmat(np.linalg.inv(r["c2w"])), width=r["w"],
                         height=r["h"], name=r["name"])
            out_w, out_h = opts.output_size(r["w"], r["h"])
            if (out_w, out_h) != (r["w"], r["h"]):
                cam = cam.resized(out_w, out_h)
            views[split].append(View(camera=cam, timestamp=r["time"], frame_index=f,
                                     loader=functools.partial(load_image, r["path"], out_w, out_h, opts.background)))
    points_world = "original" if opts.points_world == "auto" else opts.points_world
    return Scene(train_views=views["train"], test_views=views["test"], time_range=time_range_of(times),
                 normalization=norm, format="blender", name=folder.name,
                 initial_points=load_initial_points(folder, norm, points_world), num_frames=len(frame_ids))
