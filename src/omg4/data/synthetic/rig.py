"""The synthetic scene's camera rig: OpenCV cameras on a forward-facing arc, their rays, and LLFF poses.

Cameras sit at y < 0 on an arc of radius :data:`RIG_RADIUS` around :data:`TARGET`, looking at it
(+y), like the N3DV rig; ``cam00`` is the central one. :func:`llff_poses_bounds` writes them in
the ``poses_bounds.npy`` layout the N3DV reader reads (docs/architecture.md, "Cameras").
"""

from __future__ import annotations

import numpy as np

from omg4.data.scene import Camera, look_at_viewmat

TARGET = np.array([0.0, 0.5, 0.6])  # point every camera looks at
RIG_RADIUS = 5.0          # horizontal distance of the cameras from TARGET
RIG_HEIGHT = 1.6          # mean camera height
FOV_X_DEG = 55.0          # horizontal field of view of every camera


def camera_rig(num_cameras: int, width: int, height: int, rng: np.random.Generator) -> list[Camera]:
    """Cameras ``cam00..`` on a forward-facing arc around :data:`TARGET`, all looking at it.

    ``cam00`` is central (azimuth 0); the others spread over ±40° in two alternating rows
    (±0.35 m around :data:`RIG_HEIGHT`), each position and aim jittered by a few cm.
    One focal length and a centred principal point, as LLFF assumes.
    """
    focal = 0.5 * width / np.tan(np.radians(FOV_X_DEG) / 2)
    K = np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    others = num_cameras - 1
    azimuths = np.concatenate([[0.0], np.radians(np.linspace(-40.0, 40.0, others))])
    rows = np.concatenate([[0.0], np.where(np.arange(others) % 2 == 0, -0.35, 0.35)])
    jitter = rng.normal(0.0, 0.04, size=(num_cameras, 2, 3))
    cams = []
    for i in range(num_cameras):
        center = TARGET + RIG_RADIUS * np.array([np.sin(azimuths[i]), -np.cos(azimuths[i]), 0.0])
        center[2] = RIG_HEIGHT + rows[i]
        viewmat = look_at_viewmat(center + jitter[i, 0], TARGET + jitter[i, 1])
        cams.append(Camera(K=K.copy(), viewmat=viewmat, width=width, height=height, name=f"cam{i:02d}"))
    return cams


def llff_poses_bounds(cameras: list[Camera], near: np.ndarray, far: np.ndarray) -> np.ndarray:
    """LLFF ``poses_bounds.npy`` rows [N, 17] for OpenCV cameras (rt4dgs §4.1, inverse).

    The camera-to-world rotation columns [right, down, forward] (OpenCV) become
    [down, right, back]; column 4 is ``[H, W, focal]``; then ``near[i], far[i]``.
    """
    rows = np.zeros((len(cameras), 17))
    for i, cam in enumerate(cameras):
        c2w = np.linalg.inv(cam.viewmat)
        right, down, fwd = c2w[:3, 0], c2w[:3, 1], c2w[:3, 2]
        mat = np.stack([down, right, -fwd, c2w[:3, 3], [cam.height, cam.width, cam.K[0, 0]]], axis=1)
        rows[i, :15] = mat.reshape(-1)
        rows[i, 15:] = near[i], far[i]
    return rows


def camera_rays(camera: Camera, supersample: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Rays through the sample centres of ``camera`` at ``supersample``× resolution.

    Sample (i, j) of the fine grid sits at pixel coordinates ((j + 0.5) / s, (i + 0.5) / s)
    (pixel centres at +0.5, docs/architecture.md §3). Returns origin [3] and unit directions
    [H·s, W·s, 3] (float32) in world coordinates.
    """
    s = supersample
    K = camera.K
    u = (np.arange(camera.width * s) + 0.5) / s
    v = (np.arange(camera.height * s) + 0.5) / s
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    d_cam = np.stack(np.broadcast_arrays(x[None, :], y[:, None], np.ones((1, 1))), axis=-1)
    c2w = np.linalg.inv(camera.viewmat)
    d = d_cam @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return c2w[:3, 3].astype(np.float32), d.astype(np.float32)
