"""``omg4 view`` in a real browser: headless Chromium loads the page, the first frame shows, and moving the
time slider (through viser's server-side handle) changes the picture. Skipped, with the reason, where
Chromium or viser is missing (``.ci/run`` installs Debian's ``chromium``)."""

from __future__ import annotations

import socket

import numpy as np
import pytest
from omg4.testing.browser import CHROMIUM, Browser, free_port, wait
from PIL import Image

from omg4.app.cli import main
from omg4.testing import forge


@pytest.fixture
def viser():
    return pytest.importorskip("viser", reason="the viewer extra (viser) is not installed")


@pytest.fixture
def model_file(tmp_path):
    path = tmp_path / "m.omg4"
    forge.valid_file(path, 400, seed=3, codebook_scale=0.3)
    return path


def _scene_pixels(image: Image.Image) -> np.ndarray:
    """The part of the page where only the rendered frame shows (left of the panel, below the notices)."""
    pixels = np.asarray(image.convert("RGB"), dtype=np.float64)
    h, w = pixels.shape[:2]
    return pixels[h // 2:, : w // 2]


@pytest.mark.browser
@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium to drive (Debian package 'chromium')")
def test_the_page_shows_frames_and_follows_the_time_slider(viser, model_file, tmp_path):
    from omg4.app.viewer import Viewer, ViewerSettings, view_presets
    from omg4.models import load_model

    model = load_model(model_file)
    port = free_port()
    viewer = Viewer(model, view_presets(model, None), file_bytes=model_file.stat().st_size,
                    settings=ViewerSettings(port=port, long_side=320, moving_long_side=160))
    browser = Browser(tmp_path / "profile")
    try:
        browser.call("Page.navigate", url=f"http://127.0.0.1:{port}")
        wait(lambda: viewer.frames_sent > 0, "the first frame")
        wait(lambda: _scene_pixels(browser.screenshot()).std() > 10, "a frame on the page")
        first = browser.screenshot()
        t0, t1 = viewer.time_range
        sent = viewer.frames_sent
        viewer.time_slider.value = t0 + 0.8 * (t1 - t0)
        wait(lambda: viewer.frames_sent > sent, "a frame at the new time")
        wait(lambda: np.abs(_scene_pixels(browser.screenshot()) - _scene_pixels(first)).mean() > 2,
              "the page to change with time")
        assert f"{model.num_gaussians:,}" in viewer.stats.content
    finally:
        browser.close()
        viewer.stop()


def test_a_busy_port_is_a_one_line_error(viser, model_file, capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main(["view", str(model_file), "--port", str(port)]) == 2
    err = capsys.readouterr().err
    assert f"cannot serve the viewer on 127.0.0.1:{port}" in err and err.count("\n") == 1


def test_a_missing_model_is_a_one_line_error(viser, tmp_path, capsys):
    assert main(["view", str(tmp_path / "none.omg4"), "--port", str(free_port())]) == 2
    err = capsys.readouterr().err
    assert "does not exist" in err and err.count("\n") == 1


def test_camera_from_pose_inverts_a_cameras_pose():
    from scipy.spatial.transform import Rotation

    from omg4.app.viewer import camera_from_pose
    from omg4.data.scene import Camera, look_at_viewmat

    K = np.array([[300.0, 0, 320], [0, 300.0, 180], [0, 0, 1]])
    cam = Camera(K=K, viewmat=look_at_viewmat(np.array([1.0, -4.0, 1.5]), np.zeros(3)), width=640, height=360)
    c2w = cam.camtoworld
    wxyz = Rotation.from_matrix(c2w[:3, :3]).as_quat()[[3, 0, 1, 2]]
    fov_y = 2 * np.arctan(0.5 * 360 / 300.0)
    again = camera_from_pose(c2w[:3, 3], wxyz, fov_y, 640 / 360, 640)
    np.testing.assert_allclose(again.viewmat, cam.viewmat, atol=1e-12)
    np.testing.assert_allclose(again.K, K, atol=1e-9)
    portrait = camera_from_pose(c2w[:3, 3], wxyz, fov_y, 0.5, 640)
    assert (portrait.width, portrait.height) == (320, 640)
    from omg4.errors import OMG4Error

    for aspect, fov in ((0.0, fov_y), (float("nan"), fov_y), (1.5, 0.0)):
        with pytest.raises(OMG4Error, match="degenerate camera"):
            camera_from_pose(c2w[:3, 3], wxyz, fov, aspect, 640)
