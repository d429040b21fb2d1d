"""``omg4.render.compositing_load``: the blended (pixel, Gaussian) pairs it counts equal a brute-force count
over every pixel and Gaussian, and its check against the renderer catches rules that differ."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from omg4.data.scene import Camera
from omg4.render import compositing_load
from omg4.render.api import project_and_bin
from omg4.render.projection import project_gaussians
from omg4.render.view import TimeSlice, camera_tensors

WIDTH, HEIGHT = 40, 24


class StaticModel:
    """Fixed 3D Gaussians shown at every time (the ``slice_at`` a renderer calls)."""

    def __init__(self, means, covars, opacities):
        self.slice = TimeSlice(means=means, covars=covars, colors=torch.rand(len(means), 3, dtype=means.dtype),
                               opacities=opacities, index=torch.arange(len(means)), num_total=len(means))

    def slice_at(self, timestamp, camera_center):
        return self.slice


def camera() -> Camera:
    K = np.array([[30.0, 0, WIDTH / 2], [0, 30.0, HEIGHT / 2], [0, 0, 1]])
    return Camera(K=K, viewmat=np.eye(4), width=WIDTH, height=HEIGHT, name="cam")


def random_model(n: int, seed: int, dtype: torch.dtype = torch.float64) -> StaticModel:
    """``n`` Gaussians in front of :func:`camera`, dense and opaque enough that many pixels saturate."""
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([(torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([1.6, 1.0]),
                       1.0 + torch.rand(n, 1, generator=g, dtype=torch.float64)], dim=1)
    a = torch.randn(n, 3, 3, generator=g, dtype=torch.float64) * 0.12
    covars = a @ a.transpose(1, 2) + 1e-4 * torch.eye(3, dtype=torch.float64)
    opacities = 0.5 + 0.5 * torch.rand(n, generator=g, dtype=torch.float64)
    return StaticModel(means.to(dtype), covars.to(dtype), opacities.to(dtype))


def brute_force_blends(model: StaticModel, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Gaussians blended into each pixel and whether the pixel stopped early: every visible Gaussian, front to
    back, gsplat's rules in float64."""
    viewmat, K, _ = camera_tensors(cam)
    sl = model.slice
    proj = project_gaussians(sl.means.double(), sl.covars.double(), viewmat.double(), K.double(), WIDTH, HEIGHT,
                             opacities=sl.opacities.double())
    visible = proj.visible.numpy()
    order = [i for i in np.argsort(proj.depths.numpy(), kind="stable") if visible[i]]
    m2d, conics, opac = proj.means2d.numpy(), proj.conics.numpy(), sl.opacities.double().numpy()
    counts = np.zeros((HEIGHT, WIDTH), np.int64)
    stopped = np.zeros((HEIGHT, WIDTH), bool)
    for py in range(HEIGHT):
        for px in range(WIDTH):
            t = 1.0
            for i in order:
                dx, dy = m2d[i, 0] - (px + 0.5), m2d[i, 1] - (py + 0.5)
                a, b, c = conics[i]
                sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                if sigma < 0:
                    continue
                alpha = min(0.999, opac[i] * math.exp(-sigma))
                if alpha < 1 / 255:
                    continue
                if t * (1 - alpha) <= 1e-4:
                    stopped[py, px] = True
                    break
                t *= 1 - alpha
                counts[py, px] += 1
    return counts, stopped


@pytest.mark.parametrize("seed", [0, 1])
def test_the_blends_counted_equal_a_brute_force_count(seed):
    model = random_model(120, seed)
    load = compositing_load.compositing_load(model, camera(), 0.0)
    expected, stopped = brute_force_blends(model, camera())
    assert expected.mean() > 5 and stopped.mean() > 0.2  # a real workload: layers blended, many pixels saturate
    assert load["blended_per_pixel"] == pytest.approx(expected.mean(), rel=1e-12)
    assert load["visited_per_pixel"] > load["blended_per_pixel"]


def test_a_float32_model_is_counted_in_its_precision():
    """float32 rounding may decide a Gaussian at a threshold apart from the float64 reference: a few pairs."""
    model = random_model(120, 2, torch.float32)
    load = compositing_load.compositing_load(model, camera(), 0.0)
    expected, _ = brute_force_blends(model, camera())
    assert abs(load["blended_per_pixel"] - expected.mean()) * WIDTH * HEIGHT <= 2


def test_the_alpha_clamp_and_a_stopped_pixel_decide_the_count():
    """Four Gaussians centred on the image, front to back: an opaque one whose α is clamped to 0.999 at the centre
    pixel (unclamped it would leave 2.8·10⁻⁴, not 10⁻³), one of opacity 0.8 (leaving 2.0·10⁻⁴ > 10⁻⁴, so it is
    blended — unclamped it would stop the pixel), an opaque one that stops the pixel, and a faint one behind it
    that a pixel still compositing would blend: 2 at the centre."""
    means = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0], [0.0, 0.0, 3.0], [0.0, 0.0, 4.0]], dtype=torch.float64)
    covars = torch.eye(3, dtype=torch.float64).expand(4, 3, 3).clone()
    model = StaticModel(means, covars, torch.tensor([1.0, 0.8, 1.0, 0.1], dtype=torch.float64))
    counts, _ = brute_force_blends(model, camera())
    assert counts[HEIGHT // 2, WIDTH // 2] == 2
    load = compositing_load.compositing_load(model, camera(), 0.0)
    assert load["blended_per_pixel"] == pytest.approx(counts.mean(), rel=1e-12)


def test_each_box_pixel_is_visited_once():
    """One Gaussian spanning several tiles: the pixels visited are its pixel box clipped to the image, once each."""
    means = torch.tensor([[0.05, 0.02, 1.0]], dtype=torch.float64)
    model = StaticModel(means, torch.eye(3, dtype=torch.float64)[None] * 0.01, torch.tensor([0.9], dtype=torch.float64))
    viewmat, K, _ = camera_tensors(camera())
    _, _, _, boxes = project_and_bin(means, model.slice.covars, model.slice.opacities, None, viewmat[None], K[None],
                                     WIDTH, HEIGHT, near=0.2, far=1e10, eps2d=0.3, tile_size=16)
    x0, x1, y0, y1 = (int(v) for v in boxes[0])
    assert 16 < x1 - x0 < WIDTH and 8 < y1 - y0 < HEIGHT  # more than one tile, inside the image
    load = compositing_load.compositing_load(model, camera(), 0.0)
    assert load["visited_per_pixel"] * WIDTH * HEIGHT == pytest.approx((x1 - x0) * (y1 - y0), rel=1e-12)


def test_a_count_under_other_rules_is_refused(monkeypatch):
    monkeypatch.setattr(compositing_load, "ALPHA_THRESHOLD", 0.05)
    with pytest.raises(RuntimeError, match="the rules differ"):
        compositing_load.compositing_load(random_model(120, 0), camera(), 0.0)
