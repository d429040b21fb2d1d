"""Cross-layout check: ``n3dv_basketball`` and ``panoptic_basketball`` are the same recording.

The N3DV copy was resampled to one focal length and a centred principal point per camera
(a pure change of intrinsics), and its ``camXX`` is Panoptic camera ``XX``. So, once each
reader's normalization is undone, a 3D point seen by camera XX projects to pixels related by
the homography ``K_n3dv · K_panoptic⁻¹`` (within 1 px), and the Panoptic image warped by that
homography matches the decoded N3DV frame (PSNR > 30 dB).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from omg4.data import load_scene

CAMERAS = ["0", "5", "12", "21", "30"]


def original_viewmat(viewmat: np.ndarray, norm) -> np.ndarray:
    """Undo ``x_norm = s (R x + t)`` on a world-to-camera matrix (camera units in the original world)."""
    out = np.eye(4)
    out[:3, :3] = viewmat[:3, :3] @ norm.rotation
    out[:3, 3] = viewmat[:3, 3] / norm.scale + viewmat[:3, :3] @ norm.translation
    return out


def project(K: np.ndarray, viewmat: np.ndarray, points: np.ndarray) -> np.ndarray:
    """[M, 2] pixel coordinates (pixel centres at +0.5) of points [M, 3]."""
    x = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    p = x @ K.T
    return p[:, :2] / p[:, 2:]


@pytest.fixture
def scenes(n3dv_basketball, panoptic_basketball, tmp_path):
    """Frames 0–1 of the cameras in :data:`CAMERAS` in both layouts (decodes 10 frames)."""
    n3dv = load_scene(n3dv_basketball, frames=range(0, 2), cameras=[f"cam{int(c):02d}" for c in CAMERAS],
                      cache_dir=tmp_path, progress=False)
    pano = load_scene(panoptic_basketball, frames=range(0, 2), cameras=CAMERAS)
    return n3dv, pano


def test_points_project_to_the_same_pixel(scenes, panoptic_basketball):
    n3dv, pano = scenes
    meta = json.loads((panoptic_basketball / "train_meta.json").read_text())
    test_meta = json.loads((panoptic_basketball / "test_meta.json").read_text())
    raw = {str(c): (np.array(m["k"][0][i]), np.array(m["w2c"][0][i]))
           for m in (meta, test_meta) for i, c in enumerate(m["cam_id"][0])}
    n_cams = {c.name: c for c in n3dv.train_cameras() + n3dv.test_cameras()}
    p_cams = {c.name: c for c in pano.train_cameras() + pano.test_cameras()}
    rng = np.random.default_rng(0)
    for name in CAMERAS:
        # points seen by the camera: random pixels at random depths, built from the raw json
        K_raw, w2c_raw = raw[name]
        pix = rng.uniform([20, 20], [620, 340], size=(50, 2))
        depth = rng.uniform(1.0, 6.0, size=(50, 1))
        x_cam = np.concatenate([pix, np.ones((50, 1))], 1) @ np.linalg.inv(K_raw).T * depth
        world = (x_cam - w2c_raw[:3, 3]) @ w2c_raw[:3, :3]  # R^T (x − t)
        cn, cp = n_cams[f"cam{int(name):02d}"], p_cams[name]
        px_n = project(cn.K, cn.viewmat, n3dv.normalization.apply_points(world))
        px_p = project(cp.K, cp.viewmat, pano.normalization.apply_points(world))
        np.testing.assert_allclose(px_p, pix, atol=1e-6)
        resampled = np.concatenate([px_p, np.ones((50, 1))], 1) @ (cn.K @ np.linalg.inv(cp.K)).T
        err = np.linalg.norm(resampled[:, :2] / resampled[:, 2:] - px_n, axis=1)
        assert err.max() < 1.0, f"camera {name}: {err.max():.3f} px"
        # both readers' cameras agree in the original world (rotation and centre)
        vn, vp = original_viewmat(cn.viewmat, n3dv.normalization), original_viewmat(cp.viewmat, pano.normalization)
        np.testing.assert_allclose(vn[:3, :3], w2c_raw[:3, :3], atol=1e-6)
        np.testing.assert_allclose(vp, w2c_raw, atol=1e-6)


def warp_to(image: np.ndarray, H: np.ndarray, width: int, height: int) -> np.ndarray:
    """[height, width, 3] sampling ``image`` bilinearly at ``H · (u, v, 1)`` for every output pixel centre."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    src = np.stack([u, v, np.ones_like(u)], -1) @ H.T
    x, y = src[..., 0] / src[..., 2] - 0.5, src[..., 1] / src[..., 2] - 0.5
    return np.stack([map_coordinates(image[..., c], [y, x], order=1, mode="nearest") for c in range(3)], -1)


@pytest.mark.parametrize("name,frame", [("0", 0), ("12", 1), ("30", 1)])
def test_decoded_frames_agree(scenes, name, frame):
    n3dv, pano = scenes
    views_n = {(v.camera.name, v.frame_index): v for v in n3dv.train_views + n3dv.test_views}
    views_p = {(v.camera.name, v.frame_index): v for v in pano.train_views + pano.test_views}
    vn, vp = views_n[(f"cam{int(name):02d}", frame)], views_p[(name, frame)]
    assert vn.timestamp == pytest.approx(vp.timestamp)
    Rn = original_viewmat(vn.camera.viewmat, n3dv.normalization)[:3, :3]
    Rp = original_viewmat(vp.camera.viewmat, pano.normalization)[:3, :3]
    H = vp.camera.K @ Rp @ Rn.T @ np.linalg.inv(vn.camera.K)  # N3DV pixel → Panoptic pixel
    warped = warp_to(vp.image().astype(np.float64), H, vn.camera.width, vn.camera.height)
    b = 8  # border pixels may map outside the Panoptic image
    mse = np.mean((warped[b:-b, b:-b] - vn.image()[b:-b, b:-b]) ** 2)
    psnr = -10 * np.log10(mse)
    print(f"camera {name} frame {frame}: {psnr:.2f} dB")
    assert psnr > 30.0, f"camera {name} frame {frame}: {psnr:.2f} dB"
    # a one-frame offset must be detectable: the other frame agrees less
    other = views_n[(f"cam{int(name):02d}", 1 - frame)].image()
    assert np.mean((warped[b:-b, b:-b] - other[b:-b, b:-b]) ** 2) > mse
