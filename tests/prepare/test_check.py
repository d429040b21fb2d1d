"""The camera checks on a constructed rig: a camera placed wrongly is found by its matches and registered again;
one whose matches fit no pose is left out with the reason."""

from __future__ import annotations

import numpy as np
import pytest

from omg4.data.scene import look_at_viewmat
from omg4.prepare.calibrate import CalibratedCamera, Calibration
from omg4.prepare.camera_model import project
from omg4.prepare.check import check_and_repair, match_agreement, suspects

pytest.importorskip("pycolmap")

K = np.array([[200.0, 0.0, 160.0], [0.0, 200.0, 120.0], [0.0, 0.0, 1.0]])


def rig(n_cameras: int = 5, n_points: int = 400):
    """Points in a box and cameras on an arc looking at it; every camera sees every point (keypoint k = point k)."""
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, (n_points, 3)) * [1.0, 1.0, 0.6]
    cameras = {}
    for i, a in enumerate(np.linspace(-0.7, 0.7, n_cameras)):
        centre = np.array([5 * np.sin(a), -5 * np.cos(a), 0.8 + 0.2 * i])
        cameras[f"c{i}"] = CalibratedCamera(K=K.copy(), distortion=(0.0, 0.0), w2c=look_at_viewmat(centre, np.zeros(3)),
                                            reprojection_error_px=0.3, observations=n_points)
    keypoints = {n: project(points, c.K, c.distortion, c.w2c)[0] for n, c in cameras.items()}
    names = sorted(cameras)
    index = np.arange(n_points)
    matches = {(a, b): np.stack([index, index], 1) for i, a in enumerate(names) for b in names[i + 1:]}
    observations = {n: {k: k for k in range(n_points)} for n in names}
    return Calibration(cameras=cameras, points=points, colors=np.full((n_points, 3), 0.5),
                       point_instants=np.zeros(n_points, np.int64), point_cameras=[set(names)] * n_points,
                       unregistered=[], keypoints=keypoints, matches=matches, observations=observations)


def rotation_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a[:3, :3] @ b[:3, :3].T) - 1) / 2, -1, 1))))


def test_a_camera_placed_wrongly_is_registered_again():
    calibration = rig()
    truth = calibration.cameras["c3"].w2c.copy()
    wrong = truth.copy()
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90° about the camera's axis
    wrong[:3] = turn @ truth[:3]
    calibration.cameras["c3"] = CalibratedCamera(K=K, distortion=(0.0, 0.0), w2c=wrong, reprojection_error_px=0.3,
                                                 observations=400)
    agreement = match_agreement(calibration.cameras, calibration.keypoints, calibration.matches)
    assert suspects(agreement) == ["c3"] and agreement["c0"] > 0.7 > 0.3 > agreement["c3"]
    repaired, checks = check_and_repair(calibration, {n: (320, 240) for n in calibration.cameras})
    assert checks["c3"].reliable and checks["c3"].reregistered and checks["c3"].agreement > 0.99
    assert rotation_error_deg(repaired.cameras["c3"].w2c, truth) < 0.01
    assert np.allclose(repaired.cameras["c3"].center, -truth[:3, :3].T @ truth[:3, 3], atol=1e-3)
    assert all(checks[n].reliable and not checks[n].reregistered for n in ("c0", "c1", "c2", "c4"))


def test_a_camera_whose_matches_fit_no_pose_is_left_out_with_the_reason():
    calibration = rig()
    rng = np.random.default_rng(1)
    calibration.keypoints["c2"] = rng.uniform([0, 0], [320, 240], (400, 2))  # its matches point anywhere
    repaired, checks = check_and_repair(calibration, {n: (320, 240) for n in calibration.cameras})
    assert not checks["c2"].reliable and "c2" not in repaired.cameras and repaired.unregistered == ["c2"]
    assert "its matches contradict its pose" in checks["c2"].reason and "did not help" in checks["c2"].reason
    assert all(checks[n].reliable for n in ("c0", "c1", "c3", "c4"))
