"""Initial point clouds for baseline training (reference rt4dgs §3.5).

``auto`` uses the data's ``points3d.ply`` when present, else random points inside the
cameras' common view volume (:func:`omg4.data.random_initial_points`).
"""

from __future__ import annotations

from omg4.data.scene import PointCloud, Scene
from omg4.errors import OMG4Error
from omg4.train.config import TrainConfig


def initial_points(scene: Scene, mode: str, cfg: TrainConfig) -> PointCloud:
    """The initial points for ``mode`` in {auto, random, colmap}."""
    from omg4.data import random_initial_points

    if mode == "auto":
        if scene.initial_points is not None:
            return scene.initial_points
        return random_initial_points(scene, cfg.num_random_points, seed=cfg.seed)
    if mode == "random":
        return random_initial_points(scene, cfg.num_random_points, seed=cfg.seed)
    if mode == "colmap":
        from omg4.train.triangulate import triangulate_first_frame

        return triangulate_first_frame(scene)
    raise OMG4Error(f"unknown initialization '{mode}'")
