"""Evaluation as the paper's tables report it: PSNR, SSIM, LPIPS, FPS, #Gaussians, storage.

Beside them (beyond the paper): PSNR and SSIM over the pixels that move
(:mod:`omg4.metrics.dynamic`), and ``visible_fraction``: the mean share of the model's Gaussians that pass the
temporal cull and reach the rasterizer in a frame (what a frame's cost scales with).

PSNR is the standard one over all pixels and channels; SSIM is the 3DGS 11×11 Gaussian-
window SSIM; LPIPS is v0.1 with the named backbone on [−1, 1] inputs; FPS is render-only
(warm-up, synchronized, median); storage is the model file's bytes / 2^20 (MB as the
paper counts it). Renders are clamped to [0, 1] before every metric.
"""

from __future__ import annotations

import numpy as np
import torch
from tqdm.auto import tqdm

from omg4 import distributed
from omg4.data.scene import View
from omg4.data.segments import near_boundary
from omg4.errors import OMG4Error
from omg4.metrics import lpips, lpips_min_side, measure_fps_together, psnr, ssim
from omg4.metrics.dynamic import dynamic_mask, masked_psnr, masked_ssim
from omg4.metrics.frames import per_frame
from omg4.render.view import render_view, view_image

def frame_rates(models: list, views: list[View], *, fps_views: int = 30, background: torch.Tensor | None = None,
                backend: str = "auto", device: torch.device | str = "cpu") -> list[dict]:
    """Render-only FPS of each of ``models`` (on ``device``) over ``fps_views`` of ``views`` spread evenly
    (:func:`omg4.metrics.timing.measure_fps`); several models take turns frame by frame
    (:func:`~omg4.metrics.timing.measure_fps_together`), so their ratio is not a host's slow spell. In a
    distributed job rank 0 times them alone and every rank gets its figures."""
    rates = None
    if distributed.world().main:
        step = max(1, len(views) // fps_views)
        timed = views[::step][:fps_views]
        renderers = [lambda v, m=m: render_view(m, v.camera, v.timestamp, background=background, backend=backend,
                                                device=device) for m in models]
        rates = measure_fps_together(renderers, timed, warmup=min(3, len(timed)), device=device)
    return distributed.gather_objects(rates, "sharing the frame rates")[0]


class _ClipImages:
    """The ground-truth images of ``views`` as a lazy sequence (read one at a time)."""

    def __init__(self, views: list[View]):
        self.views = views

    def __len__(self) -> int:
        return len(self.views)

    def __getitem__(self, i: int) -> np.ndarray:
        return self.views[i].image()


def dynamic_masks(views: list[View]) -> dict[str, np.ndarray]:
    """The dynamic-region mask of each camera with at least two views in ``views``
    (:func:`omg4.metrics.dynamic.dynamic_mask`), keyed by camera name."""
    by_camera: dict[str, list[View]] = {}
    for v in views:
        by_camera.setdefault(v.camera.name, []).append(v)
    return {name: dynamic_mask(_ClipImages(clip)) for name, clip in by_camera.items() if len(clip) >= 2}


def evaluate(model, views: list[View], *, storage_bytes: int | None = None, lpips_nets: tuple[str, ...] = ("alex",),
             background: torch.Tensor | None = None, backend: str = "auto", fps_views: int = 30,
             progress: bool = True, device: torch.device | str = "cpu",
             masks: dict[str, np.ndarray] | None = None, time_frames: bool = True) -> dict:
    """Per-view and mean metrics of ``model`` on ``views``, plus FPS, Gaussian count and storage.

    ``model`` and ``background`` live on ``device``, where the renders, ground truths and
    metrics are computed (FPS synchronizes CUDA around every timed frame). ``psnr_dynamic``
    and ``ssim_dynamic`` are PSNR and SSIM over each test camera's dynamic region
    (``masks``, by default :func:`dynamic_masks` of ``views``; pass them in to evaluate
    several models on one scene without recomputing), ``dynamic_fraction`` its share of
    the pixels; the means skip views whose camera has no moving pixel. LPIPS skips views smaller than its
    network takes (:func:`~omg4.metrics.lpips_min_side`; None when no view fits). With ``time_frames=False``
    ``fps`` and ``fps_detail`` are None, for a caller that times several models together (:func:`frame_rates`).
    In a distributed job each rank renders its share of the views and every rank returns the same result (rows in
    view order; FPS timed by rank 0). ``bitrate_mbps`` is the storage per second of the model's time range (for
    video captures, whose times are seconds). A sequence of segments (``model.ranges``) also reports the views near
    a boundary between segments and the others apart (``boundary``, ``interior``: mean PSNR, SSIM, view count).
    ``per_frame`` summarizes every view, not only the mean: the worst frame, the spread and the 5th percentile of
    PSNR and SSIM (:func:`omg4.metrics.frames.per_frame`).
    """
    if not views:
        raise OMG4Error("there are no test views to evaluate on")
    masks = dynamic_masks(views) if masks is None else masks
    world = distributed.world()
    per_view = []
    for v in tqdm(world.shard(views), desc="eval", disable=not (progress and world.main), dynamic_ncols=True):
        with torch.no_grad():
            rendered, sl = render_view(model, v.camera, v.timestamp, background=background, backend=backend,
                                       device=device)
        img, gt = rendered.image.clamp(0.0, 1.0), view_image(v, device)
        row = {"camera": v.camera.name, "frame": v.frame_index, "time": v.timestamp, "psnr": psnr(img, gt),
               "ssim": float(ssim(img, gt)), "visible_fraction": sl.index.numel() / max(sl.num_total, 1)}
        if hasattr(model, "ranges"):
            row["boundary"] = near_boundary(v.timestamp, model.ranges, model.meta["fps"])
        mask = masks.get(v.camera.name)
        if mask is not None and mask.any():
            row.update(psnr_dynamic=masked_psnr(img, gt, mask), ssim_dynamic=masked_ssim(img, gt, mask),
                       dynamic_fraction=float(mask.mean()))
        for net in lpips_nets:
            if min(v.camera.width, v.camera.height) >= lpips_min_side(net, img.device):
                row[f"lpips_{net}"] = lpips(img, gt, net)
        per_view.append(row)
    per_view = distributed.interleave(distributed.gather_objects(per_view, "gathering the metrics"))
    keys = list(dict.fromkeys(k for r in per_view for k in r if k not in ("camera", "frame", "time", "boundary")))
    mean = {k: float(np.mean([r[k] for r in per_view if k in r])) for k in keys}
    for k in ("psnr_dynamic", "ssim_dynamic", "dynamic_fraction", *(f"lpips_{net}" for net in lpips_nets)):
        mean.setdefault(k, None)
    fps = frame_rates([model], views, fps_views=fps_views, background=background, backend=backend,
                      device=device)[0] if time_frames else None
    t0, t1 = model.config.time_range
    segments = {}
    if hasattr(model, "ranges"):
        for name, rows in (("boundary", [r for r in per_view if r["boundary"]]),
                           ("interior", [r for r in per_view if not r["boundary"]])):
            segments[name] = {"num_views": len(rows), **{k: float(np.mean([r[k] for r in rows])) if rows else None
                                                         for k in ("psnr", "ssim")}}
        segments["num_segments"] = model.num_segments
    return {
        **mean,
        **segments,
        "fps": None if fps is None else fps["fps"],
        "fps_detail": fps,
        "num_gaussians": int(model.num_gaussians),
        "storage_mb": storage_bytes / 2**20 if storage_bytes is not None else None,
        "bitrate_mbps": 8 * storage_bytes / (t1 - t0) / 1e6 if storage_bytes is not None else None,
        "num_views": len(views),
        "per_frame": per_frame(per_view),
        "per_view": per_view,
    }
