"""Camera paths for free-viewpoint videos and the viewer's presets (``omg4 render --path``, ``omg4 view``).

Every path is built from reference cameras (a dataset's, or one given camera) in the model's
normalized world and keeps the first reference camera's intrinsics and resolution:

* ``orbit``: for an inward-facing rig (Panoptic, D-NeRF: cameras on every side of the point they look at,
  :func:`omg4.data.normalize.axes_focus`) a full circle around the vertical through that point, at the
  cameras' mean horizontal distance and height; for a forward-facing rig (N3DV: every camera on one side,
  :func:`faces_forward`) one turn of a circle around the rig's mean centre, as wide as the rig's spread, so every
  view shows what the cameras saw — both always looking at that point;
* ``spiral``: the forward-facing spiral of NeRF's LLFF renders — around the mean camera
  centre in the plane of its right and up axes, two turns, radii from the spread of the
  camera centres, looking at the focus — for forward-facing rigs (N3DV);
* ``dataset``: the reference cameras in order of azimuth around the focus, positions
  interpolated linearly and orientations by spherical linear interpolation.

"Up" is +z, the normalized world's up axis (the readers rotate the cameras' summed up vector onto
it; Blender-layout worlds are +z up too).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from omg4.data.normalize import axes_focus
from omg4.data.scene import Camera, look_at_viewmat, world_to_camera
from omg4.errors import OMG4Error

SPIRAL_TURNS = 2
SPIRAL_PERCENTILE = 90  # spiral radii: this percentile of the camera centres' spread
UP = np.array([0.0, 0.0, 1.0])


def scene_focus(cameras: list[Camera]) -> np.ndarray:
    """The point the cameras look at (:func:`omg4.data.normalize.axes_focus`); for one camera, or parallel
    axes, the point in front of them at their distance from the origin."""
    return _frame(cameras)[1]


def _frame(cameras: list[Camera], focus: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centres [C, 3], the focus point [3] unless given, the unit up vector [3]) of the reference cameras."""
    centres = np.stack([c.center for c in cameras])
    forwards = np.stack([c.viewmat[2, :3] for c in cameras])
    up = UP
    if focus is None and len(cameras) > 1:
        focus = axes_focus(centres, forwards)
    if focus is None:  # one camera, or parallel axes: a point in front at the cameras' distance from the origin
        distance = max(float(np.linalg.norm(centres.mean(0))), 1.0)
        focus = centres.mean(0) + forwards.mean(0) / np.linalg.norm(forwards.mean(0)) * distance
    return centres, focus, up


def _looking_at(template: Camera, position: np.ndarray, focus: np.ndarray, up: np.ndarray, name: str) -> Camera:
    return Camera(K=template.K.copy(), viewmat=look_at_viewmat(position, focus, up), width=template.width,
                  height=template.height, name=name)


FORWARD_FACING_GAP_DEG = 180.0
"""A rig whose cameras leave a gap wider than this in their azimuths around the focus faces forward."""


def faces_forward(cameras: list[Camera], focus: np.ndarray | None = None) -> bool:
    """Whether the cameras all stand on one side of the point they look at: their azimuths around the vertical
    through it leave a gap wider than :data:`FORWARD_FACING_GAP_DEG` (one camera always does)."""
    if len(cameras) < 2:
        return True
    centres, focus, up = _frame(cameras, focus)
    offsets = centres - focus
    side = np.cross(up, offsets[0])
    azimuth = np.sort(np.degrees(np.arctan2(offsets @ side, offsets @ np.cross(side, up))))
    gaps = np.diff(np.concatenate([azimuth, azimuth[:1] + 360.0]))
    return float(gaps.max()) > FORWARD_FACING_GAP_DEG


def orbit_path(cameras: list[Camera], num_frames: int, focus: np.ndarray | None = None) -> list[Camera]:
    """``num_frames`` cameras on a circle that frames the scene (see the module docstring; ``focus`` overrides the
    point the cameras look at): around the focus for an inward-facing rig, around the rig for a forward-facing
    one."""
    if len(cameras) > 1 and faces_forward(cameras, focus):
        return _rig_circle(cameras, num_frames, turns=1, focus=focus, name="orbit", radii_of=_mean_spread)
    centres, focus, up = _frame(cameras, focus)
    offsets = centres - focus
    heights = offsets @ up
    horizontal = offsets - heights[:, None] * up
    radius = float(np.linalg.norm(horizontal, axis=1).mean())
    start = horizontal[0] / np.linalg.norm(horizontal[0])
    side = np.cross(up, start)
    angles = 2.0 * np.pi * np.arange(num_frames) / num_frames
    height = float(heights.mean())
    return [_looking_at(cameras[0], focus + up * height + radius * (np.cos(a) * start + np.sin(a) * side), focus, up,
                        f"orbit{i:04d}") for i, a in enumerate(angles)]


