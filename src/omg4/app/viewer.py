"""The interactive browser viewer of ``omg4 view``: server-side rendering streamed through viser.

The model (a checkpoint or a decoded ``.omg4`` file, :func:`omg4.models.load_model`) is
rendered by the project's own renderer (numba on the CPU, gsplat on CUDA) for every connected
browser's camera, and the image is sent as the page's background (JPEG). The panel has a time
slider with play/pause, speed and loop; camera presets (the dataset's cameras, or an orbit
around the model's bounds, :mod:`omg4.render.paths`); and the model's Gaussian count, file
size, the fraction of Gaussians visible at the current time and the measured render rate.
While the camera moves or the clip plays, frames are rendered at
:attr:`ViewerSettings.moving_long_side` pixels on the long side; once the camera has rested for
:attr:`ViewerSettings.settle_s` and the clip is paused, one frame at
:attr:`ViewerSettings.long_side` follows. A frame that fails to render is reported in the panel
and on the console; the viewer keeps serving.
"""

from __future__ import annotations

import socket
import threading
import time
from dataclasses import dataclass

import numpy as np
import torch

from omg4.data.scene import Camera, world_to_camera
from omg4.errors import OMG4Error
from omg4.io.images import to_uint8
from omg4.render.paths import UP, scene_focus
from omg4.render.view import render_view

PLAY_SECONDS = 5.0
"""At speed 1 the time slider crosses the whole clip in this many seconds."""


@dataclass(frozen=True)
class ViewerSettings:
    """How the viewer serves and renders."""

    host: str = "127.0.0.1"
    port: int = 8080
    long_side: int = 640  # pixels on the long side of a still frame
    moving_long_side: int = 320  # while the camera moves or the clip plays
    settle_s: float = 0.25  # a camera at rest this long gets a full-resolution frame
    jpeg_quality: int = 85
    backend: str = "auto"
    device: str = "cpu"


