"""Camera paths of free-viewpoint videos: geometry of orbit, spiral and dataset paths; ``omg4 render --path``."""

import json

import av
import numpy as np
import pytest

from omg4.app.cli import main
from omg4.data.scene import Camera, look_at_viewmat
from omg4.errors import OMG4Error
from omg4.render.paths import bounds_camera, camera_path, faces_forward
from omg4.testing import forge

K = np.array([[80.0, 0.0, 40.0], [0.0, 80.0, 30.0], [0.0, 0.0, 1.0]])
FOCUS = np.array([0.3, -0.2, 0.5])


def rig(n=6):
    """Cameras on an arc (radius 4, heights 1.0–1.5) in front of FOCUS, all looking at it, +z up."""
    cams = []
    for i, a in enumerate(np.linspace(-0.6, 0.6, n)):
        centre = FOCUS + np.array([4 * np.sin(a), -4 * np.cos(a), 1.0 + 0.1 * i])
        cams.append(Camera(K=K, viewmat=look_at_viewmat(centre, FOCUS), width=80, height=60, name=f"cam{i:02d}"))
    return cams


def projects_to_centre(cam, point):
    p = cam.viewmat[:3, :3] @ point + cam.viewmat[:3, 3]
    return p[2] > 0 and np.allclose((cam.K @ (p / p[2]))[:2], [40.0, 30.0], atol=1e-6)


def ring(n=6):
    """Cameras all around FOCUS (radius 4, heights 1.0–1.5), looking at it: an inward-facing rig."""
    cams = []
    for i, a in enumerate(np.linspace(0.0, 2 * np.pi, n, endpoint=False)):
        centre = FOCUS + np.array([4 * np.sin(a), -4 * np.cos(a), 1.0 + 0.1 * i])
        cams.append(Camera(K=K, viewmat=look_at_viewmat(centre, FOCUS), width=80, height=60, name=f"cam{i:02d}"))
    return cams


def test_rigs_on_one_side_face_forward():
    assert faces_forward(rig()) and not faces_forward(ring()) and faces_forward(rig()[:1])


def test_orbit_of_an_inward_rig_circles_the_focus_at_its_distance_and_height():
    path = camera_path("orbit", ring(), 12)
    offsets = np.stack([c.center for c in path]) - FOCUS
    assert np.allclose(np.linalg.norm(offsets[:, :2], axis=1), 4.0, atol=1e-9)  # the rig's horizontal radius
    assert np.allclose(offsets[:, 2], np.mean(1.0 + 0.1 * np.arange(6)), atol=1e-9)  # its mean height, +z up
    angles = np.unwrap(np.arctan2(offsets[:, 1], offsets[:, 0]))
    assert np.allclose(np.diff(angles), np.diff(angles)[0]) and abs(np.diff(angles)[0]) == pytest.approx(np.pi / 6)
    assert all(projects_to_centre(c, FOCUS) for c in path)
    assert all(np.allclose(c.K, K) and (c.width, c.height) == (80, 60) for c in path)


def test_orbit_of_a_forward_facing_rig_circles_the_rig_and_sees_what_it_saw():
    """N3DV-like: every camera on one side. The orbit turns once around the rig's mean centre, in the plane facing
    the focus, at the centres' mean distance from it there, always looking at the focus."""
    cams = rig()
    path = camera_path("orbit", cams, 12)
    centres = np.stack([c.center for c in cams])
    mean = centres.mean(0)
    axis = (mean - FOCUS) / np.linalg.norm(mean - FOCUS)
    in_plane = (centres - mean) - np.outer((centres - mean) @ axis, axis)
    radius = np.linalg.norm(in_plane, axis=1).mean()
    offsets = np.stack([c.center for c in path]) - mean
    assert np.allclose(offsets @ axis, 0.0, atol=1e-9)  # in the plane through the rig's centre
    assert np.allclose(np.linalg.norm(offsets, axis=1), radius, rtol=1e-9)
    assert radius < 0.5 * np.linalg.norm(mean - FOCUS)  # near the cameras, not around the focus
    assert all(projects_to_centre(c, FOCUS) for c in path)
    assert len({round(float(np.arctan2(*o[:2])), 6) for o in offsets}) == 12  # one turn, no repeats