def spiral_path(cameras: list[Camera], num_frames: int, turns: int = SPIRAL_TURNS) -> list[Camera]:
    """``num_frames`` cameras on NeRF's forward-facing spiral around the mean camera centre."""
    if len(cameras) < 2:
        raise OMG4Error("--path spiral needs at least two cameras to size the spiral (use --data)")
    return _rig_circle(cameras, num_frames, turns=turns, name="spiral", radii_of=_percentile_spread)


def _percentile_spread(spread: np.ndarray) -> np.ndarray:
    """The spiral's radii: :data:`SPIRAL_PERCENTILE` of the centres' spread along each axis."""
    return np.percentile(spread, SPIRAL_PERCENTILE, axis=0)


def _mean_spread(spread: np.ndarray) -> np.ndarray:
    """A circle's radius on both axes: the centres' mean distance from their mean."""
    return np.full(2, float(np.linalg.norm(spread, axis=1).mean()))


def _rig_circle(cameras: list[Camera], num_frames: int, *, turns: int, name: str, radii_of,
                focus: np.ndarray | None = None) -> list[Camera]:
    """``num_frames`` cameras on ``turns`` turns of an ellipse around the mean camera centre in the plane of its
    right and up axes (radii ``radii_of`` the centres' |offsets| [C, 2] along them), looking at the focus."""
    centres, focus, up = _frame(cameras, focus)
    mean = centres.mean(0)
    back = mean - focus
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    true_up = np.cross(back, right)
    spread = np.abs(np.stack([(centres - mean) @ right, (centres - mean) @ true_up], axis=1))
    radii = np.maximum(radii_of(spread), 1e-3 * np.linalg.norm(mean - focus))
    angles = 2.0 * np.pi * turns * np.arange(num_frames) / num_frames
    return [_looking_at(cameras[0], mean + radii[0] * np.cos(a) * right + radii[1] * np.sin(a) * true_up, focus, up,
                        f"{name}{i:04d}") for i, a in enumerate(angles)]


def dataset_path(cameras: list[Camera], num_frames: int) -> list[Camera]:
    """``num_frames`` cameras through the reference cameras, ordered by azimuth around the focus."""
    if len(cameras) < 2:
        raise OMG4Error("--path dataset needs at least two cameras (use --data)")
    centres, focus, up = _frame(cameras)
    offsets = centres - focus
    side = np.cross(up, offsets[0])
    azimuth = np.arctan2(offsets @ side, offsets @ np.cross(side, up))
    order = np.argsort(azimuth, kind="stable")
    keys = np.linspace(0.0, 1.0, len(order))
    c2w = np.stack([cameras[i].camtoworld for i in order])
    slerp = Slerp(keys, Rotation.from_matrix(c2w[:, :3, :3]))
    s = np.linspace(0.0, 1.0, num_frames)
    positions = np.stack([np.interp(s, keys, c2w[:, k, 3]) for k in range(3)], axis=1)
    rotations = slerp(s).as_matrix()
    return [Camera(K=cameras[0].K.copy(), viewmat=world_to_camera(rotations[i], positions[i]), width=cameras[0].width,
                   height=cameras[0].height, name=f"dataset{i:04d}") for i in range(num_frames)]


PATHS: dict[str, Callable[[list[Camera], int], list[Camera]]] = {
    "orbit": orbit_path, "spiral": spiral_path, "dataset": dataset_path,
}
"""Path name → the function that builds ``num_frames`` cameras from reference cameras."""


def camera_path(name: str, cameras: list[Camera], num_frames: int) -> list[Camera]:
    """The path ``name`` (one of :data:`PATHS`) of ``num_frames`` ≥ 1 cameras around ``cameras``."""
    if name not in PATHS:
        raise OMG4Error(f"unknown camera path '{name}' (choose from {', '.join(PATHS)})")
    if not cameras:
        raise OMG4Error("a camera path needs at least one reference camera")
    return PATHS[name](cameras, num_frames)


def bounds_camera(xyz: np.ndarray, width: int, height: int, fov_x_deg: float = 50.0) -> Camera:
    """A camera that frames points ``xyz`` [N, 3]: it looks at their median from −y, slightly above, at
    the distance where the 90th-percentile radius fills the horizontal field of view (when no dataset
    cameras are known)."""
    centre = np.median(xyz, axis=0)
    radius = max(float(np.percentile(np.linalg.norm(xyz - centre, axis=1), 90)), 1e-3)
    focal = 0.5 * width / np.tan(np.radians(fov_x_deg) / 2)
    distance = 1.2 * radius / np.tan(np.radians(fov_x_deg) / 2)
    position = centre + distance * np.array([0.0, -np.cos(0.3), np.sin(0.3)])
    K = np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    return Camera(K=K, viewmat=look_at_viewmat(position, centre), width=int(width), height=int(height), name="bounds")


__all__ = ["PATHS", "UP", "bounds_camera", "camera_path", "dataset_path", "faces_forward", "orbit_path", "scene_focus", "spiral_path"]
