"""The lens model is chosen by what the observations ask for: a rig seen through distortion-free lenses is
calibrated without distortion coefficients, one seen through a distorting lens keeps them."""

from __future__ import annotations

import numpy as np
import pytest

from omg4.data.scene import look_at_viewmat
from omg4.prepare.camera_model import project

import pycolmap

from omg4.prepare.calibrate import simplest_lens  # noqa: E402

K = np.array([[260.0, 0.0, 160.0], [0.0, 260.0, 120.0], [0.0, 0.0, 1.0]])


def bundle_adjusted(k1: float, k2: float, noise_px: float = 0.3, n_cameras: int = 6, n_points: int = 600):
    """A reconstruction of points in a box seen by cameras on an arc through a ``RADIAL`` lens (k1, k2), their
    keypoints with Gaussian noise, bundle-adjusted with free distortion from a distortion-free start; and the
    keypoints by camera name."""
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, (n_points, 3)) * [1.6, 1.6, 0.6]
    rec = pycolmap.Reconstruction()
    keypoints, tracks = {}, [[] for _ in range(n_points)]
    for i, angle in enumerate(np.linspace(-0.6, 0.6, n_cameras)):
        w2c = look_at_viewmat(np.array([4 * np.sin(angle), -4 * np.cos(angle), 0.5 + 0.1 * i]), np.zeros(3))
        pixels = project(points, K, (k1, k2), w2c)[0] + rng.normal(0, noise_px, (n_points, 2))
        keypoints[f"c{i}"] = pixels.astype(np.float32)
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model="RADIAL", width=320, height=240, camera_id=i + 1,
                                                        params=[250.0, 160.0, 120.0, 0.0, 0.0]))
        image = pycolmap.Image(name=f"c{i}.png", keypoints=pixels, camera_id=i + 1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3]))
        for k in range(n_points):
            tracks[k].append(pycolmap.TrackElement(i + 1, k))
    for k in range(n_points):
        rec.add_point3D(points[k] + rng.normal(0, 0.01, 3), pycolmap.Track(tracks[k]))
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    pycolmap.bundle_adjustment(rec, options)
    return rec, keypoints


def test_distortion_the_views_do_not_ask_for_is_dropped():
    rec, keypoints = bundle_adjusted(0.0, 0.0)
    assert any(abs(c.params[3]) > 1e-3 for c in rec.cameras.values())  # free coefficients fit the noise
    chosen, lens = simplest_lens(rec, keypoints)
    assert lens["distortion"] == "dropped" and lens["rms_without_px"] < 1.02 * lens["rms_with_px"]
    assert all(c.params[3] == 0.0 and c.params[4] == 0.0 for c in chosen.cameras.values())
    assert all(abs(c.params[0] / K[0, 0] - 1) < 0.01 for c in chosen.cameras.values())


def test_the_distortion_of_a_real_lens_is_kept():
    rec, keypoints = bundle_adjusted(-0.15, 0.02)
    chosen, lens = simplest_lens(rec, keypoints)
    assert lens["distortion"] == "kept" and chosen is rec
    assert all(abs(c.params[3] + 0.15) < 0.03 for c in chosen.cameras.values())
