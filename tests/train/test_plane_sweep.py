"""Plane-sweep stereo initialization (``omg4 train --init mvs``).

References independent of the code under test: an analytic textured plane seen by cameras
with known poses (exact depth per pixel), the synthetic scene's ray caster (exact surface
distance along any ray), and the held-out test camera of the real basketball scene.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from omg4.data import load_scene
from omg4.data.scene import Camera, Scene
from omg4.data.synthetic import look_at_viewmat
from omg4.errors import OMG4Error
from omg4.train.init import ray_initial_points
from omg4.train.plane_sweep import SweepConfig, choose_neighbours, plane_sweep_points, sweep_depth


def _plane_camera(x: float, w: int = 96, h: int = 72, f: float = 90.0) -> Camera:
    K = np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
    return Camera(K=K, viewmat=look_at_viewmat(np.array([x, 0.0, 0.0]), np.array([x, 5.0, 0.0])), width=w,
                  height=h, name=f"c{x}")


def _plane_hits(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Exact z-depth and grey texture of the tilted plane y = 3 + 0.3·x seen by ``cam`` (pixel centres)."""
    v, u = np.meshgrid(np.arange(cam.height) + 0.5, np.arange(cam.width) + 0.5, indexing="ij")
    rays_cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(cam.K).T
    R = cam.viewmat[:3, :3]
    dirs = rays_cam @ R  # world directions of z = 1 camera rays
    c = cam.center
    s = (3.0 + 0.3 * c[0] - c[1]) / (dirs[..., 1] - 0.3 * dirs[..., 0])  # y = 3 + 0.3 x along c + s·d
    p = c + s[..., None] * dirs
    texture = 0.5 + 0.2 * np.sin(7.3 * p[..., 0] + 1.1) * np.cos(5.9 * p[..., 2]) + 0.15 * np.sin(13.1 * p[..., 0]
                                                                                                  - 11.7 * p[..., 2])
    return s, texture.astype(np.float32)


def test_sweep_recovers_the_depth_of_a_textured_plane():
    cams = [_plane_camera(x) for x in (0.0, -0.25, 0.25, 0.5)]
    greys = [torch.from_numpy(_plane_hits(c)[1]) for c in cams]
    true_depth = _plane_hits(cams[0])[0]
    depths = torch.linspace(1.5, 6.0, 91)  # 0.05 apart
    dm = sweep_depth(cams[0], greys[0], list(zip(cams[1:], greys[1:])), depths, SweepConfig(min_texture=0.0))
    got = dm.depth.numpy()
    kept = got > 0
    assert kept.mean() > 0.7
    err = np.abs(got - true_depth)[kept]
    assert np.median(err) < 0.01 and np.mean(err < 0.05) > 0.95  # sub-plane accuracy
    # a wrong relative pose must not reproduce the plane
    shifted = [_plane_camera(x + 0.1) for x in (-0.25, 0.25, 0.5)]
    bad = sweep_depth(cams[0], greys[0], list(zip(shifted, greys[1:])), depths, SweepConfig(min_texture=0.0))
    assert np.median(np.abs(bad.depth.numpy() - true_depth)[bad.depth.numpy() > 0]) > 0.1


def test_neighbours_are_near_and_look_the_same_way():
    cams = [_plane_camera(x) for x in (0.0, 0.3, -0.1, 2.0)]
    backwards = Camera(K=cams[0].K, viewmat=look_at_viewmat(np.array([0.05, 0.0, 0.0]), np.array([0.05, -5.0, 0.0])),
                       width=96, height=72)
    assert choose_neighbours(cams + [backwards], 0, 2, 50.0) == [2, 1]


def test_points_lie_on_the_synthetic_surfaces(synth_scene, surface_error):
    pc = plane_sweep_points(synth_scene, 3000, seed=1, progress=False, cfg=SweepConfig(num_depths=96))
    assert pc.xyz.shape == (3000, 3) and pc.rgb.shape == (3000, 3) and pc.rgb.dtype == np.float32
    rel, colour = surface_error(synth_scene, pc.xyz)
    assert np.median(rel) < 0.01 and np.mean(rel < 0.03) > 0.85
    assert np.median(np.abs(colour - pc.rgb).mean(1)) < 0.05
    rays, _ = surface_error(synth_scene, ray_initial_points(synth_scene, 500, seed=1).xyz)
    assert np.median(rays) > 0.1  # the control: points at random depths along the same kind of rays
    # at most one point per voxel of 1/1000 of the far plane (far = 2.3 × the largest camera distance)
    far = 2.3 * max(float(np.linalg.norm(v.camera.center)) for v in synth_scene.train_views)
    cells = np.floor(pc.xyz / (1e-3 * far)).astype(np.int64)
    assert len(np.unique(cells, axis=0)) == len(cells)