def test_orbit_around_one_pitched_camera_stays_level():
    """One camera looking down: the orbit still circles the vertical (+z), at the camera's height."""
    cam = rig()[0]
    focus = cam.center + np.linalg.norm(cam.center) * cam.viewmat[2, :3]  # in front, at its distance from 0
    path = camera_path("orbit", [cam], 8)
    assert np.allclose([c.center[2] for c in path], cam.center[2], atol=1e-9)
    assert np.allclose([np.linalg.norm((c.center - focus)[:2]) for c in path],
                       np.linalg.norm((cam.center - focus)[:2]), atol=1e-9)
    assert all(projects_to_centre(c, focus) for c in path)


def test_spiral_stays_around_the_mean_camera_facing_the_focus():
    cams = rig()
    path = camera_path("spiral", cams, 16)
    mean = np.mean([c.center for c in cams], axis=0)
    spread = max(np.linalg.norm(c.center - mean) for c in cams)
    centres = np.stack([c.center for c in path])
    assert np.all(np.linalg.norm(centres - mean, axis=1) <= spread + 1e-9)
    assert np.ptp(centres, axis=0).max() > 0.5 * spread  # it moves
    assert all(projects_to_centre(c, FOCUS) for c in path)


def test_dataset_path_runs_through_the_cameras_in_azimuth_order():
    cams = rig()
    shuffled = [cams[i] for i in (3, 0, 5, 1, 4, 2)]
    path = camera_path("dataset", shuffled, 11)  # 11 frames: cameras every 2 frames
    for k, cam in enumerate(cams):
        np.testing.assert_allclose(path[2 * k].viewmat, cam.viewmat, atol=1e-9)
    with pytest.raises(OMG4Error, match="at least two cameras"):
        camera_path("dataset", cams[:1], 5)
    with pytest.raises(OMG4Error, match="at least two cameras"):
        camera_path("spiral", cams[:1], 5)


