"""``omg4 view`` in a real browser: headless Chromium loads the page, the first frame shows, and moving the
time slider (through viser's server-side handle) changes the picture. Skipped, with the reason, where
Chromium or viser is missing (``.ci/run`` installs Debian's ``chromium``)."""

from __future__ import annotations

import base64
import io
import json
import shutil
import socket
import subprocess
import time
import urllib.request

import numpy as np
import pytest
from PIL import Image

from omg4.cli import main
import forge

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
TIMEOUT_S = 60


@pytest.fixture
def viser():
    return pytest.importorskip("viser", reason="the viewer extra (viser) is not installed")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait(condition, what: str, timeout: float = TIMEOUT_S) -> None:
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.1)


class Browser:
    """Headless Chromium driven over the DevTools protocol (navigate, screenshot)."""

    def __init__(self, profile):
        from websockets.sync.client import connect

        self.proc = subprocess.Popen(
            [CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
             "--enable-unsafe-swiftshader", "--no-first-run", "--disable-background-networking",
             "--disable-component-update", "--disable-sync", "--disable-quic", f"--user-data-dir={profile}",
             "--remote-debugging-port=0", "--window-size=960,540", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        active = profile / "DevToolsActivePort"
        _wait(active.exists, "Chromium's DevTools port")
        port = int(active.read_text().split()[0])
        pages = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10).read())
        self.ws = connect(next(p for p in pages if p["type"] == "page")["webSocketDebuggerUrl"], max_size=None)
        self.calls = 0

    def call(self, method: str, **params) -> dict:
        self.calls += 1
        self.ws.send(json.dumps({"id": self.calls, "method": method, "params": params}))
        while True:
            message = json.loads(self.ws.recv(timeout=TIMEOUT_S))
            if message.get("id") == self.calls:
                return message["result"]

    def screenshot(self) -> Image.Image:
        return Image.open(io.BytesIO(base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])))

    def close(self) -> None:
        self.ws.close()
        self.proc.terminate()
        self.proc.wait(timeout=10)


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


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium to drive (Debian package 'chromium')")
def test_the_page_shows_frames_and_follows_the_time_slider(viser, model_file, tmp_path):
    from omg4.evaluate import load_model
    from omg4.viewer import Viewer, ViewerSettings, view_presets

    model = load_model(model_file)
    port = _free_port()
    viewer = Viewer(model, view_presets(model, None), file_bytes=model_file.stat().st_size,
                    settings=ViewerSettings(port=port, long_side=320, moving_long_side=160))
    browser = Browser(tmp_path / "profile")
    try:
        browser.call("Page.navigate", url=f"http://127.0.0.1:{port}")
        _wait(lambda: viewer.frames_sent > 0, "the first frame")
        _wait(lambda: _scene_pixels(browser.screenshot()).std() > 10, "a frame on the page")
        first = browser.screenshot()
        t0, t1 = viewer.time_range
        sent = viewer.frames_sent
        viewer.time_slider.value = t0 + 0.8 * (t1 - t0)
        _wait(lambda: viewer.frames_sent > sent, "a frame at the new time")
        _wait(lambda: np.abs(_scene_pixels(browser.screenshot()) - _scene_pixels(first)).mean() > 2,
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
    assert main(["view", str(tmp_path / "none.omg4"), "--port", str(_free_port())]) == 2
    err = capsys.readouterr().err
    assert "does not exist" in err and err.count("\n") == 1


def test_camera_from_pose_inverts_a_cameras_pose():
    from scipy.spatial.transform import Rotation

    from omg4.data.scene import Camera, look_at_viewmat
    from omg4.viewer import camera_from_pose

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
