"""The calibrated camera model: COLMAP's ``RADIAL`` (focal length f, principal point, radial distortion k1, k2).

A point at normalized undistorted coordinates (x, y) = (X/Z, Y/Z) is seen at pixel
``u = f·x·d + cx``, ``v = f·y·d + cy`` with ``d = 1 + k1·r² + k2·r⁴``, ``r² = x² + y²``; pixel (i, j) of an
image array covers u ∈ [j, j + 1), v ∈ [i, i + 1) (pixel centres at +0.5, as omg4's cameras and COLMAP's).
"""

from __future__ import annotations

import numpy as np


def distort(x: np.ndarray, y: np.ndarray, k1: float, k2: float) -> tuple[np.ndarray, np.ndarray]:
    """Distorted normalized coordinates of undistorted ones (any equal shapes)."""
    r2 = x * x + y * y
    d = 1.0 + k1 * r2 + k2 * r2 * r2
    return x * d, y * d


def project(points: np.ndarray, K: np.ndarray, distortion: tuple[float, float], w2c: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """``(pixels [N, 2], depth [N])`` of world points [N, 3] in a camera (depth ≤ 0: behind it)."""
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    safe = np.where(np.abs(z) > 1e-12, z, 1e-12)
    xd, yd = distort(cam[:, 0] / safe, cam[:, 1] / safe, *distortion)
    return np.stack([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=1), z


def sample(image: np.ndarray, pixels: np.ndarray, radius: int = 1) -> np.ndarray:
    """Mean colour in [0, 1] of the (2·radius + 1)² pixels around each of ``pixels`` [N, 2] (continuous (u, v)
    coordinates inside the image) of a uint8 image [H, W, 3]."""
    height, width = image.shape[:2]
    cols = np.clip(np.floor(pixels[:, 0]).astype(np.int64), 0, width - 1)
    rows = np.clip(np.floor(pixels[:, 1]).astype(np.int64), 0, height - 1)
    total = np.zeros((len(pixels), 3))
    for dr in range(-radius, radius + 1):
        for dc in range(-radius, radius + 1):
            total += image[np.clip(rows + dr, 0, height - 1), np.clip(cols + dc, 0, width - 1)]
    return total / ((2 * radius + 1) ** 2 * 255.0)


__all__ = ["distort", "project", "sample"]
