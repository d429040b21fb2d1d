"""The normalized world every reader returns (rt4dgs §4.1; docs/architecture.md §3 "The normalized world").

This is the official N3DV preprocessing of Real-Time4DGS (``scripts/n3v2blender.py``, itself
taken from instant-ngp's ``colmap2nerf``), written as one similarity transform
``x_norm = s · (R x + t)`` so that it can be applied to any dataset's cameras and undone:

1. world flip ``P`` (swap the x and y rows, negate z) — colmap2nerf's fixed change of axes;
2. ``R_up``: the smallest rotation taking the normalized sum of the cameras' up vectors
   (−y of the OpenCV camera) to +z;
3. centre: the weighted mean of the closest points between every pair of optical axes
   (pairs ``i < j``, weight ``|d_i × d_j|²``, only pairs with weight > 0.01; each point is
   clamped to lie in front of both cameras) is moved to the origin;
4. scale so that the mean camera distance from the origin is 4.

``R = R_up · P``, ``t = −centre`` (in the rotated frame), ``s = 4 / mean distance``.

:func:`already_normalized` tells whether poses already live in such a world (up +z within
10°, focus within 0.25 of the origin, mean distance in [3, 5]); Blender-format data
(D-NeRF, the n3v2blender output itself) usually does, and Real-Time4DGS uses it as is.

Deviation from the official script (documented fall-backs, never used by N3DV): if no pair
of optical axes passes the weight threshold (one camera, or parallel axes) the centre is the
mean camera centre; if the cameras then all sit at the centre the scale is 1.
"""

from __future__ import annotations

import numpy as np

from omg4.data.scene import Normalization
from omg4.errors import DataError

#: colmap2nerf's world flip: rows 0 and 1 swapped, row 2 negated (a proper rotation).
WORLD_FLIP = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])

#: Pairs of optical axes whose squared sine of the angle is at most this are ignored.
MIN_PAIR_WEIGHT = 0.01

#: Mean camera distance from the origin in the normalized world.
TARGET_DISTANCE = 4.0


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[3, 3] rotation taking direction ``a`` [3] onto ``b`` [3] about their common normal.

    Rodrigues' formula ``I + [v]× + [v]×² (1 − c) / s²`` with ``v = a × b``, ``c = a·b``,
    ``s = |v|`` (colmap2nerf ``rotmat``; the identity when ``a`` ∥ ``b``). Antiparallel
    inputs rotate by π about an axis orthogonal to ``a``.
    """
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(a @ b)
    s2 = float(v @ v)
    if s2 < 1e-20:
        if c > 0:
            return np.eye(3)
        axis = np.cross(a, np.eye(3)[np.argmin(np.abs(a))])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + k + k @ k * ((1.0 - c) / s2)


def axes_focus(origins: np.ndarray, forwards: np.ndarray) -> np.ndarray | None:
    """The point the cameras look at: weighted mean of pairwise closest points of their axes.

    Args:
        origins: [N, 3] camera centres.
        forwards: [N, 3] unit viewing directions.

    Returns:
        [3] point, or ``None`` when no pair has weight ``|d_i × d_j|² > 0.01``.

    For the pair (i, j) the parameters along each axis are
    ``t_i = (o_j − o_i)·(d_j × c) / |c|²`` and ``t_j = (o_j − o_i)·(d_i × c) / |c|²`` with
    ``c = d_i × d_j`` (colmap2nerf ``closest_point_2_lines``, written with the forward
    direction, hence the clamp to ``t ≥ 0``: the point stays in front of both cameras).
    """
    i, j = np.triu_indices(len(origins), k=1)
    da, db = forwards[i], forwards[j]
    c = np.cross(da, db)
    w = np.einsum("pk,pk->p", c, c)
    delta = origins[j] - origins[i]
    # colmap2nerf uses the back direction −d: t_back = det[t, −d_j, c'] with c' = c, so the
    # forward parameters below are its negatives, and its clamp t_back ≤ 0 becomes t ≥ 0.
    ta = np.maximum(np.einsum("pk,pk->p", delta, np.cross(db, c)) / (w + 1e-10), 0.0)
    tb = np.maximum(np.einsum("pk,pk->p", delta, np.cross(da, c)) / (w + 1e-10), 0.0)
    points = 0.5 * (origins[i] + ta[:, None] * da + origins[j] + tb[:, None] * db)
    keep = w > MIN_PAIR_WEIGHT
    if not keep.any():
        return None
    return (points[keep] * w[keep, None]).sum(0) / w[keep].sum()


def already_normalized(camtoworlds: np.ndarray, max_tilt_deg: float = 10.0, max_offset: float = 0.25,
                       distance_range: tuple[float, float] = (3.0, 5.0)) -> bool:
    """Whether OpenCV camera-to-world poses [N, 4, 4] already satisfy the normalized-world rules.

    Checks that the summed camera up vector (−y) is within ``max_tilt_deg`` of +z, that the
    optical axes' focus point (:func:`axes_focus`; the mean centre when undefined) is within
    ``max_offset`` of the origin, and that the mean camera distance lies in ``distance_range``.
    """
    c2w = np.asarray(camtoworlds, dtype=np.float64)
    up = (-c2w[:, :3, 1]).sum(0)
    norm = np.linalg.norm(up)
    if norm < 1e-12 or up[2] / norm < np.cos(np.radians(max_tilt_deg)):
        return False
    centers = c2w[:, :3, 3]
    forwards = c2w[:, :3, 2] / np.linalg.norm(c2w[:, :3, 2], axis=1, keepdims=True)
    focus = axes_focus(centers, forwards)
    focus = centers.mean(0) if focus is None else focus
    mean_dist = float(np.linalg.norm(centers, axis=1).mean())
    return bool(np.linalg.norm(focus) <= max_offset and distance_range[0] <= mean_dist <= distance_range[1])


def official_normalization(camtoworlds: np.ndarray) -> Normalization:
    """The normalization of ``n3v2blender.py`` for cameras given as OpenCV camera-to-world.

    Args:
        camtoworlds: [N, 4, 4] (or [N, 3, 4]) OpenCV camera-to-world matrices of every camera
            of the dataset (all splits, independent of any camera subset the user picks, so
            that a subset never changes the world).

    Returns:
        The :class:`Normalization` ``x_norm = s · (R x + t)``.
    """
    c2w = np.asarray(camtoworlds, dtype=np.float64)
    if c2w.ndim != 3 or c2w.shape[1:] not in ((4, 4), (3, 4)) or len(c2w) == 0:
        raise DataError(f"expected [N, 4, 4] camera poses, got shape {c2w.shape}")
    if not np.isfinite(c2w).all():
        raise DataError("camera poses contain NaN or Inf")
    rot = c2w[:, :3, :3]
    centers = c2w[:, :3, 3]
    up = WORLD_FLIP @ (-rot[:, :, 1]).sum(0)
    if np.linalg.norm(up) < 1e-12:
        raise DataError("camera up vectors cancel out; cannot find the up axis")
    R = rotation_between(up, np.array([0.0, 0.0, 1.0])) @ WORLD_FLIP
    origins = centers @ R.T
    forwards = rot[:, :, 2] @ R.T
    forwards /= np.linalg.norm(forwards, axis=1, keepdims=True)
    focus = axes_focus(origins, forwards)
    if focus is None:
        focus = origins.mean(0)
    mean_dist = float(np.linalg.norm(origins - focus, axis=1).mean())
    scale = TARGET_DISTANCE / mean_dist if mean_dist > 1e-12 else 1.0
    return Normalization(scale=scale, rotation=R, translation=-focus)