def test_only_pixels_with_a_depth_become_points():
    from omg4.train.plane_sweep import DepthMap, _unproject

    cam = _plane_camera(0.0, w=8, h=6)
    depth = torch.zeros(6, 8)
    depth[1, 2], depth[4, 7] = 2.0, 3.5
    points, idx = _unproject(DepthMap(camera=cam, depth=depth))
    assert idx.tolist() == [1 * 8 + 2, 4 * 8 + 7]
    # each point lies on its pixel's ray at that z-depth: back in the camera frame, z is the depth
    R, t = cam.viewmat[:3, :3], cam.viewmat[:3, 3]
    in_camera = points.numpy() @ R.T + t
    np.testing.assert_allclose(in_camera[:, 2], [2.0, 3.5], rtol=1e-6)
    np.testing.assert_allclose(in_camera[:, :2] / in_camera[:, 2:] * cam.K[0, 0] + cam.K[:2, 2],
                               [[2.5, 1.5], [7.5, 4.5]], rtol=1e-6)


def test_basketball_points_match_the_held_out_camera(n3dv_basketball):
    scene = load_scene(n3dv_basketball, downscale=4, frames=range(0, 1), progress=False)
    pc = plane_sweep_points(scene, 20000, progress=False, cfg=SweepConfig(num_depths=96))
    cam = scene.test_views[0].camera
    image = scene.test_views[0].image()

    def colour_agreement(xyz: np.ndarray, rgb: np.ndarray) -> float:
        """Correlation of the points' grey levels with cam00's pixels where they land."""
        x = xyz @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
        uv = (x @ cam.K.T)[:, :2] / x[:, 2:]
        ok = (x[:, 2] > 0.2) & (uv >= 0).all(1) & (uv[:, 0] < cam.width) & (uv[:, 1] < cam.height)
        assert ok.sum() >= 500
        px = image[uv[ok, 1].astype(int), uv[ok, 0].astype(int)]
        return float(np.corrcoef(px.mean(1), rgb[ok].mean(1))[0, 1])

    rays = ray_initial_points(scene, 20000, seed=0)
    # cam00 never took part: the stereo points land on pixels of their colour, random depths do not
    assert colour_agreement(pc.xyz, pc.rgb) > 0.6 > 0.3 > colour_agreement(rays.xyz, rays.rgb)


def test_no_usable_camera_pair_is_a_one_line_error(synth_scene):
    lone = Scene(train_views=[v for v in synth_scene.train_views if v.camera.name == synth_scene.train_views[0].camera.name],
                 test_views=synth_scene.test_views, time_range=synth_scene.time_range,
                 normalization=synth_scene.normalization, format="n3dv")
    with pytest.raises(OMG4Error, match="no training camera has two neighbours"):
        plane_sweep_points(lone, 100, progress=False)
    empty = Scene(train_views=[], test_views=synth_scene.test_views, time_range=synth_scene.time_range,
                  normalization=synth_scene.normalization, format="n3dv")
    with pytest.raises(OMG4Error, match="no training views"):
        plane_sweep_points(empty, 100, progress=False)


def test_sweep_on_an_explicit_device_under_a_meta_default_matches(synth_scene):
    """Every tensor of the sweep is created on the requested device (a stray default-device
    tensor would land on "meta" and fail): explicit CPU reproduces the default run exactly."""
    cfg = SweepConfig(num_depths=48)
    reference = plane_sweep_points(synth_scene, 800, seed=2, progress=False, cfg=cfg)
    with torch.device("meta"):
        explicit = plane_sweep_points(synth_scene, 800, seed=2, progress=False, cfg=cfg, device="cpu")
    np.testing.assert_array_equal(explicit.xyz, reference.xyz)
    np.testing.assert_array_equal(explicit.rgb, reference.rgb)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.gpu
def test_sweep_on_cuda_finds_the_cpu_points(synth_scene, surface_error):
    cfg = SweepConfig(num_depths=96)
    cpu = plane_sweep_points(synth_scene, 3000, seed=1, progress=False, cfg=cfg)
    gpu = plane_sweep_points(synth_scene, 3000, seed=1, progress=False, cfg=cfg, device="cuda")
    assert abs(len(gpu.xyz) - len(cpu.xyz)) <= 0.01 * len(cpu.xyz)
    rel, _ = surface_error(synth_scene, gpu.xyz)
    assert np.median(rel) < 0.01
