"""Sparse first-frame triangulation with pycolmap (``omg4 train --init colmap``).

References independent of the code under test: closed-form epipolar geometry, the synthetic
scene's own ray caster (exact surface depth and colour along any ray, ``surface_error`` in
``conftest.py``), its ``points3d.ply`` surface samples, and the held-out test camera of the
real basketball scene.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

from omg4.data import load_scene, random_initial_points
from omg4.data.scene import Camera, Scene
from omg4.data.synthetic import look_at_viewmat
from omg4.errors import OMG4Error
from omg4.train.triangulate import (TriangulationOptions, fundamental_from_poses, sampson_errors,
                                    triangulate_first_frame, triangulate_views)



def _camera(center, target, f=300.0, w=320, h=240, name=""):
    K = np.array([[f, 0.0, w / 2 + 3.0], [0.0, 1.1 * f, h / 2 - 2.0], [0.0, 0.0, 1.0]])
    return Camera(K=K, viewmat=look_at_viewmat(np.asarray(center, float), np.asarray(target, float)), width=w,
                  height=h, name=name)


def _project(cam: Camera, x: np.ndarray) -> np.ndarray:
    """Pixels [M, 2] of world points x [M, 3] (float64 pinhole projection)."""
    c = x @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
    uv = c @ cam.K.T
    return uv[:, :2] / uv[:, 2:]


# -- epipolar geometry of known poses ------------------------------------------------------------

def test_fundamental_vanishes_on_true_correspondences():
    rng = np.random.default_rng(0)
    cam1 = _camera([4.0, -1.0, 1.5], [0.0, 0.0, 0.3])
    cam2 = _camera([1.0, -4.0, 2.0], [0.2, 0.1, 0.0], f=420.0)
    x = rng.uniform(-1.0, 1.0, size=(200, 3))
    F = fundamental_from_poses(cam1, cam2)
    e = sampson_errors(F, _project(cam1, x), _project(cam2, x))
    assert e.max() < 1e-16
    # a random pixel in image 2 is far from the epipolar line of its partner
    wrong = sampson_errors(F, _project(cam1, x), rng.uniform(0, 240, size=(200, 2)))
    assert np.median(wrong) > 10.0


def test_sampson_error_closed_form_for_rectified_pair():
    # identical cameras, cam2 shifted along +x: epipolar lines are rows, x2ᵀ F x1 ∝ (y2 − y1),
    # both gradients have unit norm after scaling, so the Sampson error is exactly dy² / 2.
    K = np.array([[250.0, 0.0, 160.0], [0.0, 250.0, 120.0], [0.0, 0.0, 1.0]])
    v1, v2 = np.eye(4), np.eye(4)
    v2[0, 3] = -0.7
    cam1, cam2 = Camera(K, v1, 320, 240), Camera(K, v2, 320, 240)
    rng = np.random.default_rng(1)
    x1 = rng.uniform(0, 240, size=(50, 2))
    dy = rng.uniform(-3.0, 3.0, size=50)
    x2 = np.stack([rng.uniform(0, 320, size=50), x1[:, 1] + dy], axis=1)
    np.testing.assert_allclose(sampson_errors(fundamental_from_poses(cam1, cam2), x1, x2), dy**2 / 2, rtol=1e-9,
                               atol=1e-12)


# -- synthetic scene: exact surfaces from the generator's ray caster -------------------------

@pytest.fixture(scope="module")
def synth_result(synth_scene):
    import pycolmap  # noqa: F401
    return triangulate_views(synth_scene.first_frame_views(), progress=False)


def test_first_frame_views_one_per_training_camera(synth_scene, synth_config):
    views = synth_scene.first_frame_views()
    assert len(synth_scene.train_views) == (synth_config.num_cameras - 1) * synth_config.num_frames
    assert [v.frame_index for v in views] == [0] * (synth_config.num_cameras - 1)
    assert len({v.camera.name for v in views}) == synth_config.num_cameras - 1


def test_synthetic_points_lie_on_the_true_surfaces(synth_scene, synth_result, surface_error):
    from scipy.spatial import cKDTree

    xyz, rgb = synth_result.points.xyz, synth_result.points.rgb
    opts = TriangulationOptions()
    assert xyz.shape[0] >= 150 and xyz.shape == rgb.shape == (len(synth_result.errors), 3)
    assert xyz.dtype == np.float64 and rgb.dtype == np.float32
    assert rgb.min() >= 0.0 and rgb.max() <= 1.0
    assert synth_result.errors.max() <= opts.max_reproj_error and synth_result.track_lengths.min() >= 2

    # exact depth along camera rays: the median point is within 1 % of its surface distance
    rel, colour = surface_error(synth_scene, xyz)
    assert np.median(rel) < 0.01 and np.mean(rel < 0.02) > 0.75
    # multi-view points (track ≥ 3) are nearly all on a surface
    assert np.mean(rel[synth_result.track_lengths >= 3] < 0.02) > 0.9
    # colours are those of the surface (Lambertian: view independent), not e.g. BGR or 0..255
    assert np.median(np.abs(colour - rgb).mean(1)) < 0.05

    # nearest points3d.ply surface sample: close relative to the scene size, unlike random points
    tree = cKDTree(synth_scene.initial_points.xyz)
    near = np.median(tree.query(xyz)[0])
    control = np.median(tree.query(random_initial_points(synth_scene, 500, seed=3).xyz)[0])
    assert near < 0.04 * synth_scene.extent < control
    rel_control, _ = surface_error(synth_scene, random_initial_points(synth_scene, 200, seed=3).xyz)
    assert np.median(rel_control) > 0.05


def test_triangulation_is_repeatable(synth_scene, synth_result):
    again = triangulate_first_frame(synth_scene, progress=False)
    assert again.xyz.shape == synth_result.points.xyz.shape
    np.testing.assert_array_equal(again.xyz, synth_result.points.xyz)
    np.testing.assert_array_equal(again.rgb, synth_result.points.rgb)


# -- real data ---------------------------------------------------------------------------------

def test_basketball_points_are_consistent_with_the_held_out_camera(n3dv_basketball):
    import pycolmap  # noqa: F401
    scene = load_scene(n3dv_basketball, downscale=2, frames=range(0, 1), progress=False)
    result = triangulate_views(scene.first_frame_views(), progress=False)
    xyz, rgb = result.points.xyz, result.points.rgb
    assert len(xyz) >= 500 and result.upsample == 2
    assert np.median(result.errors) < 0.5

    def inside(cam: Camera, x: np.ndarray):
        depth = x @ cam.viewmat[2, :3] + cam.viewmat[2, 3]
        uv = _project(cam, x)
        return (depth > 0.2) & (uv >= 0).all(1) & (uv[:, 0] < cam.width) & (uv[:, 1] < cam.height), uv

    # every training camera sees a good share of the cloud, each point is seen by several cameras
    seen = np.array([inside(cam, xyz)[0] for cam in scene.train_cameras()])
    assert seen.mean(1).min() > 0.25 and np.median(seen.sum(0)) >= 8

    # photo-consistency with cam00, which the triangulation never used: the points' colours match
    # the held-out image where they land, far better than random points with the same colours
    test_view = scene.test_views[0]
    image = test_view.image()

    def colour_error(x: np.ndarray, c: np.ndarray) -> float:
        ok, uv = inside(test_view.camera, x)
        assert ok.sum() >= 100
        px = image[uv[ok, 1].astype(int), uv[ok, 0].astype(int)]
        return float(np.median(np.abs(px - c[ok]).mean(1)))

    control = random_initial_points(scene, 2000, seed=0).xyz
    shuffled = rgb[np.random.default_rng(0).integers(0, len(rgb), len(control))]
    assert colour_error(xyz, rgb) < 0.06 < colour_error(control, shuffled)


# -- bad input -------------------------------------------------------------------------------

def test_missing_pycolmap_is_a_one_line_error(synth_scene, monkeypatch):
    import pycolmap  # noqa: F401
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # makes ``import pycolmap`` raise ImportError
    with pytest.raises(OMG4Error, match="pip install .pycolmap"):
        triangulate_first_frame(synth_scene, progress=False)


def test_too_few_views_or_points(synth_scene):
    import pycolmap  # noqa: F401
    with pytest.raises(OMG4Error, match="at least 2 training cameras"):
        triangulate_views(synth_scene.first_frame_views()[:1], progress=False)
    with pytest.raises(OMG4Error, match="kept only .* points"):
        triangulate_views(synth_scene.first_frame_views()[:2], TriangulationOptions(min_points=10**6),
                          progress=False)
    empty = Scene(train_views=[], test_views=synth_scene.test_views, time_range=synth_scene.time_range,
                  normalization=synth_scene.normalization, format="n3dv")
    with pytest.raises(OMG4Error, match="no training views"):
        triangulate_first_frame(empty, progress=False)
