"""The camera checks on a constructed rig: a camera placed wrongly is found by its matches and registered again;
one whose matches fit no pose is left out with the reason."""

from __future__ import annotations

import numpy as np
import pytest

from omg4.data.scene import look_at_viewmat
from omg4.prepare.calibrate import CalibratedCamera, Calibration
from omg4.prepare.camera_model import project
from omg4.prepare.check import check_and_repair, match_agreement, pose_differences, rig_disagreement, suspects

import pycolmap  # noqa: F401  (a dependency of omg4)

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


def _turned(camera: CalibratedCamera, degrees: float, axis: int = 1, focal: float = 1.0) -> CalibratedCamera:
    """``camera`` turned about its own axis ``axis`` by ``degrees`` (centre kept), its focal length times ``focal``."""
    a = np.radians(degrees)
    c, s = np.cos(a), np.sin(a)
    turn = {0: [[1, 0, 0], [0, c, -s], [0, s, c]], 1: [[c, 0, s], [0, 1, 0], [-s, 0, c]],
            2: [[c, -s, 0], [s, c, 0], [0, 0, 1]]}[axis]
    w2c = camera.w2c.copy()
    centre = camera.center
    w2c[:3, :3] = np.asarray(turn) @ w2c[:3, :3]
    w2c[:3, 3] = -w2c[:3, :3] @ centre
    K = camera.K.copy()
    K[0, 0] = K[1, 1] = K[0, 0] * focal
    return CalibratedCamera(K=K, distortion=camera.distortion, w2c=w2c, reprojection_error_px=0.3, observations=400)


def _moved(camera: CalibratedCamera, R: np.ndarray, scale: float, shift: np.ndarray) -> CalibratedCamera:
    """``camera`` in a world moved by x → scale · R x + shift: the same rig, described otherwise."""
    w2c = np.eye(4)
    w2c[:3, :3] = camera.w2c[:3, :3] @ R.T
    w2c[:3, 3] = -w2c[:3, :3] @ (scale * R @ camera.center + shift)
    return CalibratedCamera(K=camera.K, distortion=camera.distortion, w2c=w2c, reprojection_error_px=0.3,
                            observations=400)


def test_pose_differences_ignore_the_world_and_measure_what_moved():
    cameras = rig().cameras
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    same = {n: _moved(c, R, 3.0, np.array([1.0, -2.0, 0.5])) for n, c in cameras.items()}
    as_pairs = lambda cams: {n: (c.w2c, float(c.K[0, 0])) for n, c in cams.items()}  # noqa: E731
    still = pose_differences(as_pairs(same), as_pairs(cameras))
    assert still["cameras"] == 5 and still["rotation_deg_max"] < 1e-5 and still["centre_pct_max"] < 1e-6
    assert still["focal_pct_max"] < 1e-9
    one = dict(same, c2=_turned(same["c2"], 4.0, axis=2, focal=1.1))  # about its viewing axis: no alignment helps
    moved = pose_differences(as_pairs(one), as_pairs(cameras))
    assert moved["rotation_deg_max"] == pytest.approx(4.0, abs=1.0) and moved["rotation_deg_median"] < 1.0
    assert moved["focal_pct_max"] == pytest.approx(10.0) and moved["focal_pct_median"] == 0.0


def test_a_rig_the_halves_of_its_instants_do_not_reproduce_is_not_trusted():
    cameras = rig().cameras
    agreeing = {n: _turned(c, 0.3) for n, c in cameras.items()}
    # every camera turned its own way and the focal lengths 30 % longer: a consistent rig, but another one
    bent = {n: _turned(c, 6.0 * (-1) ** i, axis=i % 3, focal=1.3) for i, (n, c) in enumerate(sorted(cameras.items()))}
    longer = {n: _turned(c, 0.0, focal=1.3) for n, c in cameras.items()}
    doubt, rows = rig_disagreement(cameras, [cameras, agreeing])
    assert doubt is None and len(rows) == 2 and rows[0]["rotation_deg_median"] < 1e-6
    doubt, rows = rig_disagreement(cameras, [agreeing, bent])  # one half lost its way: the other reproduces the rig
    assert doubt is None and rows[1]["focal_pct_median"] == pytest.approx(30.0)
    doubt, _ = rig_disagreement(cameras, [bent, longer])  # neither does
    assert doubt is not None and "each half" in doubt and "30 %" in doubt
    assert rig_disagreement(cameras, [longer])[0] is not None  # focal lengths alone
    assert rig_disagreement(cameras, [{"c0": bent["c0"], "c1": bent["c1"]}])[0] is None  # too few to judge
    assert rig_disagreement(cameras, [])[0] is None
