"""The scene model every reader returns: cameras, timed views and the normalized world.

Conventions (fixed; docs/architecture.md §3): OpenCV cameras (x right, y down, z forward), ``viewmat`` is
the 4×4 world-to-camera matrix, ``K`` is 3×3 in pixels at the image's actual resolution,
pixel centres at +0.5. Every reader returns its scene in a normalized world (up axis +z,
centred, mean camera distance 4) and records the transform in :class:`Normalization`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from omg4.errors import DataError


MAX_IMAGE_SIDE = 16384
MAX_PIXELS = 1 << 26  # 8192 x 8192: what one rendered image may hold


def fits_render_limits(width: int, height: int) -> bool:
    """Whether one image of ``width × height`` fits the limits (:data:`MAX_IMAGE_SIDE` a side, :data:`MAX_PIXELS`)."""
    return max(width, height) <= MAX_IMAGE_SIDE and width * height <= MAX_PIXELS


def is_orthonormal(matrix: np.ndarray, tol: float = 1e-3) -> bool:
    """Whether the square ``matrix`` is finite and ``M Mᵀ`` is the identity within ``tol`` (a rotation or a
    reflection)."""
    m = np.asarray(matrix, dtype=np.float64)
    return bool(np.isfinite(m).all() and np.abs(m @ m.T - np.eye(m.shape[0])).max() <= tol)


def look_at_viewmat(center: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """[4, 4] OpenCV world-to-camera matrix of a camera at ``center`` looking at ``target``.

    Camera axes (the conventions above): x right = fwd × up, y down = fwd × right, z forward.
    """
    fwd = (target - center) / np.linalg.norm(target - center)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])  # rows: camera axes in world coordinates
    viewmat = np.eye(4)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = -R @ center
    return viewmat


def world_to_camera(rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
    """[4, 4] world-to-camera matrix of a camera whose camera-to-world rotation is ``rotation`` [3, 3] (columns:
    the camera's x, y, z axes in the world) and whose centre is ``position`` [3]."""
    viewmat = np.eye(4)
    viewmat[:3, :3] = np.asarray(rotation).T
    viewmat[:3, 3] = -np.asarray(rotation).T @ np.asarray(position)
    return viewmat


@dataclass(frozen=True)
class Camera:
    """A pinhole camera in the normalized world.

    Attributes:
        K: [3, 3] intrinsics in pixels at (width, height).
        viewmat: [4, 4] world-to-camera (OpenCV) matrix.
        width, height: image size in pixels.
        name: camera identifier (``cam00``, ``r_000``, ``10``...).
    """

    K: np.ndarray
    viewmat: np.ndarray
    width: int
    height: int
    name: str = ""

    def __post_init__(self):
        label = f"camera {self.name!r}" if self.name else "camera"
        if not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 1
                   for v in (self.width, self.height)):
            raise DataError(f"{label}: image size {self.width}x{self.height} is not a positive size in pixels")
        K, viewmat = np.asarray(self.K), np.asarray(self.viewmat)
        if K.shape != (3, 3) or viewmat.shape != (4, 4) or not (np.isfinite(K).all() and np.isfinite(viewmat).all()):
            raise DataError(f"{label}: K must be a finite 3x3 and viewmat a finite 4x4 matrix")

    def check_renderable(self) -> "Camera":
        """This camera, after checking that one image of its size fits the limits (:data:`MAX_IMAGE_SIDE` a side,
        :data:`MAX_PIXELS` in all); raises :class:`DataError` otherwise."""
        if not fits_render_limits(self.width, self.height):
            raise DataError(f"camera image size {self.width}x{self.height} exceeds {MAX_IMAGE_SIDE} pixels a side "
                            f"or {MAX_PIXELS} pixels")
        return self

    @property
    def center(self) -> np.ndarray:
        """[3] camera centre in world coordinates."""
        R, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -R.T @ t

    @property
    def camtoworld(self) -> np.ndarray:
        """[4, 4] camera-to-world matrix."""
        return np.linalg.inv(self.viewmat)

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera at another resolution (intrinsics scaled per axis)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, :] *= sx
        K[1, :] *= sy
        K[2, :] = (0.0, 0.0, 1.0)
        return Camera(K=K, viewmat=self.viewmat.copy(), width=int(width), height=int(height), name=self.name)

    def to_json(self) -> dict:
        """``{name, K, viewmat, width, height}`` with plain lists (the ``CAM.json`` layout)."""
        return {
            "name": self.name,
            "K": np.asarray(self.K, dtype=float).tolist(),
            "viewmat": np.asarray(self.viewmat, dtype=float).tolist(),
            "width": int(self.width),
            "height": int(self.height),
        }

    @staticmethod
    def from_json(d: dict) -> "Camera":
        """Inverse of :meth:`to_json`; ``name`` is optional."""
        K = np.asarray(d["K"], dtype=np.float64).reshape(3, 3)
        viewmat = np.asarray(d["viewmat"], dtype=np.float64).reshape(4, 4)
        width, height = d["width"], d["height"]
        if not all(isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
                   and float(v).is_integer() for v in (width, height)):
            raise DataError(f"camera width and height must be whole numbers, got {width!r} x {height!r}")
        camera = Camera(K=K, viewmat=viewmat, width=int(width), height=int(height), name=str(d.get("name", "")))
        return camera.check_renderable()


