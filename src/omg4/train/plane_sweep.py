"""Dense first-frame points by plane-sweep stereo (an initialization for scenes without points).

The official pipeline starts from COLMAP multi-view-stereo points of frame 0
(rt4dgs §3.5: ``patch_match_stereo`` + ``stereo_fusion`` with known poses). This module does
the same job with known cameras and no external tool, in the classic form:

1. For every training camera of the first frame (the *reference*), pick its nearest cameras
   that look the same way; sweep fronto-parallel depth planes, warp each neighbour's image
   onto the reference through every plane (a plane-induced homography, here by projecting
   the back-projected pixel), and score each depth by the zero-mean normalized
   cross-correlation (ZNCC) of small grey-level windows — robust to the exposure and white
   balance differences between cameras. The score of a depth is the mean of the best half
   of the neighbours' ZNCCs (so an occluded neighbour does not veto a depth); the depth with
   the best score wins and is refined by a parabola through its two neighbours.
2. Keep a pixel when its score is high, its window has texture, and its depth agrees with
   the depth map of at least one neighbour (geometric consistency, as in stereo fusion).
3. Fuse all references' points, keep one per small voxel, and subsample.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from tqdm.auto import tqdm

from omg4.data.scene import Camera, PointCloud, Scene
from omg4.errors import DataError


@dataclass(frozen=True)
class SweepConfig:
    """Plane-sweep settings; depths in normalized world units."""

    num_depths: int = 160
    near: float = 0.5
    far_factor: float = 2.3  # far plane = far_factor × the largest camera distance from the origin
    neighbours: int = 4
    max_axis_angle_deg: float = 50.0
    window: int = 7
    min_score: float = 0.6
    min_texture: float = 0.015  # grey-level standard deviation of the reference window
    consistency: float = 0.02  # relative depth agreement with a neighbour's depth map
    depth_chunk: int = 16


@dataclass
class DepthMap:
    """One reference camera's sweep result: depth [H, W], 0 where rejected."""

    camera: Camera
    depth: torch.Tensor


def _grey(img: np.ndarray, device: torch.device) -> torch.Tensor:
    """[H, W] float32 luma of an [H, W, 3] image in [0, 1], on ``device``."""
    rgb = torch.from_numpy(np.ascontiguousarray(img, dtype=np.float32)).to(device)
    return rgb @ torch.tensor([0.299, 0.587, 0.114], device=device)


def _f64(array: np.ndarray, device: torch.device) -> torch.Tensor:
    return torch.as_tensor(np.asarray(array, dtype=np.float64), device=device)


def _pixel_rays(cam: Camera, device: torch.device) -> torch.Tensor:
    """[3, H·W] camera-frame rays with z = 1 through the pixel centres (row-major), on ``device``."""
    v, u = torch.meshgrid(torch.arange(cam.height, dtype=torch.float64, device=device) + 0.5,
                          torch.arange(cam.width, dtype=torch.float64, device=device) + 0.5, indexing="ij")
    pix = torch.stack([u.reshape(-1), v.reshape(-1), torch.ones(u.numel(), dtype=torch.float64, device=device)])
    return torch.linalg.solve(_f64(cam.K, device), pix)


