"""Evaluation metrics: PSNR, 3DGS SSIM, MS-SSIM, offline LPIPS and render-only FPS timing.

See each module for the exact variant (rt4dgs §3.2 and §6, omg4 §10, data §2–§3).
"""

from omg4.metrics.lpips import LPIPS, load_lpips_weights, lpips, lpips_min_side
from omg4.metrics.psnr import psnr, psnr_per_channel_mean
from omg4.metrics.ssim import ms_ssim, ssim, ssim_map
from omg4.metrics.timing import measure_fps, measure_fps_together

__all__ = ["psnr", "psnr_per_channel_mean", "ssim", "ssim_map", "ms_ssim", "LPIPS", "lpips", "lpips_min_side", "load_lpips_weights",
           "measure_fps", "measure_fps_together"]
