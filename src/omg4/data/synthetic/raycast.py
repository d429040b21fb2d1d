"""The synthetic scene's ray caster: shades rays against the scene's primitives, vectorized in numpy.

:class:`SyntheticScene` builds the rig (:mod:`.rig`) and the world (:mod:`.world`) of one
:class:`~omg4.data.synthetic.world.SynthConfig` and shades rays two ways: :meth:`~SyntheticScene.cast`
(every primitive on every ray; the reference) and :meth:`~SyntheticScene.render_samples` (a
per-camera static layer, and the moving solids and their shadows only in their screen
rectangles; the fast path). Each pixel averages ``supersample``² stratified rays (:func:`box_filter`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omg4.data.synthetic.rig import camera_rays, camera_rig
from omg4.data.synthetic.world import (AMBIENT, DIFFUSE, LIGHT, SKY, Plane, Solid, SynthConfig, random_planes,
                                       random_solids)

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
class StaticLayer:
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
        self.static_solids, self.dynamic_solids = random_solids(solid_rng)
        self.planes = random_planes(plane_rng)

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
    def static_layer(self, index: int) -> StaticLayer:
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
        return StaticLayer(origin, d, t, points, ambient_rgb, direct_rgb, receiver, shape)

    def render_samples(self, index: int, frame: int, layer: StaticLayer | None = None) -> RayHits:
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

    def render(self, index: int, frame: int, layer: StaticLayer | None = None) -> np.ndarray:
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


def _shadow_rect(solid: Solid, phase: float, planes: list[Plane], viewmat, K, W, H):
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
