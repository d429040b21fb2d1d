"""The built-in procedural dynamic scene (``omg4 synth``), written as an N3DV folder.

A small analytic ray caster of its own (no Gaussians), vectorized in numpy over all
rays: an infinite textured ground plane (z = 0) and backdrop (y = ``BACKDROP_Y``), two
static solids, and four moving, rotating, colour-changing textured solids (two spheres,
a box, a capped cylinder). Lambertian shading with one directional light; the planes
receive soft analytic "blob" shadows of every solid, so moving objects also change the
static surfaces around them. Each pixel averages ``supersample``² stratified rays.

World: metres, +z up, the cameras on a forward-facing arc at y < 0 looking at the
scene centre (+y), like the N3DV rig. Motion is a function of the clip phase
``s = frame / num_frames`` (one cycle of motion per clip whatever the frame count).
Everything random (rig jitter, object sizes, paths, colours, textures) comes from
``seed`` through independent streams, so e.g. the camera count does not change the
objects.

Output (the N3DV layout read by ``omg4.data.load_scene``, reference notes
``rt4dgs_reference.md`` §4.1):

* ``camXX.mp4``: H.264 (libx264, yuv420p) per camera, ``cam00`` the central test camera;
* ``poses_bounds.npy``: [N, 17] float64, one row per camera in sorted-name order:
  the 3×5 matrix ``[R | t | hwf]`` (camera-to-world with LLFF axes [down, right, back],
  ``hwf = [H, W, focal]``) flattened row-major, then near and far z-depth bounds;
* ``points3d.ply``: binary little-endian ``float x, y, z`` + ``uchar red, green, blue``:
  points on the surfaces seen by the training cameras at frame 0 (the role of the
  COLMAP frame-0 points of N3DV, reference §3.5), in the same world as the poses;
* ``synth.json``: the generator's parameters.
"""

from __future__ import annotations

import colorsys
import json
import os
import shutil
import tempfile
import uuid
from dataclasses import asdict, dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np

from omg4.atomic import remove_stale_temporaries
from omg4.data.scene import Camera
from omg4.errors import OMG4Error

BACKDROP_Y = 3.5          # backdrop plane y = BACKDROP_Y (metres)
TARGET = np.array([0.0, 0.5, 0.6])  # point every camera looks at
RIG_RADIUS = 5.0          # horizontal distance of the cameras from TARGET
RIG_HEIGHT = 1.6          # mean camera height
FOV_X_DEG = 55.0          # horizontal field of view of every camera
LIGHT = np.array([-0.35, -0.6, 1.0]) / np.linalg.norm([-0.35, -0.6, 1.0])  # direction towards the light
AMBIENT, DIFFUSE = 0.35, 0.75
SKY = np.array([0.55, 0.7, 0.9], dtype=np.float32)
SHADOW_STRENGTH = 0.7
_EPS = 1e-4


@dataclass(frozen=True)
class SynthConfig:
    """Parameters of ``omg4 synth`` (defaults: 16 cameras, 60 frames, 256×192, 30 fps)."""

    seed: int = 0
    num_cameras: int = 16
    num_frames: int = 60
    width: int = 256
    height: int = 192
    fps: float = 30.0
    supersample: int = 2
    num_points: int = 4000
    crf: int = 17

    def validate(self) -> None:
        """Raise :class:`OMG4Error` (one line) on a parameter outside its valid range."""
        checks = [
            (2 <= self.num_cameras <= 100, f"--cameras must be between 2 and 100, got {self.num_cameras}"),
            (1 <= self.num_frames <= 100_000, f"--frames must be between 1 and 100000, got {self.num_frames}"),
            (16 <= self.width <= 4096 and self.width % 2 == 0,
             f"--width must be even and between 16 and 4096 (H.264 yuv420p), got {self.width}"),
            (16 <= self.height <= 4096 and self.height % 2 == 0,
             f"--height must be even and between 16 and 4096 (H.264 yuv420p), got {self.height}"),
            (np.isfinite(self.fps) and 0 < self.fps <= 1000, f"--fps must be in (0, 1000], got {self.fps}"),
            (1 <= self.supersample <= 8, f"supersample must be between 1 and 8, got {self.supersample}"),
            (1 <= self.num_points <= 10_000_000, f"--points must be between 1 and 10000000, got {self.num_points}"),
            (0 <= self.crf <= 51, f"--crf must be between 0 and 51, got {self.crf}"),
            (0 <= self.seed < 2**63, f"--seed must be a non-negative integer, got {self.seed}"),
        ]
        for ok, message in checks:
            if not ok:
                raise OMG4Error(message)


# --------------------------------------------------------------------------- cameras