@dataclass
class View:
    """One training or test image: a camera at a timestamp, its image loaded lazily.

    Attributes:
        camera: the camera.
        timestamp: time in the dataset's units (N3DV: seconds; D-NeRF: [0, 1]).
        frame_index: index of the frame in its sequence.
        loader: returns the image as float32 [H, W, 3] in [0, 1].
    """

    camera: Camera
    timestamp: float
    frame_index: int
    loader: Callable[[], np.ndarray] = field(repr=False)

    def image(self) -> np.ndarray:
        """float32 [H, W, 3] in [0, 1] at the camera's resolution."""
        return self.loader()


@dataclass(frozen=True)
class Normalization:
    """Similarity transform from the dataset's world to the normalized world.

    ``x_norm = scale * (rotation @ x_orig + translation)``.
    """

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    @staticmethod
    def identity() -> "Normalization":
        return Normalization(1.0, np.eye(3), np.zeros(3))

    def apply_points(self, x: np.ndarray) -> np.ndarray:
        """Map points [..., 3] from the original world to the normalized world."""
        return self.scale * (x @ self.rotation.T + self.translation)

    def invert_points(self, x: np.ndarray) -> np.ndarray:
        """Map points [..., 3] from the normalized world back to the original world."""
        return (x / self.scale - self.translation) @ self.rotation

    def apply_viewmat(self, viewmat: np.ndarray) -> np.ndarray:
        """World-to-camera [4, 4] of the original world → of the normalized world.

        Camera coordinates are scaled by ``scale`` too, which leaves every projection
        unchanged and keeps the rotation block orthonormal.
        """
        Rc, tc = viewmat[:3, :3], viewmat[:3, 3]
        out = np.eye(4)
        out[:3, :3] = Rc @ self.rotation.T
        out[:3, 3] = self.scale * (tc - out[:3, :3] @ self.translation)
        return out

    def to_json(self) -> dict:
        return {
            "scale": float(self.scale),
            "rotation": np.asarray(self.rotation, dtype=float).tolist(),
            "translation": np.asarray(self.translation, dtype=float).tolist(),
        }

    @staticmethod
    def from_json(d: dict) -> "Normalization":
        """Inverse of :meth:`to_json`. Raises ValueError (or KeyError/TypeError for a malformed dict) unless the
        scale is finite and positive, the rotation orthonormal (to 10⁻³) and the translation finite."""
        scale = float(d["scale"])
        rotation = np.asarray(d["rotation"], dtype=np.float64).reshape(3, 3)
        translation = np.asarray(d["translation"], dtype=np.float64).reshape(3)
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"scale {scale} is not a positive number")
        if not is_orthonormal(rotation):
            raise ValueError("the rotation is not orthonormal")
        if not np.isfinite(translation).all():
            raise ValueError("the translation is not finite")
        return Normalization(scale, rotation, translation)


@dataclass
class PointCloud:
    """Initial points: positions [M, 3] in the normalized world and colours [M, 3] in [0, 1]."""

    xyz: np.ndarray
    rgb: np.ndarray


SPLITS = ("test", "train")
"""The view splits of a :class:`Scene`: the held-out test cameras and the training cameras."""


@dataclass
class Scene:
    """A dynamic multi-view scene in the normalized world.

    Attributes:
        train_views, test_views: the views of each split.
        time_range: (t0, t1) in the dataset's time units.
        normalization: original world → normalized world.
        format: reader that produced it (``n3dv``, ``blender``, ``panoptic``).
        name: the dataset folder's name.
        initial_points: points from ``points3d.ply`` when the data has it.
    """

    train_views: list[View]
    test_views: list[View]
    time_range: tuple[float, float]
    normalization: Normalization
    format: str
    name: str = ""
    initial_points: PointCloud | None = None
    num_frames: int = 0

    @property
    def duration(self) -> float:
        return float(self.time_range[1] - self.time_range[0])

    def split_views(self, split: str) -> list[View]:
        """The views of ``split``, one of :data:`SPLITS`."""
        if split not in SPLITS:
            raise DataError(f"unknown split '{split}' (choose from {', '.join(SPLITS)})")
        return self.test_views if split == "test" else self.train_views

    def train_cameras(self) -> list[Camera]:
        """The distinct training cameras, in first-seen order."""
        return _distinct_cameras(self.train_views)

    def test_cameras(self) -> list[Camera]:
        """The distinct test cameras, in first-seen order."""
        return _distinct_cameras(self.test_views)

    def cameras(self) -> list[Camera]:
        """The distinct cameras, test cameras first (presets and camera paths start at the held-out view)."""
        return self.test_cameras() + self.train_cameras()

    def first_frame_views(self) -> list[View]:
        """The training views of the first frame, one per camera (the first seen kept); the
        frame the official initialization reconstructs (rt4dgs §3.5)."""
        if not self.train_views:
            raise DataError("the scene has no training views")
        first = min(v.frame_index for v in self.train_views)
        views: dict[str, View] = {}
        for v in self.train_views:
            if v.frame_index == first:
                views.setdefault(v.camera.name or str(id(v.camera)), v)
        return list(views.values())

    @property
    def extent(self) -> float:
        """Scene extent: 1.1 × the largest distance of a training camera centre from their mean.

        Real-Time4DGS ``getNerfppNorm`` (rt4dgs §4.3); learning rates scale with it.
        """
        centers = np.stack([c.center for c in self.train_cameras()])
        radius = np.linalg.norm(centers - centers.mean(0), axis=1).max()
        return float(1.1 * max(radius, 1e-6))


def _distinct_cameras(views: list[View]) -> list[Camera]:
    seen: dict[str, Camera] = {}
    for v in views:
        key = v.camera.name or str(id(v.camera))
        seen.setdefault(key, v.camera)
    return list(seen.values())
