"""What the synthetic scene contains: its parameters, textures and primitives, drawn from one seed.

An infinite textured ground plane (z = 0) and backdrop (y = :data:`BACKDROP_Y`), two static
solids and four moving, rotating, colour-changing textured solids (two spheres, a box, a capped
cylinder), lit by one directional light (:data:`LIGHT`) with Lambertian shading; every solid
casts a soft analytic "blob" shadow on the planes. Each primitive answers the ray caster's three
questions (:mod:`omg4.data.synthetic.raycast`): where a ray hits it (``intersect``), the normal
and albedo there (``surface``) and, for solids, how much it shadows a point (``shadow``), all as
functions of the clip phase s = frame / num_frames.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass

import numpy as np

from omg4.errors import OMG4Error

BACKDROP_Y = 3.5          # backdrop plane y = BACKDROP_Y (metres)
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


@dataclass(frozen=True)
class Plane:
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
class Motion:
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
class Solid:
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
    motion: Motion

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


def random_solids(rng: np.random.Generator) -> tuple[list[Solid], list[Solid]]:
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
        Solid("sphere", np.array([r_big]), colors[0], hue[0], 4,
               Motion(np.array([lanes[0], y0[0], r_big]), np.array([0.15, 0.3, 0.8]), np.array([1.0, 1.0, 2.0]),
                       phases[0], True, spin_axes[0], phases[0, 0], rng.uniform(0.5, 1.0))),
        Solid("box", box, colors[1], hue[1], 3,
               Motion(np.array([lanes[1], y0[1], 1.05]), np.array([0.35, 0.4, 0.15]), np.ones(3),
                       phases[1], False, spin_axes[1], phases[1, 0], rng.uniform(0.4, 0.8))),
        Solid("cylinder", cyl, colors[2], hue[2], 4,
               Motion(np.array([lanes[2], y0[2], cyl[1]]), np.array([0.35, 0.35, 0.0]), np.ones(3),
                       np.array([phases[2, 0], phases[2, 0] + np.pi / 2, 0.0]), False, z_axis, 0.0,
                       rng.uniform(0.5, 1.0) * rng.choice([-1, 1]))),
        Solid("sphere", np.array([r_small]), colors[3], hue[3], 3,
               Motion(np.array([lanes[3], y0[3], 1.65]), np.array([0.5, 0.3, 0.25]), np.array([1.0, 1.0, 2.0]),
                       np.array([phases[3, 0], phases[3, 0] + np.pi / 2, 2 * phases[3, 0]]), False, spin_axes[3],
                       0.0, rng.uniform(0.5, 1.0))),
    ]
    side = rng.choice([-1.0, 1.0])
    still = np.zeros(3)
    static_colors = _palette(rng, 6, (0.3, 0.7), (0.55, 0.85)).reshape(2, 3, 3)
    static = [
        Solid("box", np.array([0.3, 0.3, 0.45]), static_colors[0], 0.0, 3,
               Motion(np.array([2.3 * side, 2.0, 0.45]), still, still, still, False, z_axis, rng.uniform(0, 1), 0.0)),
        Solid("cylinder", np.array([0.25, 0.7]), static_colors[1], 0.0, 5,
               Motion(np.array([-2.3 * side, 2.2, 0.7]), still, still, still, False, z_axis, 0.0, 0.0)),
    ]
    return static, dynamic


def random_planes(rng: np.random.Generator) -> list[Plane]:
    """The ground (z = 0) and the backdrop (y = BACKDROP_Y) with seeded colours and noise."""
    noise = rng.uniform(0, 1, (256, 256)).astype(np.float32)
    ground_colors = _palette(rng, 2, (0.15, 0.35), (0.45, 0.8))
    backdrop_colors = np.concatenate([_palette(rng, 5, (0.3, 0.6), (0.5, 0.85)), [[0.92, 0.9, 0.85]]])
    order = rng.integers(0, 5, 64)
    return [
        Plane(np.zeros(3), np.array([0.0, 0.0, 1.0]), "ground", ground_colors.astype(np.float32), order, noise),
        Plane(np.array([0.0, BACKDROP_Y, 0.0]), np.array([0.0, -1.0, 0.0]), "backdrop",
               backdrop_colors.astype(np.float32), order, noise),
    ]