def look_at_viewmat(center: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """[4, 4] OpenCV world-to-camera matrix of a camera at ``center`` looking at ``target``.

    Camera axes (DESIGN.md): x right = fwd × up, y down = fwd × right, z forward.
    """
    fwd = (target - center) / np.linalg.norm(target - center)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])  # rows: camera axes in world coordinates
    viewmat = np.eye(4)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = -R @ center
    return viewmat


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
    """LLFF ``poses_bounds.npy`` rows [N, 17] for OpenCV cameras (reference §4.1, inverse).

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
    (pixel centres at +0.5, DESIGN.md). Returns origin [3] and unit directions
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


# --------------------------------------------------------------------------- textures


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """[3, 3] rotation by ``angle`` (rad) about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * Kx @ Kx


def _hue_rotate(rgb: np.ndarray, turns: float) -> np.ndarray:
    """Colours [..., 3] rotated about the grey axis by ``turns`` full turns, clipped to [0.03, 0.97]."""
    return np.clip(rgb @ _axis_angle(np.ones(3), 2 * np.pi * turns).T, 0.03, 0.97)


def _value_noise(u: np.ndarray, v: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Smooth 2D value noise in [0, 1]: bilinear (smoothstep) interpolation of a
    periodic [256, 256] lattice of random values. ``u, v``: [...] lattice coordinates."""
    iu, iv = np.floor(u), np.floor(v)
    fu, fv = u - iu, v - iv
    fu, fv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
    i0, j0 = iu.astype(np.int64) & 255, iv.astype(np.int64) & 255
    i1, j1 = (i0 + 1) & 255, (j0 + 1) & 255
    top = table[i0, j0] * (1 - fu) + table[i1, j0] * fu
    bottom = table[i0, j1] * (1 - fu) + table[i1, j1] * fu
    return top * (1 - fv) + bottom * fv


def _palette(rng: np.random.Generator, n: int, sat: tuple[float, float], val: tuple[float, float]) -> np.ndarray:
    """[n, 3] random colours with spread hues and saturation/value in the given ranges."""
    hues = (rng.uniform() + np.arange(n) / n + rng.uniform(-0.05, 0.05, n)) % 1.0
    rng.shuffle(hues)
    return np.array([colorsys.hsv_to_rgb(h, rng.uniform(*sat), rng.uniform(*val)) for h in hues])


# --------------------------------------------------------------------------- primitives


@dataclass(frozen=True)
class _Plane:
    """Infinite textured plane ``{p : (p − point)·normal = 0}`` facing the cameras.

    ``texture`` is ``ground`` (checker + noise + grid lines, coords (x, y)) or
    ``backdrop`` (coloured stripes + dots + noise, coords (x, z)).
    """

    point: np.ndarray
    normal: np.ndarray
    texture: str
    colors: np.ndarray  # ground: [2, 3]; backdrop: [6, 3] (5 stripe colours + dots)
    stripe_order: np.ndarray  # [64] palette indices of the backdrop stripes
    noise: np.ndarray  # [256, 256] value-noise lattice

    def intersect(self, o: np.ndarray, d: np.ndarray, phase: float) -> np.ndarray:
        """Ray parameter t [P] of the hit (inf if none). ``o``: [3] or [P, 3]; ``d``: [P, 3]."""
        dn = d @ self.normal.astype(np.float32)
        dist = (self.point - o) @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (dist / dn).astype(np.float32)
        return np.where(t > _EPS, t, np.float32(np.inf))

    def surface(self, p: np.ndarray, phase: float) -> tuple[np.ndarray, np.ndarray]:
        """Normals [K, 3] and albedo [K, 3] at hit points ``p`` [K, 3]."""
        normal = np.broadcast_to(self.normal.astype(np.float32), p.shape)
        if self.texture == "ground":
            x, y = p[:, 0], p[:, 1]
            check = (np.floor(x / 0.5) + np.floor(y / 0.5)).astype(np.int64) & 1
            base = self.colors[check]
            grain = 0.55 * _value_noise(3 * x, 3 * y, self.noise) + 0.45 * _value_noise(11 * x + 91, 11 * y, self.noise)
            line = (np.abs(x - np.round(x)) < 0.02) | (np.abs(y - np.round(y)) < 0.02)
            albedo = base * (0.7 + 0.3 * grain)[:, None] * np.where(line, 0.45, 1.0)[:, None]
        else:
            x, z = p[:, 0], p[:, 2]
            stripe = self.stripe_order[np.floor(x / 0.4).astype(np.int64) & 63]
            base = self.colors[stripe]
            gx, gz = x / 0.6 - np.round(x / 0.6), z / 0.6 - np.round(z / 0.6)
            dot = (gx * gx + gz * gz) < (0.13 / 0.6) ** 2
            base = np.where(dot[:, None], self.colors[5], base)
            grain = _value_noise(4 * x + 17, 4 * z, self.noise)
            albedo = base * (0.78 + 0.22 * grain)[:, None] * np.where(z < 0.25, 0.6, 1.0)[:, None]
        return normal, albedo.astype(np.float32)


@dataclass(frozen=True)
class _Motion:
    """Pose as a function of the clip phase s ∈ [0, 1).

    centre(s) = base + amp · sin(2π·freq·s + phase0) per axis, except that a bouncing
    solid has z = base_z + amp_z · |sin(π·freq_z·s + phase0_z)|; rotation(s) =
    rotation by spin0 + 2π·spin_turns·s about spin_axis.
    """

    base: np.ndarray
    amp: np.ndarray
    freq: np.ndarray
    phase0: np.ndarray
    bounce: bool
    spin_axis: np.ndarray
    spin0: float
    spin_turns: float

    def pose(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """(centre [3], rotation [3, 3] local → world) at phase ``s``."""
        center = self.base + self.amp * np.sin(2 * np.pi * self.freq * s + self.phase0)
        if self.bounce:
            center[2] = self.base[2] + self.amp[2] * abs(np.sin(np.pi * self.freq[2] * s + self.phase0[2]))
        return center, _axis_angle(self.spin_axis, self.spin0 + 2 * np.pi * self.spin_turns * s)


@dataclass(frozen=True)
class _Solid:
    """A textured sphere, box or capped cylinder (local axis z) moving with ``motion``.

    ``size``: sphere [r]; box half extents [3]; cylinder [radius, half height].
    ``colors`` [3, 3] are the texture colours at s = 0; their hue turns ``hue_turns``
    times over the clip.
    """

    kind: str
    size: np.ndarray
    colors: np.ndarray
    hue_turns: float
    tex_freq: int
    motion: _Motion

    @property
    def bound_radius(self) -> float:
        """Radius of a sphere around the centre that contains the solid."""
        return float(np.linalg.norm(self.size) if self.kind != "sphere" else self.size[0])

    @property
    def shadow_radius(self) -> float:
        """Radius of the soft blob shadow the solid casts."""
        return float(self.size[0] if self.kind == "sphere" else 0.85 * self.bound_radius)

    def intersect(self, o: np.ndarray, d: np.ndarray, phase: float) -> np.ndarray:
        """Ray parameter t [P] of the first hit (inf if none). ``o``: [3] or [P, 3]; ``d``: [P, 3]."""
        center, R = self.motion.pose(phase)
        ol = ((o - center) @ R).astype(np.float32)  # R^T (o - c), row vectors
        dl = d @ R.astype(np.float32)
        inf = np.float32(np.inf)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            if self.kind == "sphere":
                b = np.einsum("...k,...k->...", ol, dl)
                c = np.einsum("...k,...k->...", ol, ol) - np.float32(self.size[0] ** 2)
                disc = b * b - c
                t = -b - np.sqrt(np.maximum(disc, 0))
                return np.where((disc >= 0) & (t > _EPS), t, inf)
            if self.kind == "box":
                h = self.size.astype(np.float32)
                t1, t2 = (-h - ol) / dl, (h - ol) / dl
                tnear = np.nanmax(np.minimum(t1, t2), axis=-1)
                tfar = np.nanmin(np.maximum(t1, t2), axis=-1)
                return np.where((tnear <= tfar) & (tnear > _EPS), tnear, inf)
            r, hh = np.float32(self.size[0]), np.float32(self.size[1])
            a = dl[..., 0] ** 2 + dl[..., 1] ** 2
            b = ol[..., 0] * dl[..., 0] + ol[..., 1] * dl[..., 1]
            c = ol[..., 0] ** 2 + ol[..., 1] ** 2 - r * r
            disc = b * b - a * c
            t_side = (-b - np.sqrt(np.maximum(disc, 0))) / a
            z_side = ol[..., 2] + t_side * dl[..., 2]
            t_side = np.where((disc >= 0) & (np.abs(z_side) <= hh) & (t_side > _EPS), t_side, inf)
            t_cap = (np.where(dl[..., 2] < 0, hh, -hh) - ol[..., 2]) / dl[..., 2]
            x_cap, y_cap = ol[..., 0] + t_cap * dl[..., 0], ol[..., 1] + t_cap * dl[..., 1]
            t_cap = np.where((x_cap ** 2 + y_cap ** 2 <= r * r) & (t_cap > _EPS), t_cap, inf)
            return np.minimum(t_side, t_cap)

    def surface(self, p: np.ndarray, phase: float) -> tuple[np.ndarray, np.ndarray]:
        """Normals [K, 3] and albedo [K, 3] at hit points ``p`` [K, 3] (texture fixed to the solid)."""
        center, R = self.motion.pose(phase)
        q = ((p - center) @ R).astype(np.float32)  # local coordinates
        n = self.tex_freq
        if self.kind == "sphere":
            qn = q / np.float32(self.size[0])
            normal_l = qn
            lon = np.arctan2(qn[:, 1], qn[:, 0])
            lat = np.arcsin(np.clip(qn[:, 2], -1, 1))
            tex = (np.floor(lon / (2 * np.pi) * 2 * n) + np.floor(lat / np.pi * n)).astype(np.int64) & 1
            tex = np.where(np.abs(qn[:, 2]) < 0.12, 2, tex)
        elif self.kind == "box":
            qn = q / self.size.astype(np.float32)
            rows, axis = np.arange(len(q)), np.argmax(np.abs(qn), axis=-1)
            normal_l = np.zeros_like(q)
            normal_l[rows, axis] = np.sign(qn[rows, axis])
            qn[rows, axis] = 0  # 2D checker in the face's own coordinates
            tex = np.sum(np.floor((qn + 1) * n / 2), axis=-1).astype(np.int64) & 1
            edge = np.max(np.abs(qn), axis=-1) > 0.88
            tex = np.where(edge, 2, tex)
        else:
            r, hh = self.size
            radial = np.sqrt(q[:, 0] ** 2 + q[:, 1] ** 2)
            cap = np.abs(q[:, 2]) / hh > radial / r
            normal_l = np.where(cap[:, None], np.stack([0 * radial, 0 * radial, np.sign(q[:, 2])], -1),
                                np.stack([q[:, 0] / r, q[:, 1] / r, 0 * radial], -1)).astype(np.float32)
            angle = np.arctan2(q[:, 1], q[:, 0])
            stripes = np.floor(angle / (2 * np.pi) * 2 * n) + np.floor((q[:, 2] / hh + 1) * 2)
            rings = np.floor(radial / r * 3)
            tex = np.where(cap, 2 * (rings.astype(np.int64) & 1), stripes.astype(np.int64) & 1)
        colors = _hue_rotate(self.colors, self.hue_turns * phase).astype(np.float32)
        return (normal_l @ R.T.astype(np.float32)), colors[tex]

    def shadow(self, p: np.ndarray, phase: float) -> np.ndarray:
        """Occlusion in [0, SHADOW_STRENGTH] [...] of the light at points ``p`` [..., 3].

        A soft disc: full inside 0.7·ρ of the light ray through the centre, none beyond
        1.15·ρ (ρ = shadow radius), fading in over 0.5·ρ on the light's side.
        """
        center, _ = self.motion.pose(phase)
        v = p - center.astype(np.float32)
        L = LIGHT.astype(np.float32)
        a = v @ L
        d2 = np.einsum("...k,...k->...", v, v) - a * a
        rho = self.shadow_radius
        x = np.clip((d2 - (0.7 * rho) ** 2) / ((1.15 * rho) ** 2 - (0.7 * rho) ** 2), 0, 1)
        side = np.clip(-a / (0.5 * rho), 0, 1)
        return (SHADOW_STRENGTH * (1 - x * x * (3 - 2 * x)) * side).astype(np.float32)


# --------------------------------------------------------------------------- scene


def _random_solids(rng: np.random.Generator) -> tuple[list[_Solid], list[_Solid]]:
    """(static solids, dynamic solids) of one seed.

    Dynamic: a bouncing sphere, a box tumbling in the air, an upright spinning cylinder
    circling on the ground, a small sphere on a figure-eight; in shuffled lanes.
    Static: a box and a cylinder at the sides, mirrored by the seed.
    """
    lanes = rng.permutation([-1.5, -0.5, 0.5, 1.5])
    y0 = rng.uniform(0.0, 1.0, 4)
    colors = _palette(rng, 12, (0.55, 0.95), (0.6, 0.95)).reshape(4, 3, 3)
    hue = rng.uniform(0.3, 0.8, 4) * rng.choice([-1, 1], 4)
    spin_axes = rng.normal(size=(4, 3))
    phases = rng.uniform(0, 2 * np.pi, (4, 3))
    r_big, r_small = rng.uniform(0.35, 0.45), rng.uniform(0.15, 0.2)
    box = rng.uniform(0.2, 0.32, 3)
    cyl = np.array([rng.uniform(0.2, 0.28), rng.uniform(0.3, 0.45)])
    z_axis = np.array([0.0, 0.0, 1.0])
    dynamic = [
        _Solid("sphere", np.array([r_big]), colors[0], hue[0], 4,
               _Motion(np.array([lanes[0], y0[0], r_big]), np.array([0.15, 0.3, 0.8]), np.array([1.0, 1.0, 2.0]),
                       phases[0], True, spin_axes[0], phases[0, 0], rng.uniform(0.5, 1.0))),
        _Solid("box", box, colors[1], hue[1], 3,
               _Motion(np.array([lanes[1], y0[1], 1.05]), np.array([0.35, 0.4, 0.15]), np.ones(3),
                       phases[1], False, spin_axes[1], phases[1, 0], rng.uniform(0.4, 0.8))),
        _Solid("cylinder", cyl, colors[2], hue[2], 4,
               _Motion(np.array([lanes[2], y0[2], cyl[1]]), np.array([0.35, 0.35, 0.0]), np.ones(3),
                       np.array([phases[2, 0], phases[2, 0] + np.pi / 2, 0.0]), False, z_axis, 0.0,
                       rng.uniform(0.5, 1.0) * rng.choice([-1, 1]))),
        _Solid("sphere", np.array([r_small]), colors[3], hue[3], 3,
               _Motion(np.array([lanes[3], y0[3], 1.65]), np.array([0.5, 0.3, 0.25]), np.array([1.0, 1.0, 2.0]),
                       np.array([phases[3, 0], phases[3, 0] + np.pi / 2, 2 * phases[3, 0]]), False, spin_axes[3],
                       0.0, rng.uniform(0.5, 1.0))),
    ]
    side = rng.choice([-1.0, 1.0])
    still = np.zeros(3)
    static_colors = _palette(rng, 6, (0.3, 0.7), (0.55, 0.85)).reshape(2, 3, 3)
    static = [
        _Solid("box", np.array([0.3, 0.3, 0.45]), static_colors[0], 0.0, 3,
               _Motion(np.array([2.3 * side, 2.0, 0.45]), still, still, still, False, z_axis, rng.uniform(0, 1), 0.0)),
        _Solid("cylinder", np.array([0.25, 0.7]), static_colors[1], 0.0, 5,
               _Motion(np.array([-2.3 * side, 2.2, 0.7]), still, still, still, False, z_axis, 0.0, 0.0)),
    ]
    return static, dynamic


def _random_planes(rng: np.random.Generator) -> list[_Plane]:
    """The ground (z = 0) and the backdrop (y = BACKDROP_Y) with seeded colours and noise."""
    noise = rng.uniform(0, 1, (256, 256)).astype(np.float32)
    ground_colors = _palette(rng, 2, (0.15, 0.35), (0.45, 0.8))
    backdrop_colors = np.concatenate([_palette(rng, 5, (0.3, 0.6), (0.5, 0.85)), [[0.92, 0.9, 0.85]]])
    order = rng.integers(0, 5, 64)
    return [
        _Plane(np.zeros(3), np.array([0.0, 0.0, 1.0]), "ground", ground_colors.astype(np.float32), order, noise),
        _Plane(np.array([0.0, BACKDROP_Y, 0.0]), np.array([0.0, -1.0, 0.0]), "backdrop",
               backdrop_colors.astype(np.float32), order, noise),
    ]


@dataclass
class RayHits:
    """What the ray caster saw along a set of rays.

    Attributes:
        t: [...] distance along each (unit) ray to the visible surface, inf for sky.
        rgb: [..., 3] float32 shaded colour in [0, 1].
    """

    t: np.ndarray
    rgb: np.ndarray


@dataclass
class _StaticLayer:
    """Per-camera precomputation of the static part (planes + static solids), flattened.

    origin [3], dirs [P, 3], t [P], points [P, 3], ambient_rgb [P, 3] = albedo·AMBIENT,
    direct_rgb [P, 3] = albedo·DIFFUSE·max(n·l, 0)·(static shadows), receiver [P] bool
    (the static hit is a plane, which receives shadows), shape (H·s, W·s).
    """

    origin: np.ndarray
    dirs: np.ndarray
    t: np.ndarray
    points: np.ndarray
    ambient_rgb: np.ndarray
    direct_rgb: np.ndarray
    receiver: np.ndarray
    shape: tuple[int, int]


class SyntheticScene:
    """The procedural scene of one :class:`SynthConfig`: cameras, planes and solids.

    ``cameras`` are OpenCV cameras at the output resolution in the scene's own world
    (metres, +z up), ``cam00`` first; ``point_rng`` draws the ``points3d.ply`` samples.
    Two paths shade the same image: :meth:`cast` (brute force, any rays; the reference)
    and :meth:`render_samples` (per-camera static layer + screen rectangles; the fast one).
    """

    def __init__(self, config: SynthConfig):
        config.validate()
        self.config = config
        seeds = np.random.SeedSequence(config.seed).spawn(4)
        rig_rng, solid_rng, plane_rng, self.point_rng = (np.random.default_rng(s) for s in seeds)
        self.cameras = camera_rig(config.num_cameras, config.width, config.height, rig_rng)
        self.static_solids, self.dynamic_solids = _random_solids(solid_rng)
        self.planes = _random_planes(plane_rng)

    def phase(self, frame: int) -> float:
        """Clip phase s = frame / num_frames of a frame index."""
        return frame / self.config.num_frames

    # -- reference path: every primitive on every ray
    def cast(self, origins: np.ndarray, dirs: np.ndarray, phase: float) -> RayHits:
        """Shade arbitrary rays by brute force (every primitive on every ray).

        origins: [3] or [..., 3]; dirs: [..., 3] unit directions. Returns t [...] and rgb [..., 3].
        """
        shape = dirs.shape[:-1]
        d = np.asarray(dirs, dtype=np.float32).reshape(-1, 3)
        o = np.asarray(origins, dtype=np.float32)
        o = o if o.ndim == 1 else o.reshape(-1, 3)
        solids = self.static_solids + self.dynamic_solids
        t, albedo, ndl, prim = _nearest(self.planes + solids, o, d, phase)
        points = o + np.where(np.isinf(t), 0, t)[:, None] * d
        receiver = (prim >= 0) & (prim < len(self.planes))
        shadow = np.ones_like(t)
        for solid in solids:
            shadow[receiver] *= 1 - solid.shadow(points[receiver], phase)
        rgb = albedo * (AMBIENT + DIFFUSE * ndl * shadow)[:, None]
        rgb[np.isinf(t)] = SKY
        return RayHits(t.reshape(shape), np.clip(rgb, 0, 1).reshape(*shape, 3))

    # -- fast path: static layer once per camera, dynamic solids and shadows in screen crops
    def static_layer(self, index: int) -> _StaticLayer:
        """Precompute the static planes and solids of camera ``index`` (supersampled)."""
        cam = self.cameras[index]
        origin, dirs = camera_rays(cam, self.config.supersample)
        shape = dirs.shape[:2]
        d = dirs.reshape(-1, 3)
        t, albedo, ndl, prim = _nearest(self.planes + self.static_solids, origin, d, 0.0)
        points = origin + np.where(np.isinf(t), 0, t)[:, None] * d
        receiver = (prim >= 0) & (prim < len(self.planes))
        shadow = np.ones_like(t)
        for solid in self.static_solids:
            shadow[receiver] *= 1 - solid.shadow(points[receiver], 0.0)
        ambient_rgb = albedo * AMBIENT
        direct_rgb = albedo * (DIFFUSE * ndl * shadow)[:, None]
        ambient_rgb[np.isinf(t)] = SKY
        return _StaticLayer(origin, d, t, points, ambient_rgb, direct_rgb, receiver, shape)

    def render_samples(self, index: int, frame: int, layer: _StaticLayer | None = None) -> RayHits:
        """All supersamples of camera ``index`` at ``frame``: t [H·s, W·s], rgb [H·s, W·s, 3].

        Equal (to float rounding) to :meth:`cast` on :func:`camera_rays`, but only rays in
        the screen rectangle around each moving solid (and around its shadow on each
        plane) are tested against it.
        """
        layer = layer if layer is not None else self.static_layer(index)
        cam = self.cameras[index]
        s = self.config.supersample
        Hs, Ws = layer.shape
        phase = self.phase(frame)
        K = cam.K * np.array([[s], [s], [1.0]])
        shadow = np.ones(layer.shape, dtype=np.float32)
        for solid in self.dynamic_solids:
            box = _shadow_rect(solid, phase, self.planes, cam.viewmat, K, Ws, Hs)
            if box is not None:
                idx = _rect_indices(box, Ws)
                sel = idx[layer.receiver[idx]]
                shadow.reshape(-1)[sel] *= 1 - solid.shadow(layer.points[sel], phase)
        rgb = layer.ambient_rgb + layer.direct_rgb * shadow.reshape(-1, 1)
        t = layer.t.copy()
        for solid in self.dynamic_solids:
            center, _ = solid.motion.pose(phase)
            box = _sphere_rect(center, solid.bound_radius, cam.viewmat, K, Ws, Hs)
            if box is None:
                continue
            idx = _rect_indices(box, Ws)
            t_obj = solid.intersect(layer.origin, layer.dirs[idx], phase)
            front = t_obj < t[idx]
            idx, t_obj = idx[front], t_obj[front]
            if len(idx) == 0:
                continue
            normal, albedo = solid.surface(layer.origin + t_obj[:, None] * layer.dirs[idx], phase)
            ndl = np.maximum(normal @ LIGHT.astype(np.float32), 0)
            rgb[idx] = albedo * (AMBIENT + DIFFUSE * ndl)[:, None]
            t[idx] = t_obj
        return RayHits(t.reshape(Hs, Ws), np.clip(rgb, 0, 1).reshape(Hs, Ws, 3))

    def render(self, index: int, frame: int, layer: _StaticLayer | None = None) -> np.ndarray:
        """Image of camera ``index`` at ``frame``: float32 [H, W, 3] in [0, 1] (box-filtered supersamples)."""
        return box_filter(self.render_samples(index, frame, layer).rgb, self.config.supersample)


def box_filter(samples: np.ndarray, s: int) -> np.ndarray:
    """Average each s×s block of supersamples [H·s, W·s, C] into one pixel [H, W, C]."""
    out = np.zeros((samples.shape[0] // s, samples.shape[1] // s, samples.shape[2]), dtype=np.float32)
    for dy in range(s):
        for dx in range(s):
            out += samples[dy::s, dx::s]
    return out / np.float32(s * s)


def _nearest(prims: list, o: np.ndarray, d: np.ndarray, phase: float):
    """Nearest hit of rays among primitives: t [P], albedo [P, 3], max(n·l, 0) [P], primitive index [P] (-1: none)."""
    ts = np.stack([p.intersect(o, d, phase) for p in prims])
    prim = np.argmin(ts, axis=0)
    t = ts[prim, np.arange(d.shape[0])]
    prim[np.isinf(t)] = -1
    albedo = np.zeros((d.shape[0], 3), dtype=np.float32)
    ndl = np.zeros(d.shape[0], dtype=np.float32)
    for k, p in enumerate(prims):
        sel = np.nonzero(prim == k)[0]
        if len(sel):
            oo = o if o.ndim == 1 else o[sel]
            normal, albedo[sel] = p.surface(oo + t[sel, None] * d[sel], phase)
            ndl[sel] = np.maximum(normal @ LIGHT.astype(np.float32), 0)
    return t, albedo, ndl, prim


def _project_rect(corners: np.ndarray, viewmat: np.ndarray, K: np.ndarray, W: int, H: int):
    """Sample-index rectangle (x0, x1, y0, y1), end exclusive, containing the projections of
    ``corners`` [M, 3]; the whole image when a corner is not in front of the camera;
    None when the rectangle is off-screen. Sample j has its centre at pixel coordinate j + 0.5."""
    cam = corners @ viewmat[:3, :3].T + viewmat[:3, 3]
    if np.any(cam[:, 2] <= 1e-3):
        return 0, W, 0, H
    u = K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2]
    v = K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]
    x0, x1 = max(int(np.floor(u.min() - 0.5)) - 1, 0), min(int(np.ceil(u.max() - 0.5)) + 2, W)
    y0, y1 = max(int(np.floor(v.min() - 0.5)) - 1, 0), min(int(np.ceil(v.max() - 0.5)) + 2, H)
    return (x0, x1, y0, y1) if x0 < x1 and y0 < y1 else None


def _sphere_rect(center: np.ndarray, radius: float, viewmat, K, W, H):
    """Screen rectangle of a bounding sphere (the projection of its bounding cube's corners)."""
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
    return _project_rect(center + radius * signs, viewmat, K, W, H)


def _shadow_rect(solid: _Solid, phase: float, planes: list[_Plane], viewmat, K, W, H):
    """Screen rectangle containing every plane point the solid's shadow can darken.

    The occluded points lie within 1.15·ρ of the light ray through the centre: on a plane
    with normal n, inside a disc of radius 1.15·ρ / |l·n| around where that line meets it;
    the rectangle bounds the projections of the square around each such disc.
    """
    center, _ = solid.motion.pose(phase)
    corners = []
    for plane in planes:
        cos = float(LIGHT @ plane.normal)
        if abs(cos) < 1e-6:
            return 0, W, 0, H
        q = center - ((center - plane.point) @ plane.normal / cos) * LIGHT
        u = np.cross(plane.normal, [1.0, 0.0, 0.0] if abs(plane.normal[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(plane.normal, u)
        r = 1.15 * solid.shadow_radius / abs(cos) * 1.01
        corners += [q + r * (a * u + b * v) for a in (-1, 1) for b in (-1, 1)]
    return _project_rect(np.array(corners), viewmat, K, W, H)


def _rect_indices(box: tuple[int, int, int, int], W: int) -> np.ndarray:
    """Flat sample indices [h·w] of the rectangle ``(x0, x1, y0, y1)`` in a row-major grid of width W."""
    x0, x1, y0, y1 = box
    return (np.arange(y0, y1)[:, None] * W + np.arange(x0, x1)[None, :]).reshape(-1)


# --------------------------------------------------------------------------- writing


@dataclass
class SynthResult:
    """What :func:`write_synthetic_scene` wrote."""

    path: Path
    cameras: list[Camera]
    num_points: int
    poses_bounds: np.ndarray  # [N, 17]


def write_ply_points(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Binary little-endian PLY with ``float x, y, z`` and ``uchar red, green, blue``
    (the COLMAP / 3DGS ``points3d.ply`` layout). xyz: [M, 3]; rgb: [M, 3] uint8."""
    data = np.empty(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                     ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for k, name in enumerate("xyz"):
        data[name] = xyz[:, k]
    for k, name in enumerate(("red", "green", "blue")):
        data[name] = rgb[:, k]
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(xyz)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    path.write_bytes(header.encode("ascii") + data.tobytes())


def _to_uint8(rgb: np.ndarray) -> np.ndarray:
    return np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)


def _prepare_target(out_dir: Path, force: bool) -> None:
    """Refuse an existing non-empty folder (or a file) at ``out_dir`` unless ``force``."""
    if out_dir.is_file() or out_dir.is_symlink():
        if not force:
            raise OMG4Error(f"{out_dir} exists and is not a folder (use --force to replace it)")
    elif out_dir.is_dir() and any(out_dir.iterdir()) and not force:
        raise OMG4Error(f"{out_dir} exists and is not empty (use --force to overwrite it)")


def _replace_dir(tmp: Path, out_dir: Path) -> None:
    """Move the finished folder ``tmp`` onto ``out_dir``; an old ``out_dir`` is moved aside first
    and deleted only after the rename, so an interruption never leaves a half-written scene."""
    old = None
    if out_dir.exists() or out_dir.is_symlink():
        old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.old.{os.getpid()}-", dir=out_dir.parent))
        os.replace(out_dir, old / "x")
    os.replace(tmp, out_dir)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def write_synthetic_scene(out_dir: str | os.PathLike, config: SynthConfig = SynthConfig(), force: bool = False,
                          progress: bool = True) -> SynthResult:
    """Render the scene of ``config`` and write it as an N3DV folder at ``out_dir``.

    The folder is built beside the target and renamed into place when complete. An
    existing non-empty ``out_dir`` is refused unless ``force``.
    """
    import av
    from tqdm import tqdm

    config.validate()
    out_dir = Path(os.path.abspath(out_dir))
    _prepare_target(out_dir, force)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    scene = SyntheticScene(config)
    cams = scene.cameras
    n_train = len(cams) - 1
    per_cam = -(-config.num_points // n_train)
    near, far = np.zeros(len(cams)), np.zeros(len(cams))
    xyz, rgb = [], []
    remove_stale_temporaries(out_dir.parent, f".{out_dir.name}.tmp-")
    remove_stale_temporaries(out_dir.parent, f".{out_dir.name}.old.")
    tmp = out_dir.parent / f".{out_dir.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:12]}"
    tmp.mkdir()
    try:
        with tqdm(total=len(cams) * config.num_frames, desc="omg4 synth", unit="frame", disable=not progress) as bar:
            for i, cam in enumerate(cams):
                layer = scene.static_layer(i)
                with av.open(str(tmp / f"{cam.name}.mp4"), "w") as container:
                    stream = container.add_stream("libx264", rate=Fraction(config.fps).limit_denominator(1001))
                    stream.width, stream.height, stream.pix_fmt = cam.width, cam.height, "yuv420p"
                    stream.options = {"crf": str(config.crf), "preset": "medium"}
                    for f in range(config.num_frames):
                        samples = scene.render_samples(i, f, layer)
                        if f == 0:
                            near[i], far[i], pts = _frame0_samples(cam, layer, samples)
                            if i > 0:
                                pick = scene.point_rng.choice(len(pts[0]), min(per_cam, len(pts[0])), replace=False)
                                xyz.append(pts[0][pick])
                                rgb.append(pts[1][pick])
                        image = box_filter(samples.rgb, config.supersample)
                        frame = av.VideoFrame.from_ndarray(_to_uint8(image), format="rgb24")
                        container.mux(stream.encode(frame))
                        bar.update(1)
                    container.mux(stream.encode(None))
        points = np.concatenate(xyz)[: config.num_points]
        colors = _to_uint8(np.concatenate(rgb)[: config.num_points])
        poses_bounds = llff_poses_bounds(cams, near, far)
        np.save(tmp / "poses_bounds.npy", poses_bounds)
        write_ply_points(tmp / "points3d.ply", points, colors)
        meta = {"generator": "omg4 synth", **asdict(config), "test_camera": "cam00",
                "world": "metres, +z up, LLFF poses", "time": "timestamp = frame / fps; motion phase = frame / frames"}
        (tmp / "synth.json").write_text(json.dumps(meta, indent=2) + "\n")
        _replace_dir(tmp, out_dir)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return SynthResult(out_dir, cams, len(points), poses_bounds)


def _frame0_samples(cam: Camera, layer: _StaticLayer, samples: RayHits):
    """Near/far z-depth bounds (0.9·min, 1.1·max) and the visible surface points
    ([K, 3], colours [K, 3]) of one camera's frame-0 supersamples."""
    t = samples.t.reshape(-1)
    hit = np.isfinite(t)
    points = layer.origin + t[hit, None] * layer.dirs[hit]
    depth = (points - layer.origin) @ cam.viewmat[2, :3].astype(np.float32)
    return 0.9 * depth.min(), 1.1 * depth.max(), (points, samples.rgb.reshape(-1, 3)[hit])
