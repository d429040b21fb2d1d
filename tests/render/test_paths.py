"""Camera paths of free-viewpoint videos: geometry of orbit, spiral and dataset paths; ``omg4 render --path``."""

import json

import av
import numpy as np
import pytest

from omg4.cli import main
import forge
from omg4.data.scene import Camera, look_at_viewmat
from omg4.errors import OMG4Error
from omg4.render.paths import bounds_camera, camera_path

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


def test_orbit_circles_the_focus_at_the_rigs_distance_and_height():
    path = camera_path("orbit", rig(), 12)
    offsets = np.stack([c.center for c in path]) - FOCUS
    assert np.allclose(np.linalg.norm(offsets[:, :2], axis=1), 4.0, atol=1e-9)  # the rig's horizontal radius
    assert np.allclose(offsets[:, 2], np.mean(1.0 + 0.1 * np.arange(6)), atol=1e-9)  # its mean height, +z up
    angles = np.unwrap(np.arctan2(offsets[:, 1], offsets[:, 0]))
    assert np.allclose(np.diff(angles), np.diff(angles)[0]) and abs(np.diff(angles)[0]) == pytest.approx(np.pi / 6)
    assert all(projects_to_centre(c, FOCUS) for c in path)
    assert all(np.allclose(c.K, K) and (c.width, c.height) == (80, 60) for c in path)


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
    from omg4.evaluate import load_model

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
