"""Differentiable Gaussian rasterization (:func:`rasterize`) and per-view rendering of models.

``rasterize`` renders 3D Gaussians with a numba CPU backend or gsplat on CUDA;
``render_view`` renders a model's time slice at a camera (:mod:`omg4.render.view`).
"""

from omg4.render.api import Rendered, rasterize
from omg4.render.view import TimeSlice, render_view

__all__ = ["Rendered", "TimeSlice", "rasterize", "render_view"]
