"""Initial point clouds for baseline training (reference rt4dgs §3.5).

``auto`` uses the data's ``points3d.ply`` when present, else plane-sweep stereo for
multi-view video, else random points inside the cameras' common view volume
(:func:`omg4.data.random_initial_points`); ``rays`` places
coloured points along the first frame's training rays (:func:`ray_initial_points`);
``mvs`` runs plane-sweep stereo on the first frame (:mod:`omg4.train.plane_sweep`);
``colmap`` triangulates the first frame with pycolmap.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from omg4.data.scene import PointCloud, Scene
from omg4.errors import DataError, OMG4Error
from omg4.train.config import TrainConfig


def initial_points(scene: Scene, mode: str, cfg: TrainConfig, log: Callable[[str], None] = print) -> PointCloud:
    """The initial points for ``mode`` in {auto, random, rays, mvs, colmap}.

    ``auto``: the data's ``points3d.ply``; else plane-sweep stereo (on ``cfg.device``) when the first frame has at
    least three training cameras (multi-view video); else — a monocular scene such as D-NeRF,
    or a sweep that finds nothing — random points, as the official code does for D-NeRF.
    """
    from omg4.data import random_initial_points
    from omg4.device import resolve_device

    if mode == "auto":
        if scene.initial_points is not None:
            return scene.initial_points
        if len(scene.first_frame_views()) >= 3:
            from omg4.train.plane_sweep import plane_sweep_points

            try:
                points = plane_sweep_points(scene, cfg.num_random_points, seed=cfg.seed, device=resolve_device(cfg.device))
                log(f"initialization: {len(points.xyz)} plane-sweep stereo points of the first frame")
                return points
            except DataError as err:
                log(f"initialization: {err}; using random points")
        return random_initial_points(scene, cfg.num_random_points, seed=cfg.seed)
    if mode == "random":
        return random_initial_points(scene, cfg.num_random_points, seed=cfg.seed)
    if mode == "rays":
        return ray_initial_points(scene, cfg.num_random_points, seed=cfg.seed)
    if mode == "mvs":
        from omg4.train.plane_sweep import plane_sweep_points

        return plane_sweep_points(scene, cfg.num_random_points, seed=cfg.seed, device=resolve_device(cfg.device))
    if mode == "colmap":
        from omg4.train.triangulate import triangulate_first_frame

        return triangulate_first_frame(scene)
    raise OMG4Error(f"unknown initialization '{mode}'")


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