def check_port_free(host: str, port: int) -> None:
    """Raise a one-line :class:`OMG4Error` when ``host:port`` cannot be bound (a live listener, or not ours).

    Binds with ``SO_REUSEADDR`` as the server will, so a port left in TIME_WAIT by a viewer that just
    stopped counts as free."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as e:
            raise OMG4Error(f"cannot serve the viewer on {host}:{port} ({e.strerror or e}); choose another --port") \
                from None


def render_frame(model, camera: Camera, timestamp: float, *, background: torch.Tensor | None = None,
                 backend: str = "auto", device: torch.device | str = "cpu") -> tuple[np.ndarray, float]:
    """(uint8 image [H, W, 3], fraction of the model's Gaussians drawn) of ``camera`` at ``timestamp``."""
    with torch.no_grad():
        rendered, sl = render_view(model, camera, timestamp, background=background, backend=backend, device=device)
    return to_uint8(rendered.image.cpu().numpy()), sl.index.numel() / max(sl.num_total, 1)


def camera_from_pose(position: np.ndarray, wxyz: np.ndarray, fov_y: float, aspect: float, long_side: int) -> Camera:
    """An OpenCV :class:`Camera` from a viser client pose (camera-to-world ``[R(wxyz) | position]``, OpenCV
    axes), its vertical field of view and the canvas aspect, ``long_side`` pixels on the longer side.
    Raises :class:`OMG4Error` for a degenerate pose (zero or non-finite aspect or field of view)."""
    from scipy.spatial.transform import Rotation

    if not (np.isfinite(aspect) and aspect > 0 and np.isfinite(fov_y) and 0 < fov_y < np.pi):
        raise OMG4Error(f"the browser reported a degenerate camera (aspect {aspect}, field of view {fov_y})")
    width, height = (long_side, max(1, round(long_side / aspect))) if aspect >= 1 else \
        (max(1, round(long_side * aspect)), long_side)
    R = Rotation.from_quat(np.asarray(wxyz, float)[[1, 2, 3, 0]]).as_matrix()
    fy = 0.5 * height / np.tan(0.5 * fov_y)
    K = np.array([[fy, 0.0, width / 2], [0.0, fy, height / 2], [0.0, 0.0, 1.0]])
    return Camera(K=K, viewmat=world_to_camera(R, position), width=int(width), height=int(height),
                  name="viewer").check_renderable()


class Viewer:
    """A viser server showing ``model``; :meth:`stop` shuts it down.

    Args:
        model: a render-only model (:func:`omg4.models.load_model`).
        presets: cameras offered in the preset list (the first is where a new browser starts).
        file_bytes: the model file's size, shown in the panel.
    """

    def __init__(self, model, presets: list[Camera], *, file_bytes: int, settings: ViewerSettings = ViewerSettings()):
        import viser

        if not presets:
            raise ValueError("the viewer needs at least one camera preset")
        check_port_free(settings.host, settings.port)
        self.model, self.presets, self.settings = model, list(presets), settings
        self.device = torch.device(settings.device)
        self.background = torch.zeros(3, device=self.device)
        t0, t1 = model.config.time_range
        self.time_range = (float(t0), float(t1))
        self.frames_sent = 0
        self.render_ms = float("nan")
        self.last_error: str | None = None
        self.focus = scene_focus(self.presets)  # where the orbit controls pivot
        self._moved_at: dict[int, float] = {}
        self._sharp: set[int] = set()
        self._lock = threading.Lock()
        self._running = True
        self.server = viser.ViserServer(host=settings.host, port=settings.port, verbose=False)
        gui = self.server.gui
        self.time_slider = gui.add_slider("time", min=t0, max=t1, step=(t1 - t0) / 1000, initial_value=t0)
        self.playing = gui.add_checkbox("play", initial_value=False)
        self.speed = gui.add_slider("speed", min=0.1, max=4.0, step=0.1, initial_value=1.0)
        self.loop = gui.add_checkbox("loop", initial_value=True)
        self.preset = gui.add_dropdown("camera", options=[c.name or f"camera {i}" for i, c in enumerate(presets)],
                                       initial_value=presets[0].name or "camera 0")
        self.stats = gui.add_markdown("")
        self.file_bytes = file_bytes
        self.time_slider.on_update(lambda _: self._refresh_all())
        self.playing.on_update(lambda _: self._refresh_all())  # pausing sharpens the last frame
        self.preset.on_update(lambda _: self._apply_preset_to_all())
        self.server.on_client_connect(self._on_connect)
        self._thread = threading.Thread(target=self._loop, name="omg4-viewer", daemon=True)
        self._thread.start()

    # ---------------------------------------------------------------- clients and presets
    def _on_connect(self, client) -> None:
        self._apply_preset(client)
        client.camera.on_update(lambda cam: self._moved(client.client_id))
        self._moved(client.client_id)

    def _apply_preset(self, client) -> None:
        cam = self.presets[self.preset.options.index(self.preset.value)]
        c2w = cam.camtoworld
        with client.atomic():
            client.camera.fov = float(2.0 * np.arctan(0.5 * cam.height / cam.K[1, 1]))
            client.camera.up_direction = UP
            client.camera.position = c2w[:3, 3]
            client.camera.look_at = self.focus

    def _apply_preset_to_all(self) -> None:
        for client in self.server.get_clients().values():
            self._apply_preset(client)
            self._moved(client.client_id)

    def _moved(self, client_id: int) -> None:
        with self._lock:
            self._moved_at[client_id] = time.perf_counter()
            self._sharp.discard(client_id)

    def _refresh_all(self) -> None:
        with self._lock:
            self._sharp.clear()

    # ---------------------------------------------------------------- rendering
    def render(self, camera: Camera, timestamp: float) -> tuple[np.ndarray, float]:
        """:func:`render_frame` of the viewer's model with its background, backend and device."""
        return render_frame(self.model, camera, timestamp, background=self.background, backend=self.settings.backend,
                            device=self.device)

    def _advance_time(self, elapsed: float) -> None:
        if not self.playing.value:
            return
        t0, t1 = self.time_range
        t = self.time_slider.value + self.speed.value * elapsed * (t1 - t0) / PLAY_SECONDS
        if t > t1:
            if self.loop.value:
                t = t0 + (t - t1) % (t1 - t0)
            else:
                t, self.playing.value = t1, False
        self.time_slider.value = t

    def _loop(self) -> None:
        last = time.perf_counter()
        while self._running:
            now = time.perf_counter()
            self._advance_time(now - last)
            last = now
            busy = False
            for client in list(self.server.get_clients().values()):
                try:
                    busy |= self._serve(client)
                except Exception as e:  # noqa: BLE001 — one bad frame must not stop the viewer
                    self._report(f"frame not rendered: {type(e).__name__}: {e}")
            if not busy:
                time.sleep(0.01)

    def _serve(self, client) -> bool:
        """Render and send one frame to ``client`` if it needs one; whether it did."""
        cid = client.client_id
        with self._lock:
            moved_at = self._moved_at.get(cid)
            if moved_at is None:
                return False
            moving = time.perf_counter() - moved_at < self.settings.settle_s
            if not (moving or self.playing.value or cid not in self._sharp):
                return False
            if not (moving or self.playing.value):
                self._sharp.add(cid)
        cam = client.camera
        if cam.update_timestamp == 0.0:  # the browser has not reported its camera yet
            with self._lock:
                self._sharp.discard(cid)
            return False
        playing = bool(self.playing.value)
        camera = camera_from_pose(cam.position, cam.wxyz, cam.fov, cam.aspect,
                                  self.settings.moving_long_side if moving or playing else self.settings.long_side)
        start = time.perf_counter()
        image, visible = self.render(camera, float(self.time_slider.value))
        ms = 1000 * (time.perf_counter() - start)
        self.render_ms = ms if np.isnan(self.render_ms) else 0.8 * self.render_ms + 0.2 * ms
        client.scene.set_background_image(image, format="jpeg", jpeg_quality=self.settings.jpeg_quality)
        self.frames_sent += 1
        self.stats.content = (f"**{self.model.num_gaussians:,}** Gaussians · **{self.file_bytes / 2**20:.2f} MB**  \n"
                              f"visible now: {100 * visible:.0f} %  \n"
                              f"render: {1000 / self.render_ms:.1f} FPS at {camera.width}×{camera.height}")
        self.last_error = None
        return True

    def _report(self, message: str) -> None:
        if message != self.last_error:
            print(f"omg4 view: {message}", flush=True)
            self.stats.content = f"**{message}**"
        self.last_error = message
        time.sleep(0.2)

    def stop(self) -> None:
        """Stop rendering and shut the server down."""
        self._running = False
        self._thread.join(timeout=5)
        self.server.stop()


def view_presets(model, cameras: list[Camera] | None, width: int = 640, height: int = 360) -> list[Camera]:
    """The preset list: the dataset's ``cameras``, else the camera rig the file records (:mod:`omg4.codec.rig`),
    else an orbit of 8 views around the model's bounds."""
    from omg4.codec.rig import rig_cameras
    from omg4.render.paths import bounds_camera, orbit_path

    cameras = cameras or [Camera.from_json(c) for c in rig_cameras(getattr(model, "meta", None) or {}) or []]
    if cameras:
        return list(cameras)
    xyz = model.values["xyz"].cpu().numpy()
    return orbit_path([bounds_camera(xyz, width, height)], 8, focus=np.median(xyz, axis=0))


__all__ = ["PLAY_SECONDS", "Viewer", "ViewerSettings", "camera_from_pose", "check_port_free", "render_frame",
           "view_presets"]
