"""``benchmarks/compositing_load.py``: the blended (pixel, Gaussian) pairs it counts equal a brute-force count
over every pixel and Gaussian, and its check against the renderer catches rules that differ."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from omg4.data.scene import Camera
from omg4.render.projection import project_gaussians
from omg4.render.view import TimeSlice, camera_tensors

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import compositing_load  # noqa: E402

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


def random_model(n: int, seed: int) -> StaticModel:
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([(torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([1.6, 1.0]),
                       1.0 + torch.rand(n, 1, generator=g, dtype=torch.float64)], dim=1)
    a = torch.randn(n, 3, 3, generator=g, dtype=torch.float64) * 0.05
    covars = a @ a.transpose(1, 2) + 1e-4 * torch.eye(3, dtype=torch.float64)
    return StaticModel(means, covars, 0.2 + 0.8 * torch.rand(n, generator=g, dtype=torch.float64))


def brute_force_blends(model: StaticModel, cam: Camera) -> np.ndarray:
    """Gaussians blended into each pixel: every visible Gaussian, front to back, gsplat's rules in float64."""
    viewmat, K, _ = camera_tensors(cam)
    sl = model.slice
    proj = project_gaussians(sl.means, sl.covars, viewmat.double(), K.double(), WIDTH, HEIGHT,
                             opacities=sl.opacities)
    visible = proj.visible.numpy()
    order = [i for i in np.argsort(proj.depths.numpy(), kind="stable") if visible[i]]
    m2d, conics, opac = proj.means2d.numpy(), proj.conics.numpy(), sl.opacities.numpy()
    counts = np.zeros((HEIGHT, WIDTH), np.int64)
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
                    break
                t *= 1 - alpha
                counts[py, px] += 1
    return counts


@pytest.mark.parametrize("seed", [0, 1])
def test_the_blends_counted_equal_a_brute_force_count(seed):
    model = random_model(40, seed)
    load = compositing_load.compositing_load(model, camera(), 0.0)
    expected = brute_force_blends(model, camera())
    assert expected.sum() > 10 * WIDTH  # a real workload: many Gaussians per pixel on average
    assert load["blended_per_pixel"] == pytest.approx(expected.sum() / (WIDTH * HEIGHT), rel=1e-12)
    assert load["visited_per_pixel"] > load["blended_per_pixel"]


def test_an_opaque_front_gaussian_ends_the_pixel():
    """Two opaque Gaussians centred on the image, one behind the other: at the centre pixel the first leaves a
    transmittance of 0.003 and the second (α 0.99) would take it below 1e-4, so one Gaussian is blended there;
    six pixels to the right the first has α 0.82 and both are blended."""
    means = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0]], dtype=torch.float64)
    covars = torch.eye(3, dtype=torch.float64).expand(2, 3, 3) * 0.1
    model = StaticModel(means, covars, torch.ones(2, dtype=torch.float64))
    counts = brute_force_blends(model, camera())
    assert counts[HEIGHT // 2, WIDTH // 2] == 1 and counts[HEIGHT // 2, WIDTH // 2 + 6] == 2
    load = compositing_load.compositing_load(model, camera(), 0.0)
    assert load["blended_per_pixel"] == pytest.approx(counts.mean(), rel=1e-12)


def test_a_count_under_other_rules_is_refused(monkeypatch):
    monkeypatch.setattr(compositing_load, "ALPHA_THRESHOLD", 0.05)
    with pytest.raises(RuntimeError, match="the rules differ"):
        compositing_load.compositing_load(random_model(40, 0), camera(), 0.0)
