"""The built-in synthetic scene (``omg4 synth``): layout, determinism, geometry, dynamics, errors.

Geometry is checked against an independent reading of ``poses_bounds.npy`` (LLFF
[down, right, back] → OpenCV [right, down, forward], rt4dgs §4.1) and
an independent PLY parser; frames are checked by decoding the videos with PyAV.
"""

from __future__ import annotations

import json
from pathlib import Path

import av
import numpy as np
import pytest

from omg4.app.cli import main
from omg4.data import load_scene
from omg4.data.synthetic import SynthConfig, SyntheticScene, box_filter, camera_rays, write_synthetic_scene
from omg4.errors import OMG4Error

TINY = SynthConfig(seed=3, num_cameras=4, num_frames=6, width=64, height=48, num_points=500)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "scene"
    write_synthetic_scene(out, TINY, progress=False)
    return out


def decode(path: Path) -> list[np.ndarray]:
    """All frames of a video as uint8 [H, W, 3]."""
    with av.open(str(path)) as c:
        return [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]


def llff_to_opencv(row: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int]:
    """(K [3, 3], world-to-camera [4, 4], W, H) of one poses_bounds row, written from the
    LLFF convention (rt4dgs §4.1): c2w columns [down, right, back] → [right, down, forward]; cx = W/2, cy = H/2."""
    m = row[:15].reshape(3, 5)
    H, W, f = m[:, 4]
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = m[:, 1], m[:, 0], -m[:, 2], m[:, 3]
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    return K, np.linalg.inv(c2w), int(W), int(H)


