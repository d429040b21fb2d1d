"""Removing a calibrated camera's lens distortion: its frames resampled to a pinhole camera of the same size with
a centred principal point, as the N3DV layout (one focal length per camera in ``poses_bounds.npy``) needs.

The pinhole's focal length is the smallest (the widest view) that keeps every output pixel inside the source
image, so no black border enters the dataset; an output pixel takes the bilinear interpolation of the source at its distorted
position (:mod:`omg4.prepare.camera_model`).
"""

from __future__ import annotations

import numpy as np
import torch

from omg4.prepare.camera_model import distort


def _source_pixels(K: np.ndarray, distortion: tuple[float, float], focal: float, u: np.ndarray, v: np.ndarray,
                   width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Source coordinates (u, v) of output pixel positions ``u``, ``v`` of the pinhole with ``focal``."""
    x, y = (u - width / 2) / focal, (v - height / 2) / focal
    xd, yd = distort(x, y, *distortion)
    return K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]


def pinhole_focal(K: np.ndarray, distortion: tuple[float, float], width: int, height: int) -> float:
    """The smallest focal length (the widest view) whose border pixel centres all map within the source's pixel
    centres (between a quarter and four times the source's focal length)."""
    border = np.concatenate([np.stack([np.arange(width) + 0.5, np.full(width, 0.5)], 1),
                             np.stack([np.arange(width) + 0.5, np.full(width, height - 0.5)], 1),
                             np.stack([np.full(height, 0.5), np.arange(height) + 0.5], 1),
                             np.stack([np.full(height, width - 0.5), np.arange(height) + 0.5], 1)])

    def inside(focal: float) -> bool:
        su, sv = _source_pixels(K, distortion, focal, border[:, 0], border[:, 1], width, height)
        tolerance = 1e-9 * width  # pixel centres onto pixel centres (no distortion: the focal length itself)
        return bool(np.all((su >= 0.5 - tolerance) & (su <= width - 0.5 + tolerance)
                           & (sv >= 0.5 - tolerance) & (sv <= height - 0.5 + tolerance)))

    low, high = 0.25 * K[0, 0], 4.0 * K[0, 0]
    if inside(low):
        return low
    for _ in range(60):  # bisection: ``high`` always sees only source pixels
        middle = 0.5 * (low + high)
        low, high = (low, middle) if inside(middle) else (middle, high)
    return high


def pinhole_K(focal: float, width: int, height: int) -> np.ndarray:
    """[3, 3] intrinsics of a pinhole with a centred principal point."""
    return np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])


class Undistorter:
    """Resamples one camera's frames (uint8 [H, W, 3]) to the pinhole ``K`` (:func:`pinhole_K` of
    :func:`pinhole_focal`)."""

    def __init__(self, K: np.ndarray, distortion: tuple[float, float], width: int, height: int):
        self.width, self.height = width, height
        self.focal = pinhole_focal(K, distortion, width, height)
        self.K = pinhole_K(self.focal, width, height)
        v, u = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
        su, sv = _source_pixels(K, distortion, self.focal, u, v, width, height)
        # grid_sample's normalized coordinates with align_corners=False: −1 and 1 are the image's outer edges
        grid = np.stack([2 * su / width - 1, 2 * sv / height - 1], axis=-1)
        self.grid = torch.as_tensor(grid, dtype=torch.float32)[None]

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        image = torch.from_numpy(np.array(frame, dtype=np.float32)).permute(2, 0, 1)[None]
        out = torch.nn.functional.grid_sample(image, self.grid, mode="bilinear", padding_mode="border",
                                              align_corners=False)
        return out[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy()


__all__ = ["Undistorter", "pinhole_K", "pinhole_focal"]
