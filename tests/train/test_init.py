"""Initial point clouds: coloured points along the first frame's pixel rays."""

import numpy as np
import torch

from omg4.train.init import ray_initial_points


def test_ray_points_project_onto_a_pixel_of_their_colour(tiny_scene):
    pc = ray_initial_points(tiny_scene, 400, seed=3, near=0.5)
    first = min(v.frame_index for v in tiny_scene.train_views)
    views = [v for v in tiny_scene.train_views if v.frame_index == first]
    explained = np.zeros(len(pc.xyz), bool)
    for view in views:
        cam, img = view.camera, view.image()
        X = pc.xyz @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
        uv = X @ cam.K.T
        u, v = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
        inside = (X[:, 2] >= 0.5 - 1e-9) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        col = img[np.clip(v.astype(int), 0, cam.height - 1), np.clip(u.astype(int), 0, cam.width - 1)]
        explained |= inside & np.all(np.abs(col - pc.rgb) < 1e-6, axis=1)
    assert explained.all()
    # depths spread over the range: not all points on one surface
    depth_spread = np.ptp(np.linalg.norm(pc.xyz - views[0].camera.center, axis=1))
    assert depth_spread > 1.0


def test_ray_points_are_deterministic(tiny_scene):
    a = ray_initial_points(tiny_scene, 100, seed=1)
    b = ray_initial_points(tiny_scene, 100, seed=1)
    assert np.array_equal(a.xyz, b.xyz) and np.array_equal(a.rgb, b.rgb)
    assert not np.array_equal(a.xyz, ray_initial_points(tiny_scene, 100, seed=2).xyz)


def _without_points(scene, views=None):
    from dataclasses import replace

    return replace(scene, initial_points=None, train_views=scene.train_views if views is None else views)


def test_auto_prefers_ply_then_stereo_then_random(tiny_scene, monkeypatch):
    import omg4.train.init as init_module  # the sweep as initialization calls it
    from omg4.data import random_initial_points
    from omg4.data.scene import PointCloud
    from omg4.errors import DataError
    from omg4.train import make_config
    from omg4.train.init import initial_points

    cfg = make_config("cpu-small", num_random_points=50)
    stereo = PointCloud(xyz=np.zeros((3, 3)), rgb=np.zeros((3, 3), np.float32))
    calls, devices = [], []

    def fake_sweep(scene, num_points, seed=0, device="cpu"):
        calls.append(num_points)
        devices.append(device)
        return stereo

    monkeypatch.setattr(init_module, "plane_sweep_points", fake_sweep)
    assert initial_points(tiny_scene, "auto", cfg, log=lambda m: None) is tiny_scene.initial_points
    assert calls == []
    assert initial_points(_without_points(tiny_scene), "auto", cfg, log=lambda m: None) is stereo
    assert calls == [50] and devices == [torch.device("cpu")]  # the sweep runs on the training device

    # one camera (monocular, like D-NeRF): random points, the sweep is not tried
    name = tiny_scene.train_views[0].camera.name
    mono = _without_points(tiny_scene, [v for v in tiny_scene.train_views if v.camera.name == name])
    got = initial_points(mono, "auto", cfg, log=lambda m: None)
    assert calls == [50] and np.array_equal(got.xyz, random_initial_points(mono, 50, seed=cfg.seed).xyz)

    # a sweep that finds nothing falls back to random points and says so
    def failing_sweep(scene, num_points, seed=0, device="cpu"):
        raise DataError("plane-sweep initialization found no consistent point")

    monkeypatch.setattr(init_module, "plane_sweep_points", failing_sweep)
    messages = []
    got = initial_points(_without_points(tiny_scene), "auto", cfg, log=messages.append)
    assert len(got.xyz) == 50 and "using random points" in messages[0]