def _relative_projection(ref: Camera, other: Camera, rays: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(a [3, P], b [3]) with ``K_o (R_o X + t_o) = depth · a + b`` for X at ``depth`` on a ref ray."""
    device = rays.device
    R_r, t_r = _f64(ref.viewmat[:3, :3], device), _f64(ref.viewmat[:3, 3], device)
    R_o, t_o = _f64(other.viewmat[:3, :3], device), _f64(other.viewmat[:3, 3], device)
    K_o = _f64(other.K, device)
    A = R_o @ R_r.T
    return K_o @ A @ rays, K_o @ (t_o - A @ t_r)


def _sample(image: torch.Tensor, pix: torch.Tensor, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear samples of ``image`` [C, H, W] at pixel positions ``pix`` [..., 2] and a validity mask."""
    grid = torch.stack([2 * pix[..., 0] / width - 1, 2 * pix[..., 1] / height - 1], -1)
    inside = (grid.abs() <= 1).all(-1)
    out = F.grid_sample(image.unsqueeze(0).expand(grid.shape[0], -1, -1, -1), grid.float(),
                        mode="bilinear", padding_mode="border", align_corners=False)
    return out, inside


def _window_stats(x: torch.Tensor, window: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Windowed mean and variance of [B, 1, H, W] maps."""
    pad = window // 2
    mean = F.avg_pool2d(x, window, 1, pad, count_include_pad=False)
    var = F.avg_pool2d(x * x, window, 1, pad, count_include_pad=False) - mean * mean
    return mean, var.clamp_min(0)


def choose_neighbours(cameras: list[Camera], index: int, count: int, max_angle_deg: float) -> list[int]:
    """The ``count`` cameras nearest to camera ``index`` whose optical axes are within the angle."""
    axis = cameras[index].viewmat[2, :3]
    cos_min = np.cos(np.radians(max_angle_deg))
    distance = [float(np.linalg.norm(c.center - cameras[index].center)) for c in cameras]
    candidates = [(distance[j], j) for j, c in enumerate(cameras)
                  if distance[j] > 1e-9 and float(c.viewmat[2, :3] @ axis) >= cos_min]
    return [j for _, j in sorted(candidates)[:count]]


def sweep_depth(ref: Camera, ref_grey: torch.Tensor, others: list[tuple[Camera, torch.Tensor]],
                depths: torch.Tensor, cfg: SweepConfig) -> DepthMap:
    """Best-ZNCC depth per reference pixel over the planes ``depths`` (step 1 above)."""
    H, W = ref.height, ref.width
    device = ref_grey.device
    rays = _pixel_rays(ref, device)
    r = ref_grey.view(1, 1, H, W)
    r_mean, r_var = _window_stats(r, cfg.window)
    keep = max(1, (len(others) + 1) // 2)
    projections = [_relative_projection(ref, cam, rays) for cam, _ in others]
    scores = torch.empty(len(depths), H, W, device=device)
    for start in range(0, len(depths), cfg.depth_chunk):
        d = depths[start:start + cfg.depth_chunk].double()
        per_neighbour = []
        for (cam, grey), (a, b) in zip(others, projections):
            p = d.view(-1, 1, 1) * a.unsqueeze(0) + b.view(1, 3, 1)  # [D, 3, P]
            z = p[:, 2]
            pix = (p[:, :2] / z.clamp_min(1e-9).unsqueeze(1)).transpose(1, 2).reshape(-1, H, W, 2)
            warped, inside = _sample(grey.view(1, cam.height, cam.width), pix, cam.width, cam.height)
            valid = (inside & (z.view(-1, H, W) > 0)).unsqueeze(1)
            w_mean, w_var = _window_stats(warped, cfg.window)
            cov = F.avg_pool2d(warped * r, cfg.window, 1, cfg.window // 2, count_include_pad=False) - w_mean * r_mean
            ncc = cov / torch.sqrt(w_var * r_var + 1e-8)
            per_neighbour.append(torch.where(valid, ncc, torch.full_like(ncc, -1.0))[:, 0])
        stacked = torch.stack(per_neighbour, 0)  # [N, D, H, W]
        scores[start:start + len(d)] = stacked.topk(keep, dim=0).values.mean(0)
    best_score, best = scores.max(0)
    depth = depths[best]
    # sub-plane refinement: vertex of the parabola through the best score and its neighbours
    inner = (best > 0) & (best < len(depths) - 1)
    lo = scores.gather(0, (best - 1).clamp_min(0).unsqueeze(0))[0]
    hi = scores.gather(0, (best + 1).clamp_max(len(depths) - 1).unsqueeze(0))[0]
    curvature = lo - 2 * best_score + hi
    offset = torch.where(inner & (curvature < 0), 0.5 * (lo - hi) / curvature.clamp_max(-1e-9), torch.zeros_like(lo))
    step = float(depths[1] - depths[0]) if len(depths) > 1 else 0.0
    depth = depth + offset.clamp(-0.5, 0.5) * step
    texture = r_var[0, 0].sqrt() >= cfg.min_texture
    depth = torch.where((best_score >= cfg.min_score) & texture, depth, torch.zeros_like(depth))
    return DepthMap(camera=ref, depth=depth)


def _unproject(dm: DepthMap) -> tuple[torch.Tensor, torch.Tensor]:
    """World points [P, 3] (float64) of a depth map's kept pixels and their flat pixel indices."""
    flat = dm.depth.reshape(-1).double()
    device = flat.device
    idx = torch.nonzero(flat > 0)[:, 0]
    rays = _pixel_rays(dm.camera, device)[:, idx]
    R, t = _f64(dm.camera.viewmat[:3, :3], device), _f64(dm.camera.viewmat[:3, 3], device)
    return ((rays * flat[idx]).T - t) @ R, idx


def consistent_mask(dm: DepthMap, points: torch.Tensor, neighbours: list[DepthMap], tolerance: float) -> torch.Tensor:
    """[P] bool: the point's depth in at least one neighbour agrees with that neighbour's map (step 2)."""
    device = points.device
    ok = torch.zeros(points.shape[0], dtype=torch.bool, device=device)
    for other in neighbours:
        cam = other.camera
        x = points @ _f64(cam.viewmat[:3, :3], device).T + _f64(cam.viewmat[:3, 3], device)
        z = x[:, 2]
        uv = (x @ _f64(cam.K, device).T)[:, :2] / z.clamp_min(1e-9).unsqueeze(1)
        col, row = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        inside = (z > 0) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        seen = other.depth[row.clamp(0, cam.height - 1), col.clamp(0, cam.width - 1)].double()
        ok |= inside & (seen > 0) & ((seen - z).abs() <= tolerance * z)
    return ok


def plane_sweep_points(scene: Scene, num_points: int, *, seed: int = 0, cfg: SweepConfig = SweepConfig(),
                       progress: bool = True, device: torch.device | str = "cpu") -> PointCloud:
    """Coloured first-frame points from plane-sweep stereo over the training cameras (steps 1–3).

    The sweep runs on ``device`` (a GPU computes every camera's depth map in a fraction of
    the CPU's time); the points come back as CPU arrays.

    Raises:
        DataError: when no camera has a usable neighbour or no pixel passes the checks.
    """
    views = scene.first_frame_views()
    cameras = [v.camera for v in views]
    images = [v.image() for v in views]
    device = torch.device(device)
    greys = [_grey(img, device) for img in images]
    far = cfg.far_factor * max(float(np.linalg.norm(c.center)) for c in cameras)
    depths = torch.linspace(cfg.near, far, cfg.num_depths, device=device)
    neighbours = [choose_neighbours(cameras, i, cfg.neighbours, cfg.max_axis_angle_deg) for i in range(len(cameras))]
    maps: dict[int, DepthMap] = {}
    for i in tqdm(range(len(cameras)), desc="plane sweep", disable=not progress):
        if len(neighbours[i]) >= 2:
            maps[i] = sweep_depth(cameras[i], greys[i], [(cameras[j], greys[j]) for j in neighbours[i]], depths, cfg)
    if not maps:
        raise DataError("plane-sweep initialization: no training camera has two neighbours looking the same way")
    xyz, rgb = [], []
    for i, dm in maps.items():
        points, idx = _unproject(dm)
        ok = consistent_mask(dm, points, [maps[j] for j in neighbours[i] if j in maps], cfg.consistency)
        xyz.append(points[ok].cpu().numpy())
        rgb.append(images[i].reshape(-1, 3)[idx[ok].cpu().numpy()])
    xyz_all, rgb_all = np.concatenate(xyz), np.concatenate(rgb).astype(np.float32)
    if len(xyz_all) == 0:
        raise DataError("plane-sweep initialization found no consistent point; use --init rays or random")
    voxel = 1e-3 * far
    _, first_in_voxel = np.unique(np.floor(xyz_all / voxel).astype(np.int64), axis=0, return_index=True)
    xyz_all, rgb_all = xyz_all[first_in_voxel], rgb_all[first_in_voxel]
    if len(xyz_all) > num_points:
        pick = np.random.default_rng(seed).choice(len(xyz_all), num_points, replace=False)
        xyz_all, rgb_all = xyz_all[pick], rgb_all[pick]
    return PointCloud(xyz=xyz_all, rgb=rgb_all)
