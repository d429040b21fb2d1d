"""Initial point clouds: coloured points along the first frame's pixel rays."""

import numpy as np

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