def project(K: np.ndarray, w2c: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates [M, 2] (centres at +0.5) and z-depths [M] of world points X [M, 3]."""
    Xc = X @ w2c[:3, :3].T + w2c[:3, 3]
    return (Xc[:, :2] / Xc[:, 2:3]) @ K[:2, :2].T + K[:2, 2], Xc[:, 2]


def read_ply(path: Path) -> np.ndarray:
    """Structured array of a binary little-endian PLY with float x,y,z and uchar red,green,blue."""
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:end].decode("ascii").splitlines()
    assert header[:2] == ["ply", "format binary_little_endian 1.0"]
    count = int(next(h for h in header if h.startswith("element vertex")).split()[-1])
    props = [h.split()[1:] for h in header if h.startswith("property")]
    assert props == [["float", "x"], ["float", "y"], ["float", "z"],
                     ["uchar", "red"], ["uchar", "green"], ["uchar", "blue"]]
    dtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    assert len(raw) - end == count * 15
    return np.frombuffer(raw[end:], dtype=dtype)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(np.mean((a.astype(np.float64) - b) ** 2)))


def test_layout(tiny):
    names = sorted(p.name for p in tiny.iterdir())
    assert names == ["cam00.mp4", "cam01.mp4", "cam02.mp4", "cam03.mp4", "points3d.ply", "poses_bounds.npy",
                     "synth.json"]
    pb = np.load(tiny / "poses_bounds.npy")
    assert pb.shape == (4, 17) and pb.dtype == np.float64
    for i in range(4):
        with av.open(str(tiny / f"cam{i:02d}.mp4")) as c:
            s = c.streams.video[0]
            assert s.codec_context.name == "h264" and s.codec_context.pix_fmt == "yuv420p"
            assert s.average_rate == 30
        frames = decode(tiny / f"cam{i:02d}.mp4")
        assert len(frames) == 6 and frames[0].shape == (48, 64, 3)
        K, _, W, H = llff_to_opencv(pb[i])
        assert (W, H) == (64, 48) and 30 < K[0, 0] < 100  # ~55° horizontal field of view
        assert 0 < pb[i, 15] < pb[i, 16]  # near < far
        assert b"bframes=0" in (tiny / f"cam{i:02d}.mp4").read_bytes()  # written reproducibly (x264's own record)
    meta = json.loads((tiny / "synth.json").read_text())
    assert meta["seed"] == 3 and meta["num_frames"] == 6 and meta["fps"] == 30
    assert len(read_ply(tiny / "points3d.ply")) == 500
    assert not [p for p in tiny.parent.iterdir() if p.name.startswith(".")]  # no temporary folder left


def test_determinism(tiny, tmp_path):
    write_synthetic_scene(tmp_path / "same", TINY, progress=False)
    write_synthetic_scene(tmp_path / "other", SynthConfig(**{**TINY.__dict__, "seed": 4}), progress=False)
    pb = np.load(tiny / "poses_bounds.npy")
    assert np.array_equal(pb, np.load(tmp_path / "same" / "poses_bounds.npy"))
    assert np.array_equal(decode(tiny / "cam01.mp4")[0], decode(tmp_path / "same" / "cam01.mp4")[0])
    assert (tiny / "points3d.ply").read_bytes() == (tmp_path / "same" / "points3d.ply").read_bytes()
    assert np.abs(pb[:, :15] - np.load(tmp_path / "other" / "poses_bounds.npy")[:, :15]).max() > 1e-3
    diff = np.abs(decode(tiny / "cam01.mp4")[0].astype(int) - decode(tmp_path / "other" / "cam01.mp4")[0])
    assert diff.mean() > 10


def test_poses_match_ray_caster(tiny):
    """Every surface point the ray caster hit projects, through the cameras read back from
    poses_bounds.npy, onto the centre of the sample that saw it; the scene centre projects
    near the image centre and the ground is at the bottom of the image."""
    scene = SyntheticScene(TINY)
    pb = np.load(tiny / "poses_bounds.npy")
    s = TINY.supersample
    for i in range(TINY.num_cameras):
        K, w2c, W, H = llff_to_opencv(pb[i])
        hits = scene.render_samples(i, 0)
        origin, dirs = camera_rays(scene.cameras[i], s)
        X = (origin + hits.t[..., None] * dirs).reshape(-1, 3).astype(np.float64)
        uv, z = project(K, w2c, X)
        jj, ii = np.meshgrid((np.arange(W * s) + 0.5) / s, (np.arange(H * s) + 0.5) / s)
        expected = np.stack([jj, ii], -1).reshape(-1, 2)
        assert np.all(np.isfinite(hits.t)) and np.all(z > 0)
        np.testing.assert_allclose(uv, expected, atol=2e-3)
        centre, _ = project(K, w2c, np.array([[0.0, 0.5, 0.6]]))  # the point the rig looks at
        assert np.abs(centre[0] - [W / 2, H / 2]).max() < 0.08 * W
        assert abs(X.reshape(H * s, W * s, 3)[-1, W * s // 2, 2]) < 1e-3  # bottom centre: ground z = 0
        assert X.reshape(H * s, W * s, 3)[0, W * s // 2, 2] > 1.0  # top centre: backdrop, above


def test_rays_from_file_reproduce_video(tiny):
    """Rays built from poses_bounds.npy alone, shaded by the ray caster, give the decoded
    frames (up to H.264/yuv420p loss); a wrong axis convention does not."""
    scene = SyntheticScene(TINY)
    pb = np.load(tiny / "poses_bounds.npy")
    s = TINY.supersample

    def render_from(K, w2c, W, H, frame):
        c2w = np.linalg.inv(w2c)
        u, v = np.meshgrid((np.arange(W * s) + 0.5) / s, (np.arange(H * s) + 0.5) / s)
        d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ c2w[:3, :3].T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return box_filter(scene.cast(c2w[:3, 3], d, scene.phase(frame)).rgb, s)

    for i in (0, 2):
        video = decode(tiny / f"cam{i:02d}.mp4")
        K, w2c, W, H = llff_to_opencv(pb[i])
        for frame in (0, 4):
            assert psnr(video[frame] / 255.0, render_from(K, w2c, W, H, frame)) > 27
        flipped = w2c.copy()
        flipped[:2] *= -1  # OpenGL-style camera axes read as OpenCV: image rotated by 180°
        assert psnr(video[0] / 255.0, render_from(K, flipped, W, H, 0)) < 20


def test_fast_path_equals_brute_force():
    """The per-camera static layer + screen-rectangle culling equals casting every primitive on every ray."""
    scene = SyntheticScene(SynthConfig(seed=5, num_cameras=5, num_frames=8, width=48, height=32))
    for i, frame in [(0, 0), (1, 3), (4, 7), (2, 5)]:
        fast = scene.render_samples(i, frame)
        ref = scene.cast(*camera_rays(scene.cameras[i], 2), scene.phase(frame))
        np.testing.assert_array_equal(fast.t, ref.t)
        np.testing.assert_allclose(fast.rgb, ref.rgb, atol=1e-5)


def test_points_on_visible_surfaces(tiny):
    """Each PLY point is a frame-0 surface sample of a training camera: read back through
    poses_bounds.npy it projects onto a sample centre whose depth and colour it carries."""
    scene = SyntheticScene(TINY)
    pb = np.load(tiny / "poses_bounds.npy")
    ply = read_ply(tiny / "points3d.ply")
    X = np.stack([ply["x"], ply["y"], ply["z"]], -1).astype(np.float64)
    rgb = np.stack([ply["red"], ply["green"], ply["blue"]], -1)
    s = TINY.supersample
    found = np.zeros(len(X), bool)
    for i in range(1, TINY.num_cameras):  # training cameras only (cam00 is the test camera)
        K, w2c, W, H = llff_to_opencv(pb[i])
        hits = scene.render_samples(i, 0)
        uv, z = project(K, w2c, X)
        grid = uv * s - 0.5  # sample indices when the point is a sample centre
        on_sample = np.all(np.abs(grid - np.round(grid)) < 1e-2, axis=1)
        on_sample &= np.all((grid > -0.5) & (grid < [W * s - 0.5, H * s - 0.5]), axis=1)
        jj, ii = np.round(grid[on_sample]).astype(int).T
        dist = np.linalg.norm(X[on_sample] - np.linalg.inv(w2c)[:3, 3], axis=1)
        match = np.abs(dist - hits.t[ii, jj]) < 1e-3 * dist
        match &= np.all(np.abs(np.round(hits.rgb[ii, jj] * 255) - rgb[on_sample]) <= 1, axis=1)
        idx = np.nonzero(on_sample)[0][match]
        assert np.all((z[idx] > pb[i, 15]) & (z[idx] < pb[i, 16]))  # inside the near/far bounds
        found[idx] = True
    assert found.all()


def test_static_and_dynamic_pixels(tiny):
    frames = np.stack(decode(tiny / "cam00.mp4")).astype(int)
    change = np.abs(frames - frames[:1]).max(axis=(0, 3))  # [H, W] largest change from frame 0
    assert (change <= 6).mean() > 0.4  # static background (only coding noise)
    assert (change > 60).mean() > 0.05  # moving objects


def test_bad_config_values():
    for bad, word in [(dict(num_cameras=1), "--cameras"), (dict(width=63), "--width"), (dict(height=0), "--height"),
                      (dict(num_frames=0), "--frames"), (dict(fps=-1.0), "--fps"), (dict(seed=-2), "--seed"),
                      (dict(fps=float("nan")), "--fps"), (dict(crf=60), "--crf")]:
        with pytest.raises(OMG4Error, match=word) as info:
            SynthConfig(**bad).validate()
        assert "\n" not in str(info.value)


def test_cli_errors_and_overwrite(tmp_path, capsys):
    out = tmp_path / "scene"
    assert main(["synth", str(out), "--width", "63"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--width" in err and err.startswith("omg4 synth: error:")
    assert not out.exists()

    out.mkdir()
    (out / "keep.txt").write_text("x")
    assert main(["synth", str(out), "--cameras", "2", "--frames", "2", "--width", "32", "--height", "32"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "not empty" in err and "--force" in err
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]

    args = ["synth", str(out), "--cameras", "2", "--frames", "2", "--width", "32", "--height", "32", "--force"]
    assert main(args) == 0
    assert "wrote 2 cameras" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["cam00.mp4", "cam01.mp4", "points3d.ply", "poses_bounds.npy",
                                                     "synth.json"]
    assert [p.name for p in tmp_path.iterdir()] == ["scene"]


def test_interrupted_write_leaves_nothing(tmp_path, monkeypatch):
    calls = []

    def failing(self, index, frame, layer=None):
        calls.append(frame)
        if len(calls) > 3:
            raise KeyboardInterrupt
        return original(self, index, frame, layer)

    original = SyntheticScene.render_samples
    monkeypatch.setattr(SyntheticScene, "render_samples", failing)
    with pytest.raises(KeyboardInterrupt):
        write_synthetic_scene(tmp_path / "scene", SynthConfig(num_cameras=2, num_frames=3, width=32, height=32),
                              progress=False)
    assert list(tmp_path.iterdir()) == []


def test_reads_back_as_n3dv_scene(tiny):
    """The N3DV reader sees cam00 as the test camera, all frames, and cameras that project
    the ray caster's surface points onto the samples that saw them (in its normalized world)."""
    loaded = load_scene(tiny)
    assert [c.name for c in loaded.test_cameras()] == ["cam00"]
    assert sorted(c.name for c in loaded.train_cameras()) == ["cam01", "cam02", "cam03"]
    assert loaded.num_frames == 6 and len(loaded.test_views) == 6 and len(loaded.train_views) == 18
    view = next(v for v in loaded.train_views if v.camera.name == "cam02" and v.frame_index == 4)
    assert view.timestamp == pytest.approx(4 / 30)
    np.testing.assert_allclose(view.image(), decode(tiny / "cam02.mp4")[4] / 255.0, atol=1.5 / 255)
    scene = SyntheticScene(TINY)
    cam = view.camera
    hits = scene.render_samples(2, 0)
    origin, dirs = camera_rays(scene.cameras[2], 2)
    X = loaded.normalization.apply_points((origin + hits.t[..., None] * dirs).reshape(-1, 3).astype(np.float64))
    uv, _ = project(cam.K, cam.viewmat, X)
    jj, ii = np.meshgrid((np.arange(64 * 2) + 0.5) / 2, (np.arange(48 * 2) + 0.5) / 2)
    np.testing.assert_allclose(uv, np.stack([jj, ii], -1).reshape(-1, 2), atol=1e-2)
