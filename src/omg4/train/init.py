"""Initial point clouds for baseline training (rt4dgs §3.5).

``auto`` uses the data's ``points3d.ply`` when present, else plane-sweep stereo for
multi-view video, else random points inside the cameras' common view volume
(:func:`omg4.data.random_initial_points`); ``rays`` places
coloured points along the first frame's training rays (:func:`ray_initial_points`);
``mvs`` runs plane-sweep stereo on the first frame (:mod:`omg4.train.plane_sweep`);
``colmap`` triangulates the first frame with pycolmap.
"""

from __future__ import annotations

import logging
from typing import Callable

import numpy as np

from omg4.data import random_initial_points
from omg4.data.scene import PointCloud, Scene
from omg4.device import resolve_device
from omg4.errors import DataError, OMG4Error
from omg4.train.config import TrainConfig
from omg4.train.plane_sweep import plane_sweep_points
from omg4.train.triangulate import triangulate_first_frame

logger = logging.getLogger(__name__)


def initial_points(scene: Scene, mode: str, cfg: TrainConfig, log: Callable[[str], None] | None = None) -> PointCloud:
    """The initial points for ``mode``, one of :data:`INIT_MODES`."""
    if mode not in INIT_MODES:
        raise OMG4Error(f"unknown initialization '{mode}' (choose from {', '.join(INIT_MODES)})")
    return INIT_MODES[mode](scene, cfg, log or logger.info)


def auto_initialization(scene: Scene) -> str:
    """What ``--init auto`` starts ``scene`` from: ``"points3d.ply"`` (the data's points), ``"mvs"`` (plane-sweep
    stereo, when the first frame has at least three training cameras: multi-view video) or ``"random"`` (a
    monocular scene such as D-NeRF, as the official code does)."""
    if scene.initial_points is not None:
        return "points3d.ply"
    return "mvs" if len(scene.first_frame_views()) >= 3 else "random"


def _auto_points(scene: Scene, cfg: TrainConfig, log: Callable[[str], None]) -> PointCloud:
    """The points of :func:`auto_initialization`, plane-sweep stereo running on ``cfg.device``; random points
    where the sweep finds nothing."""
    mode = auto_initialization(scene)
    if mode == "points3d.ply":
        return scene.initial_points
    if mode == "mvs":
        try:
            points = _plane_sweep_points(scene, cfg, log)
            log(f"initialization: {len(points.xyz)} plane-sweep stereo points of the first frame")
            return points
        except DataError as err:
            log(f"initialization: {err}; using random points")
    return _random_points(scene, cfg, log)


def _random_points(scene: Scene, cfg: TrainConfig, log: Callable[[str], None]) -> PointCloud:
    return random_initial_points(scene, cfg.num_random_points, seed=cfg.seed)


def _ray_points(scene: Scene, cfg: TrainConfig, log: Callable[[str], None]) -> PointCloud:
    return ray_initial_points(scene, cfg.num_random_points, seed=cfg.seed)


def _plane_sweep_points(scene: Scene, cfg: TrainConfig, log: Callable[[str], None]) -> PointCloud:
    return plane_sweep_points(scene, cfg.num_random_points, seed=cfg.seed, device=resolve_device(cfg.device))


def _colmap_points(scene: Scene, cfg: TrainConfig, log: Callable[[str], None]) -> PointCloud:
    return triangulate_first_frame(scene)


INIT_MODES: dict[str, Callable[[Scene, TrainConfig, Callable[[str], None]], PointCloud]] = {
    "auto": _auto_points, "random": _random_points, "rays": _ray_points, "mvs": _plane_sweep_points,
    "colmap": _colmap_points,
}
"""Initialization mode → the function that makes its points (see the module docstring)."""


def ray_initial_points(scene: Scene, num_points: int, seed: int = 0, near: float = 0.5,
                       far_factor: float = 2.0) -> PointCloud:
    """Points along random pixel rays of the first frame's training views, coloured by the pixel.

    Each point takes a random training camera of the first frame, a random pixel and a
    depth uniform in ``[near, far_factor × largest camera distance]`` (normalized units), so
    surfaces seen by some cameras only — the walls of a capture dome — get points too; its
    colour is that pixel's colour. Training carves away the points off the surfaces.
    """
    views = scene.first_frame_views()
    rng = np.random.default_rng(seed)
    far = far_factor * max(float(np.linalg.norm(v.camera.center)) for v in views)
    which = rng.integers(len(views), size=num_points)
    xyz = np.empty((num_points, 3))
    rgb = np.empty((num_points, 3), np.float32)
    for k, view in enumerate(views):  # one vectorized batch per camera
        sel = np.nonzero(which == k)[0]
        if sel.size == 0:
            continue
        cam, img = view.camera, view.image()
        u = rng.uniform(0, cam.width, sel.size)
        v = rng.uniform(0, cam.height, sel.size)
        depth = rng.uniform(near, far, sel.size)
        pix = np.stack([u, v, np.ones_like(u)], 1) @ np.linalg.inv(cam.K).T  # camera rays with z = 1
        R, t = cam.viewmat[:3, :3], cam.viewmat[:3, 3]
        xyz[sel] = (pix * depth[:, None] - t) @ R
        rgb[sel] = img[np.minimum(v.astype(int), cam.height - 1), np.minimum(u.astype(int), cam.width - 1)]
    return PointCloud(xyz=xyz, rgb=rgb)
