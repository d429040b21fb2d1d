"""What a segment of a long capture learns where it shares frames with the one before: the crossfade of that
segment's renders into the video (beyond the paper: neighbours agree where playback blends them). Training
(:mod:`omg4.train.segmented`) and compression (:func:`omg4.compress.api.compress_segments`) both fit it."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from omg4.data.scene import Scene
from omg4.data.segments import crossfade_weight
from omg4.device import resolve_device
from omg4.render.view import render_view


def taught_by(scene: Scene, teacher, frames: tuple[int, int], *,
              background: tuple[float, float, float] = (0.0, 0.0, 0.0), backend: str = "auto",
              device: str | torch.device = "cpu") -> Scene:
    """``scene`` whose training views of the frames ``[start, stop)`` it shares with the segment before show the
    crossfade of ``teacher``'s render (that segment's, on ``background``, rendered once, when first asked for) into
    the video, at the weights playback blends the two segments with (:func:`~omg4.data.segments.crossfade_weight`):
    the segment learns to agree with the one before where playback shows mostly that one, and the video where it
    shows mostly itself, so the blend moves from one to the other without a jump. Test views keep the video."""
    device = resolve_device(device)
    background = torch.tensor(background, dtype=torch.float32, device=device)
    start, stop = frames

    def target(view):
        cache = {}
        weight = crossfade_weight(view.frame_index, start, stop)

        def image():
            if "image" not in cache:
                with torch.no_grad():
                    rendered = render_view(teacher, view.camera, view.timestamp, background=background,
                                           backend=backend, device=device)[0]
                taught = rendered.image.clamp(0.0, 1.0).cpu().numpy()
                cache["image"] = ((1.0 - weight) * taught + weight * view.image()).astype(np.float32)
            return cache["image"]
        return image

    train = [dataclasses.replace(v, loader=target(v)) if start <= v.frame_index < stop else v
             for v in scene.train_views]
    return dataclasses.replace(scene, train_views=train)


__all__ = ["taught_by"]
