"""What a rasterization returns (:class:`Rendered`) and the backends that produce it (:data:`BACKENDS`).

Its own module so that the CPU entry points (:mod:`omg4.render.api`) and the gsplat backend
(:mod:`omg4.render.gsplat_backend`) both import it without importing each other, and the
command line can offer the backends without importing numba.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

BACKENDS = ("auto", "cpu", "gsplat")


@dataclass
class Rendered:
    """One rendered view, or several (leading ``V`` axis on the images) from :func:`rasterize_views`.

    Attributes:
        image: [H, W, C] (or [V, H, W, C]) composited colours over the background.
        alpha: [H, W, 1] (or [V, H, W, 1]) accumulated opacity ``1 − T_final``.
        depth: [H, W, 1] (or [V, H, W, 1]) alpha-weighted view depth ``Σ z·α·T`` (not normalized by alpha).
        means2d: [N, 2] projected means in pixels (of each row's view); after ``backward()`` its
            ``.grad`` is ∂loss/∂means2d (the OMG4 SD score and densification read it).
        radii: [N] int32 box radius in pixels, 0 = not rendered.
    """

    image: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    means2d: torch.Tensor
    radii: torch.Tensor


__all__ = ["BACKENDS", "Rendered"]