def test_bounds_camera_frames_the_points():
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(500, 3)) * 0.5 + FOCUS
    cam = bounds_camera(xyz, 64, 48)
    p = xyz @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
    uv = (p @ cam.K.T)[:, :2] / p[:, 2:]
    inside = (p[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < 64) & (uv[:, 1] >= 0) & (uv[:, 1] < 48)
    assert inside.mean() > 0.8


def test_render_path_writes_a_moving_video(tmp_path):
    model = tmp_path / "m.omg4"
    forge.valid_file(model, 300, seed=2, codebook_scale=0.3)
    from omg4.models import load_model

    camera = bounds_camera(load_model(model).values["xyz"].numpy(), 64, 48)
    (tmp_path / "cam.json").write_text(json.dumps(camera.to_json()))
    out = tmp_path / "orbit.mp4"
    assert main(["render", "--model", str(model), "--camera", str(tmp_path / "cam.json"), "--path", "orbit",
                 "--num-frames", "6", "--time-range", "0.2:0.8", "--out", str(out)]) == 0
    with av.open(str(out)) as container:
        frames = [f.to_ndarray(format="rgb24").astype(float) for f in container.decode(video=0)]
    assert len(frames) == 6 and frames[0].shape == (48, 64, 3)
    assert np.abs(frames[0] - frames[3]).mean() > 1.0  # half an orbit later the view differs
    assert main(["render", "--model", str(model), "--camera", str(tmp_path / "cam.json"), "--path", "orbit",
                 "--out", str(tmp_path / "x.png")]) == 2


@pytest.mark.parametrize("name", ["orbit", "spiral", "dataset"])
def test_every_path_keeps_the_first_cameras_intrinsics_and_size(name):
    """The module's rule: a path's cameras take the first reference camera's K and resolution, whatever the others'."""
    cams = rig()
    for i, c in enumerate(cams[1:], start=1):
        cams[i] = Camera(K=np.diag([40.0 + i, 50.0 + i, 1.0]) + np.array([[0, 0, 11.0 + i], [0, 0, 7.0 + i], [0, 0, 0]]),
                         viewmat=c.viewmat, width=64 + i, height=48 + i, name=c.name)
    path = camera_path(name, cams, 7)
    assert len(path) == 7
    assert all(np.array_equal(c.K, K) and (c.width, c.height) == (80, 60) for c in path)


def nerfstudio_path(cameras, times=None, fps=None) -> dict:
    """A nerfstudio camera_path.json of ``cameras`` (square pixels, centred principal points): OpenGL axes, vertical
    field of view in degrees."""
    entries = []
    for k, cam in enumerate(cameras):
        c2w = np.linalg.inv(cam.viewmat)
        c2w[:3, 1:3] *= -1  # OpenCV y down, z forward → OpenGL y up, z backward
        entry = {"camera_to_world": c2w.reshape(-1).tolist(), "fov": float(np.degrees(2 * np.arctan(
            cam.height / 2 / cam.K[1, 1])))}
        if times is not None:
            entry["render_time"] = times[k]
        entries.append(entry)
    path = {"render_width": cameras[0].width, "render_height": cameras[0].height, "camera_path": entries}
    return path if fps is None else {**path, "fps": fps}


def test_a_nerfstudio_camera_path_gives_back_its_cameras(tmp_path):
    from omg4.io.camera_path import read_camera_path

    cams = rig(4)
    (tmp_path / "path.json").write_text(json.dumps(nerfstudio_path(cams, times=[0.0, 0.25, 0.5, 1.0], fps=12)))
    read = read_camera_path(tmp_path / "path.json")
    assert read.times == [0.0, 0.25, 0.5, 1.0] and read.fps == 12
    for got, cam in zip(read.cameras, cams):
        np.testing.assert_allclose(got.viewmat, cam.viewmat, atol=1e-9)
        np.testing.assert_allclose(got.K, cam.K, atol=1e-9)
        assert (got.width, got.height) == (80, 60)
    bad = nerfstudio_path(cams)
    bad["camera_path"][1]["camera_to_world"][0] = 2.0  # a scaled axis
    for broken, message in ((bad, "camera 1: camera_to_world is not a rotation"),
                            ({**nerfstudio_path(cams), "render_width": 0}, "render sizes"),
                            ({"camera_path": []}, "no 'render_width'")):
        (tmp_path / "bad.json").write_text(json.dumps(broken))
        with pytest.raises(OMG4Error, match=message):
            read_camera_path(tmp_path / "bad.json")


def test_render_follows_a_camera_path_file_and_sizes_images(tmp_path):
    model = tmp_path / "m.omg4"
    forge.valid_file(model, 300, seed=2, codebook_scale=0.3)
    from omg4.models import load_model

    camera = bounds_camera(load_model(model).values["xyz"].numpy(), 64, 48)
    (tmp_path / "path.json").write_text(json.dumps(nerfstudio_path([camera] * 5, fps=10)))
    out = tmp_path / "path.mp4"
    assert main(["render", "--model", str(model), "--path", str(tmp_path / "path.json"), "--out", str(out)]) == 0
    with av.open(str(out)) as container:
        stream = container.streams.video[0]
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
        assert float(stream.average_rate) == 10
    assert len(frames) == 5 and frames[0].shape == (48, 64, 3)
    (tmp_path / "cam.json").write_text(json.dumps(camera.to_json()))
    assert main(["render", "--model", str(model), "--camera", str(tmp_path / "cam.json"), "--time", "0.5",
                 "--width", "96", "--out", str(tmp_path / "wide.npy")]) == 0
    assert main(["render", "--model", str(model), "--camera", str(tmp_path / "cam.json"), "--time", "0.5",
                 "--out", str(tmp_path / "native.npy")]) == 0
    wide, native = np.load(tmp_path / "wide.npy"), np.load(tmp_path / "native.npy")
    assert wide.shape == (72, 96, 3) and native.shape == (48, 64, 3) and native.std() > 0.01
    # the same view at 1.5× the pixels: block means of the larger image follow the smaller one
    assert np.corrcoef(wide[::3, ::3].reshape(-1), native[::2, ::2].reshape(-1))[0, 1] > 0.9
