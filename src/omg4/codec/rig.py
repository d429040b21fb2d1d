"""The capture's camera rig in an ``.omg4`` file (``meta.rig``, docs/file-format.md §2; beyond the paper).

``compress`` records where the capture looked from, so a viewer opens a file at its first test camera without
the dataset (without it, only an orbit around the model's bounds is known, which mostly shows floaters):

    {"cameras": [{"name": str, "width": W, "height": H, "K": [fx, fy, cx, cy], "pose": [12 numbers]}, ...],
     "test": T}

``pose`` is the world → camera matrix's top three rows (row-major, OpenCV axes, the normalized world the model
lives in); the first ``T`` cameras are the held-out test cameras (test cameras first, as ``Scene.cameras``
orders them). Numbers keep 7 significant digits: 21 N3DV cameras take about 2 KB of JSON, a few hundred bytes
once the header is deflated. Files without a rig keep the older fallback.

A reader validates a rig like every part of the header (:func:`check_rig`): at most :data:`MAX_CAMERAS`
cameras, names of at most 64 characters, whole image sizes in [1, 16384], finite intrinsics with
positive focal lengths, a finite pose whose rotation is orthonormal within 10⁻³ — anything else is a one-line
:class:`~omg4.errors.CorruptFileError`.
"""

from __future__ import annotations

import math

import numpy as np

from omg4.errors import CorruptFileError

MAX_CAMERAS = 1024
MAX_NAME = 64
MAX_SIDE = 16384  # pixels, omg4.data.scene.MAX_IMAGE_SIDE
DIGITS = 7


def _rounded(values) -> list[float]:
    return [float(f"{float(v):.{DIGITS}g}") for v in values]


def rig_json(cameras: list, test: int) -> dict:
    """The ``meta.rig`` of ``cameras`` (anything with ``name``, ``K``, ``viewmat``, ``width`` and ``height``, such as
    :class:`~omg4.data.scene.Camera`; the first ``test`` held out)."""
    return {"cameras": [{"name": c.name[:MAX_NAME], "width": int(c.width), "height": int(c.height),
                         "K": _rounded([c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2]]),
                         "pose": _rounded(np.asarray(c.viewmat)[:3].ravel())} for c in cameras[:MAX_CAMERAS]],
            "test": min(int(test), len(cameras), MAX_CAMERAS)}


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def check_rig(rig: object) -> None:
    """Raise :class:`CorruptFileError` unless ``rig`` is a valid ``meta.rig`` (module docstring)."""
    cameras = rig.get("cameras") if isinstance(rig, dict) else None
    if not (isinstance(cameras, list) and 1 <= len(cameras) <= MAX_CAMERAS and isinstance(rig.get("test"), int)
            and not isinstance(rig["test"], bool) and 0 <= rig["test"] <= len(cameras)):
        raise CorruptFileError(f"invalid camera rig (1 to {MAX_CAMERAS} cameras and a test count)")
    for i, c in enumerate(cameras):
        ok = (isinstance(c, dict) and isinstance(c.get("name"), str) and len(c["name"]) <= MAX_NAME
              and all(type(c.get(k)) is int and 1 <= c[k] <= MAX_SIDE for k in ("width", "height"))
              and isinstance(c.get("K"), list) and len(c["K"]) == 4 and all(map(_number, c["K"]))
              and c["K"][0] > 0 and c["K"][1] > 0
              and isinstance(c.get("pose"), list) and len(c["pose"]) == 12 and all(map(_number, c["pose"])))
        if not ok:
            raise CorruptFileError(f"invalid camera {i} in the camera rig")
        rotation = np.asarray(c["pose"], np.float64).reshape(3, 4)[:, :3]
        with np.errstate(over="ignore", invalid="ignore"):  # a forged huge entry overflows: refused below
            orthonormal = np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-3)
        if not orthonormal:
            raise CorruptFileError(f"camera {i} of the camera rig has no rotation in its pose")


def rig_cameras(meta: dict) -> list[dict] | None:
    """The rig's cameras in the ``CAM.json`` layout (``{name, K 3×3, viewmat 4×4, width, height}``, what
    :meth:`omg4.data.scene.Camera.from_json` reads; test cameras first) of a file's ``meta``, or None for a file
    without one."""
    rig = meta.get("rig") if isinstance(meta, dict) else None
    if rig is None:
        return None
    check_rig(rig)
    cameras = []
    for c in rig["cameras"]:
        fx, fy, cx, cy = c["K"]
        viewmat = np.eye(4)
        viewmat[:3] = np.asarray(c["pose"], np.float64).reshape(3, 4)
        cameras.append({"name": c["name"], "K": [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]],
                        "viewmat": viewmat.tolist(), "width": c["width"], "height": c["height"]})
    return cameras


__all__ = ["MAX_CAMERAS", "check_rig", "rig_cameras", "rig_json"]
