"""Camera paths from a file: nerfstudio's ``camera_path.json`` (what its viewer's render panel exports).

The file holds ``render_width``, ``render_height`` and ``camera_path``: one entry per frame with
``camera_to_world`` (16 numbers, a row-major 4×4 matrix with OpenGL camera axes: x right, y up, z backward)
and ``fov`` (the vertical field of view in degrees, a three.js perspective camera's), and optionally
``render_time`` (the frame's time as a fraction of the clip, 0 to 1; every entry or none) and a top-level
``fps``. Poses are read in the model's normalized world (the world ``omg4 view`` and ``omg4 info --json``
show), turned into OpenCV cameras (x right, y down, z forward) with square pixels and a centred principal point.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omg4.data.scene import Camera, world_to_camera
from omg4.errors import OMG4Error

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0])
"""Camera axes of OpenGL (y up, z backward) to those of OpenCV (y down, z forward)."""


@dataclass
class FileCameraPath:
    """A camera path read from a file.

    Attributes:
        cameras: one per frame, OpenCV convention.
        times: each frame's time as a fraction of the clip (0 to 1), or None when the file gives none.
        fps: the file's frame rate, or None.
    """

    cameras: list[Camera]
    times: list[float] | None
    fps: float | None


def read_camera_path(path: str | os.PathLike) -> FileCameraPath:
    """The cameras of a nerfstudio ``camera_path.json``; anything else is a one-line error naming the file."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise OMG4Error(f"camera path {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise OMG4Error(f"cannot read the camera path {path} ({getattr(exc, 'strerror', None) or exc})") from None
    except ValueError as exc:
        raise OMG4Error(f"{path}: not JSON ({exc})") from None
    try:
        return _parse(data)
    except (KeyError, TypeError, ValueError) as exc:
        detail = f"no {exc}" if isinstance(exc, KeyError) else str(exc)
        raise OMG4Error(f"{path}: not a nerfstudio camera path ({detail})") from None


def _parse(data: dict) -> FileCameraPath:
    if not isinstance(data, dict):
        raise TypeError("the file holds no JSON object")
    width, height = _size(data["render_width"]), _size(data["render_height"])
    entries = data["camera_path"]
    if not isinstance(entries, list) or not entries:
        raise ValueError("camera_path must be a non-empty list")
    cameras = [_camera(entry, width, height, k) for k, entry in enumerate(entries)]
    timed = ["render_time" in entry for entry in entries]
    if any(timed) and not all(timed):
        raise ValueError("render_time must be given for every camera or for none")
    times = [_fraction(entry["render_time"], k) for k, entry in enumerate(entries)] if all(timed) else None
    fps = data.get("fps")
    if fps is not None and not (_is_number(fps) and 0 < fps <= 1000):
        raise ValueError(f"fps must be a number in (0, 1000], got {fps!r}")
    return FileCameraPath(cameras, times, None if fps is None else float(fps))


def _camera(entry: dict, width: int, height: int, k: int) -> Camera:
    values = entry["camera_to_world"]
    if not (isinstance(values, list) and len(values) in (12, 16) and all(_is_number(v) for v in values)):
        raise ValueError(f"camera {k}: camera_to_world must be 16 (or 12) finite numbers")
    c2w = np.asarray(values, dtype=np.float64).reshape(-1, 4)[:3]
    rotation = c2w[:, :3]
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-3) or np.linalg.det(rotation) < 0:
        raise ValueError(f"camera {k}: camera_to_world is not a rotation and a translation")
    fov = entry["fov"]
    if not (_is_number(fov) and 0 < fov < 180):
        raise ValueError(f"camera {k}: fov must be a vertical field of view in (0, 180) degrees, got {fov!r}")
    focal = 0.5 * height / math.tan(math.radians(fov) / 2)
    K = np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    return Camera(K=K, viewmat=world_to_camera(rotation @ OPENGL_TO_OPENCV, c2w[:, 3]), width=width, height=height,
                  name=f"path{k:04d}")


def _size(value) -> int:
    if not (_is_number(value) and float(value).is_integer() and 1 <= value <= 16384):
        raise ValueError(f"render sizes must be whole numbers of pixels in [1, 16384], got {value!r}")
    return int(value)


def _fraction(value, k: int) -> float:
    if not (_is_number(value) and 0.0 <= value <= 1.0):
        raise ValueError(f"camera {k}: render_time must be a fraction of the clip in [0, 1], got {value!r}")
    return float(value)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


__all__ = ["FileCameraPath", "read_camera_path"]
