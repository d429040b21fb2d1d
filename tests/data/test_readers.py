"""Readers on the real shared scenes: counts, shapes, time ranges, splits, intrinsics, pixels,
the normalized world (against an independent transcription of n3v2blender), the frame cache
and initial points. Expected values come from the raw files (numpy/PyAV/PIL/json), never
from the readers themselves."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import av
import numpy as np
import pytest
from PIL import Image

from omg4.data import PointCloud, load_scene, random_initial_points, read_ply, write_ply
from omg4.data import frame_cache as frame_cache_module
from omg4.data.normalize import official_normalization
from omg4.errors import DataError


# ----------------------------------------------------------------------------- shared functions


def raw_frames(video: Path, count: int) -> np.ndarray:
    """uint8 [count, H, W, 3] decoded with PyAV directly."""
    out = []
    with av.open(str(video)) as c:
        for frame in c.decode(video=0):
            out.append(frame.to_ndarray(format="rgb24"))
            if len(out) == count:
                break
    return np.stack(out)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10.0 * np.log10(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)))


def camtoworld_opengl(viewmat: np.ndarray) -> np.ndarray:
    c2w = np.linalg.inv(viewmat)
    return c2w @ np.diag([1.0, -1.0, -1.0, 1.0])


def n3v2blender_reference(poses_bounds: np.ndarray) -> np.ndarray:
    """[N, 4, 4] OpenGL camera-to-world in the normalized world, transcribed step by step from the
    official ``n3v2blender.py`` (rt4dgs §4.1) with explicit loops."""
    poses = poses_bounds[:, :15].reshape(-1, 3, 5)
    out = []
    for p in poses:
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = p[:, 1], p[:, 0], -p[:, 2], p[:, 3]
        m[:3, 1] *= -1
        m[:3, 2] *= -1
        m = m[[1, 0, 2, 3], :]
        m[2, :] *= -1
        out.append(m)
    poses = np.stack(out)
    up = poses[:, :3, 1].sum(0)
    up /= np.linalg.norm(up)
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(up, z), up @ z
    kmat = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    R = np.eye(4)
    R[:3, :3] = np.eye(3) + kmat + kmat @ kmat * ((1 - c) / (v @ v + 1e-10))
    poses = np.stack([R @ p for p in poses])
    totw, totp = 0.0, np.zeros(3)
    for i in range(len(poses)):
        for j in range(i + 1, len(poses)):
            oa, da = poses[i, :3, 3], poses[i, :3, 2] / np.linalg.norm(poses[i, :3, 2])
            ob, db = poses[j, :3, 3], poses[j, :3, 2] / np.linalg.norm(poses[j, :3, 2])
            cr = np.cross(da, db)
            denom = cr @ cr
            t = ob - oa
            ta = min(np.linalg.det(np.stack([t, db, cr])) / (denom + 1e-10), 0.0)
            tb = min(np.linalg.det(np.stack([t, da, cr])) / (denom + 1e-10), 0.0)
            if denom > 0.01:
                totp += (oa + ta * da + ob + tb * db) * 0.5 * denom
                totw += denom
    poses[:, :3, 3] -= totp / totw
    poses[:, :3, 3] *= 4.0 / np.linalg.norm(poses[:, :3, 3], axis=-1).mean()
    return poses


# ----------------------------------------------------------------------------- N3DV


def test_n3dv_counts_times_intrinsics_and_pixels(n3dv_basketball, tmp_path):
    pb = np.load(n3dv_basketball / "poses_bounds.npy")
    scene = load_scene(n3dv_basketball, frames=range(1, 4), cameras=["cam00", "cam03", "cam07"], cache_dir=tmp_path,
                       progress=False)
    assert scene.format == "n3dv" and scene.num_frames == 3
    assert len(scene.train_views) == 2 * 3 and len(scene.test_views) == 3
    assert {v.camera.name for v in scene.test_views} == {"cam00"}
    assert [c.name for c in scene.train_cameras()] == ["cam03", "cam07"]
    assert sorted(v.timestamp for v in scene.test_views) == pytest.approx([1 / 30, 2 / 30, 3 / 30])
    assert scene.time_range == pytest.approx((1 / 30, 4 / 30))
    for cam in scene.train_cameras() + scene.test_cameras():
        row = int(cam.name[3:])
        h, w, f = pb[row, 4], pb[row, 9], pb[row, 14]
        assert (cam.width, cam.height) == (int(w), int(h)) == (640, 360)
        np.testing.assert_allclose(cam.K, [[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], rtol=1e-12)
    raw = raw_frames(n3dv_basketball / "cam07.mp4", 4)
    view = next(v for v in scene.train_views if v.camera.name == "cam07" and v.frame_index == 2)
    img = view.image()
    assert img.dtype == np.float32 and img.shape == (360, 640, 3)
    np.testing.assert_array_equal(np.rint(img * 255).astype(np.uint8), raw[2])


def test_n3dv_full_summary_without_decoding(n3dv_basketball, tmp_path):
    scene = load_scene(n3dv_basketball, cache_dir=tmp_path, decode=False)
    assert len(scene.train_cameras()) == 30 and len(scene.test_cameras()) == 1
    assert len(scene.train_views) == 30 * 60 and len(scene.test_views) == 60
    assert scene.num_frames == 60 and scene.time_range == pytest.approx((0.0, 2.0))
    assert list(tmp_path.iterdir()) == []  # nothing decoded


def test_n3dv_normalization_matches_official_script(n3dv_basketball, tmp_path):
    pb = np.load(n3dv_basketball / "poses_bounds.npy")
    expected = n3v2blender_reference(pb)
    scene = load_scene(n3dv_basketball, frames=range(0, 1), cache_dir=tmp_path, decode=False)
    cams = {c.name: c for c in scene.train_cameras() + scene.test_cameras()}
    for i in range(len(pb)):
        np.testing.assert_allclose(camtoworld_opengl(cams[f"cam{i:02d}"].viewmat), expected[i], atol=1e-9)


def test_n3dv_downscale_and_width(n3dv_basketball, tmp_path):
    full = load_scene(n3dv_basketball, frames=[0], cameras=["cam04"], cache_dir=tmp_path, progress=False)
    half = load_scene(n3dv_basketball, frames=[0], cameras=["cam04"], downscale=2, cache_dir=tmp_path, progress=False)
    by_width = load_scene(n3dv_basketball, frames=[0], cameras=["cam04"], width=320, cache_dir=tmp_path,
                          progress=False)
    cf, ch = full.train_views[0].camera, half.train_views[0].camera
    assert (ch.width, ch.height) == (320, 180)
    np.testing.assert_allclose(ch.K[:2], cf.K[:2] / 2)
    assert by_width.train_views[0].camera.width == 320 and by_width.train_views[0].camera.height == 180
    img = half.train_views[0].image()
    assert img.shape == (180, 320, 3)
    box = full.train_views[0].image().reshape(180, 2, 320, 2, 3).mean((1, 3))  # 2×2 box filter reference
    assert psnr(img, box) > 32
    # bicubic differs from the box filter, but not by a lot; a shifted image would fail this
    assert psnr(img[:, 1:], box[:, :-1]) < psnr(img, box) - 3
    assert len(list(tmp_path.glob("*.npy"))) == 2  # one cache per output size


def test_frame_cache_reuses_prefix_and_stores_uint8(n3dv_basketball, tmp_path):
    load_scene(n3dv_basketball, frames=range(0, 4), cameras=["cam02"], cache_dir=tmp_path, progress=False)
    (cache_file,) = tmp_path.glob("cam02-*.npy")
    stored = np.load(cache_file, mmap_mode="r")
    assert stored.dtype == np.uint8 and stored.shape == (4, 360, 640, 3)
    np.testing.assert_array_equal(stored, raw_frames(n3dv_basketball / "cam02.mp4", 4))
    stamp = cache_file.stat().st_mtime_ns
    scene = load_scene(n3dv_basketball, frames=range(1, 3), cameras=["cam02"], cache_dir=tmp_path, progress=False)
    assert cache_file.stat().st_mtime_ns == stamp  # the 4-frame prefix serves frames 1..2
    assert scene.train_views[0].image().dtype == np.float32
    load_scene(n3dv_basketball, frames=range(0, 6), cameras=["cam02"], cache_dir=tmp_path, progress=False)
    assert np.load(cache_file, mmap_mode="r").shape[0] == 6  # longer prefix replaces the file
    assert len(list(tmp_path.iterdir())) == 1


def test_frame_cache_env_var(n3dv_basketball, tmp_path, monkeypatch):
    monkeypatch.setenv("OMG4_CACHE_DIR", str(tmp_path / "envcache"))
    load_scene(n3dv_basketball, frames=[0], cameras=["cam01"], progress=False)
    assert len(list((tmp_path / "envcache").glob("cam01-*.npy"))) == 1


def test_crashed_decode_leaves_no_cache(n3dv_basketball, tmp_path, monkeypatch):
    calls = {"n": 0}
    real_resize = frame_cache_module.resize_rgb

    def failing_resize(img, w, h):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt  # a user interrupt in the middle of decoding
        return real_resize(img, w, h)

    monkeypatch.setattr(frame_cache_module, "resize_rgb", failing_resize)
    with pytest.raises(KeyboardInterrupt):
        load_scene(n3dv_basketball, frames=range(0, 5), cameras=["cam01"], cache_dir=tmp_path, progress=False)
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setattr(frame_cache_module, "resize_rgb", real_resize)
    scene = load_scene(n3dv_basketball, frames=range(0, 5), cameras=["cam01"], cache_dir=tmp_path, progress=False)
    assert scene.train_views[4].image().shape == (360, 640, 3)


# ----------------------------------------------------------------------------- Panoptic


def test_panoptic_counts_splits_and_pixels(panoptic_basketball):
    meta_test = json.loads((panoptic_basketball / "test_meta.json").read_text())
    scene = load_scene(panoptic_basketball, frames=range(0, 2))
    assert scene.format == "panoptic" and scene.num_frames == 2
    assert len(scene.train_cameras()) == 27 and len(scene.train_views) == 54
    assert [c.name for c in scene.test_cameras()] == ["0", "10", "15", "30"] and len(scene.test_views) == 8
    assert scene.time_range == pytest.approx((0.0, 2 / 30))
    view = next(v for v in scene.test_views if v.camera.name == "10" and v.frame_index == 1)
    assert view.timestamp == pytest.approx(1 / 30)
    np.testing.assert_allclose(view.camera.K, meta_test["k"][1][1])
    expected = np.asarray(Image.open(panoptic_basketball / "ims" / meta_test["fn"][1][1]), dtype=np.float32) / 255
    np.testing.assert_allclose(view.image(), expected, atol=1e-6)
    full = load_scene(panoptic_basketball)
    assert full.num_frames == 60 and full.time_range == pytest.approx((0.0, 2.0))
    assert len(full.train_views) == 27 * 60 and len(full.test_views) == 4 * 60


def test_panoptic_camera_subset_keeps_world(panoptic_basketball):
    full = load_scene(panoptic_basketball, frames=[0])
    sub = load_scene(panoptic_basketball, frames=[0], cameras=["3", "15"])
    assert [c.name for c in sub.train_cameras()] == ["3"] and [c.name for c in sub.test_cameras()] == ["15"]
    np.testing.assert_allclose(sub.normalization.rotation, full.normalization.rotation)
    assert sub.normalization.scale == pytest.approx(full.normalization.scale)


# ----------------------------------------------------------------------------- D-NeRF / Blender


def test_dnerf_counts_times_intrinsics(dnerf_mutant):
    train_json = json.loads((dnerf_mutant / "transforms_train.json").read_text())
    scene = load_scene(dnerf_mutant, downscale=2)
    assert scene.format == "blender"
    assert len(scene.train_views) == 150 and len(scene.test_views) == 20
    assert scene.time_range == (0.0, 1.0)
    times = sorted({f["time"] for name in ("train", "test")
                    for f in json.loads((dnerf_mutant / f"transforms_{name}.json").read_text())["frames"]})
    assert scene.num_frames == len(times)
    assert [v.timestamp for v in scene.train_views] == [f["time"] for f in train_json["frames"]]
    focal = 0.5 * 400 / math.tan(0.5 * train_json["camera_angle_x"])
    cam = scene.train_views[0].camera
    assert (cam.width, cam.height) == (400, 400)
    np.testing.assert_allclose(cam.K, [[focal, 0, 200], [0, focal, 200], [0, 0, 1]], rtol=1e-9)
    # D-NeRF is already up +z, centred, radius ≈ 4: "auto" keeps its world (official checkpoints)
    assert scene.normalization.scale == 1.0
    c2w = np.array(train_json["frames"][5]["transform_matrix"])
    np.testing.assert_allclose(camtoworld_opengl(scene.train_views[5].camera.viewmat), c2w, atol=1e-9)
    assert scene.test_views[0].image().shape == (400, 400, 3)


def test_dnerf_alpha_compositing(dnerf_mutant):
    frame = json.loads((dnerf_mutant / "transforms_test.json").read_text())["frames"][3]
    rgba = np.asarray(Image.open(dnerf_mutant / (frame["file_path"] + ".png")).convert("RGBA"), dtype=np.float64) / 255
    black = load_scene(dnerf_mutant, cameras=[frame["file_path"][2:]]).test_views[0].image()
    white = load_scene(dnerf_mutant, cameras=[frame["file_path"][2:]], background=(1, 1, 1)).test_views[0].image()
    alpha = rgba[..., 3:]
    assert 0.05 < (alpha < 1).mean() < 0.95  # both foreground and background pixels exist
    np.testing.assert_allclose(black, rgba[..., :3] * alpha, atol=1 / 255 + 1e-6)
    np.testing.assert_allclose(white - black, np.broadcast_to(1 - alpha, black.shape), atol=2 / 255 + 1e-6)


def test_forced_normalization_properties(dnerf_mutant, panoptic_basketball):
    """Normalized world: mean camera distance 4, summed camera up ∥ +z, axes' focus at the origin
    (closest points solved as a 2×2 least-squares system, an independent formula)."""
    for scene in (load_scene(dnerf_mutant, normalize=True), load_scene(panoptic_basketball, frames=[0])):
        cams = scene.train_cameras() + scene.test_cameras()
        c2w = np.stack([np.linalg.inv(c.viewmat) for c in cams])
        centers, fwd = c2w[:, :3, 3], c2w[:, :3, 2]
        assert np.linalg.norm(centers, axis=1).mean() == pytest.approx(4.0, rel=1e-9)
        up = (-c2w[:, :3, 1]).sum(0)
        np.testing.assert_allclose(up / np.linalg.norm(up), [0, 0, 1], atol=1e-9)
        num, den = np.zeros(3), 0.0
        for i in range(len(cams)):
            for j in range(i + 1, len(cams)):
                A = np.stack([fwd[i], -fwd[j]], axis=1)
                s, u = np.linalg.lstsq(A, centers[j] - centers[i], rcond=None)[0]
                w = np.linalg.norm(np.cross(fwd[i], fwd[j])) ** 2
                if w > 0.01:
                    num += w * 0.5 * (centers[i] + max(s, 0) * fwd[i] + centers[j] + max(u, 0) * fwd[j])
                    den += w
        np.testing.assert_allclose(num / den, 0.0, atol=1e-7)


def test_normalization_on_a_known_rig():
    """Eight cameras on a tilted circle of radius 3 around (5, −2, 1), all looking at it."""
    center, axis = np.array([5.0, -2.0, 1.0]), np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    e1 = np.cross(axis, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    c2ws = []
    for a in np.linspace(0, 2 * np.pi, 8, endpoint=False):
        pos = center + 3.0 * (np.cos(a) * e1 + np.sin(a) * e2) + 0.5 * axis
        fwd = (center - pos) / np.linalg.norm(center - pos)
        right = np.cross(fwd, axis)
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, down, fwd, pos
        c2ws.append(m)
    norm = official_normalization(np.stack(c2ws))
    assert norm.scale == pytest.approx(4.0 / math.sqrt(3.0**2 + 0.5**2))
    np.testing.assert_allclose(norm.apply_points(center), 0.0, atol=1e-9)
    np.testing.assert_allclose(norm.rotation @ axis, [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(norm.rotation @ norm.rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(norm.rotation) == pytest.approx(1.0)


def test_normalization_matches_official_script_on_a_dense_arc():
    """A forward-facing arc with 1.5° spacing: neighbouring axes are nearly parallel (pair weight
    below 0.01, skipped), distant ones are not; LLFF rows as N3DV stores them."""
    rows = []
    for k, a in enumerate(np.radians(np.arange(-12, 12.1, 1.5))):
        fwd = np.array([np.sin(a), 0.1, np.cos(a)])
        fwd /= np.linalg.norm(fwd)
        down = np.array([0.0, 1.0, 0.0]) - fwd[1] * fwd
        down /= np.linalg.norm(down)
        right = np.cross(down, fwd)
        pos = np.array([3.0 * np.sin(a) + 0.2, -0.5 + 0.05 * k, -3.0 * np.cos(a) + 1.0])
        pose = np.stack([down, right, -fwd, pos, [360.0, 640.0, 500.0]], axis=1)  # LLFF [down, right, back, t, hwf]
        rows.append(np.concatenate([pose.ravel(), [0.5, 20.0]]))
    pb = np.stack(rows)
    from omg4.data.n3dv import llff_to_opencv

    c2w, _ = llff_to_opencv(pb)
    norm = official_normalization(c2w)
    got = np.stack([camtoworld_opengl(norm.apply_viewmat(np.linalg.inv(m))) for m in c2w])
    np.testing.assert_allclose(got, n3v2blender_reference(pb), atol=1e-9)


# ----------------------------------------------------------------------------- points


def test_ply_roundtrip_and_formats(tmp_path):
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(50, 3))
    rgb = rng.integers(0, 256, size=(50, 3)) / 255.0
    write_ply(tmp_path / "a.ply", PointCloud(xyz=xyz, rgb=rgb))
    back = read_ply(tmp_path / "a.ply")
    np.testing.assert_allclose(back.xyz, xyz.astype(np.float32))
    np.testing.assert_allclose(back.rgb, rgb, atol=1e-6)
    (tmp_path / "b.ply").write_text("ply\nformat ascii 1.0\ncomment x\nelement vertex 2\nproperty double x\n"
                                    "property double y\nproperty double z\nproperty float nx\nproperty uchar red\n"
                                    "property uchar green\nproperty uchar blue\nend_header\n"
                                    "1 2 3 0 255 0 51\n-1.5 0 2e-1 1 0 102 255\n")
    b = read_ply(tmp_path / "b.ply")
    np.testing.assert_allclose(b.xyz, [[1, 2, 3], [-1.5, 0, 0.2]])
    np.testing.assert_allclose(b.rgb, [[1, 0, 0.2], [0, 0.4, 1]], atol=1e-6)
    body = np.array([(1.0, 2.0, 3.0), (4.0, 5.0, 6.0)], dtype=[("x", ">f8"), ("y", ">f8"), ("z", ">f8")])
    (tmp_path / "c.ply").write_bytes(b"ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty double x\n"
                                     b"property double y\nproperty double z\nend_header\n" + body.tobytes())
    c = read_ply(tmp_path / "c.ply")
    np.testing.assert_allclose(c.xyz, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_allclose(c.rgb, 0.5)  # no colours: grey
    (tmp_path / "d.ply").write_bytes((tmp_path / "a.ply").read_bytes()[:-20])
    with pytest.raises(DataError, match="truncated"):
        read_ply(tmp_path / "d.ply")


def test_points3d_ply_is_mapped_into_the_normalized_world(panoptic_basketball, tmp_path):
    folder = tmp_path / "pano"
    folder.mkdir()
    for name in ("train_meta.json", "test_meta.json", "ims"):
        os.symlink(panoptic_basketball / name, folder / name)
    xyz = np.array([[0.0, 0.0, 0.0], [1.0, -2.0, 3.0], [0.5, 0.5, 4.0]])
    write_ply(folder / "points3d.ply", PointCloud(xyz=xyz, rgb=np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1]])))
    scene = load_scene(folder, frames=[0])
    n = scene.normalization
    expected = n.scale * (xyz.astype(np.float32).astype(np.float64) @ n.rotation.T + n.translation)
    np.testing.assert_allclose(scene.initial_points.xyz, expected, atol=1e-12)
    np.testing.assert_allclose(scene.initial_points.rgb, np.eye(3))
    same = load_scene(folder, frames=[0], points_world="normalized")
    np.testing.assert_allclose(same.initial_points.xyz, xyz, atol=1e-6)


def test_random_initial_points_in_common_view(panoptic_basketball):
    scene = load_scene(panoptic_basketball, frames=[0])
    pts = random_initial_points(scene, 3000, seed=3)
    again = random_initial_points(scene, 3000, seed=3)
    assert pts.xyz.shape == (3000, 3) and pts.rgb.shape == (3000, 3)
    np.testing.assert_array_equal(pts.xyz, again.xyz)
    assert not np.array_equal(pts.xyz, random_initial_points(scene, 3000, seed=4).xyz)
    assert (np.abs(pts.rgb - 0.5) <= 0.05 + 1e-7).all()
    seen = np.zeros(len(pts.xyz), dtype=int)
    for cam in scene.train_cameras():  # brute-force projection per camera
        x = pts.xyz @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
        u = cam.K[0, 0] * x[:, 0] / x[:, 2] + cam.K[0, 2]
        v = cam.K[1, 1] * x[:, 1] / x[:, 2] + cam.K[1, 2]
        seen += (x[:, 2] >= 0.2) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    assert seen.min() >= 2
    assert seen.mean() > 5  # the common view volume, not the fringe
    near = random_initial_points(scene, 2000, seed=0, near=3.0, far=5.0, min_views=3)
    depth_ok = np.zeros(len(near.xyz), dtype=int)
    for cam in scene.train_cameras():
        x = near.xyz @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
        u = cam.K[0, 0] * x[:, 0] / x[:, 2] + cam.K[0, 2]
        v = cam.K[1, 1] * x[:, 1] / x[:, 2] + cam.K[1, 2]
        depth_ok += (x[:, 2] >= 3.0) & (x[:, 2] <= 5.0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    assert depth_ok.min() >= 3
