"""A render-only model's frame on the fused CPU kernels (omg4.models.frame_arrays, omg4.gaussians.slice_kernels,
omg4.render.arrays) equals the same frame by the pure-torch reference (OMG4_KERNELS=reference): in float64 to
rounding, in float32 to float tolerance — both backbones, stored SH and appearance MLPs, one view and several, and the
edges (no Gaussian shown, one Gaussian, times outside the clip, tiny and huge time scales)."""

from __future__ import annotations

import pytest
import torch

from omg4.data.scene import Camera
from omg4.gaussians import GaussianConfig, Gaussians4D
from omg4.gaussians.appearance import AppearanceMLP
from omg4.gaussians.slice_kernels import EXPLICIT, MLP_CONDITIONED, MLP_POSITION_TERM
from omg4.kernels import using_kernels
from omg4.models.windowed import WindowedModel
from omg4.render.view import render_view, render_views

import numpy as np

TIME_RANGE = (0.0, 2.0)


def camera(x: float = 0.3, name: str = "cam") -> Camera:
    """A 64×48 pinhole camera at (x, 0.2, −4) looking at the origin along +z (OpenCV)."""
    viewmat = np.eye(4)
    viewmat[:3, 3] = [-x, -0.2, 4.0]
    K = np.array([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]])
    return Camera(name=name, viewmat=viewmat, K=K, width=64, height=48)


def model(backbone: str, mlp: bool, dtype: torch.dtype, n: int = 400, seed: int = 0, time_scale: float | None = None
          ) -> WindowedModel:
    """A random render-only model of ``backbone`` with stored SH or appearance MLPs, in ``dtype``."""
    g = torch.Generator().manual_seed(seed)
    config = GaussianConfig(time_range=TIME_RANGE, backbone=backbone, sh_degree_t=2 if backbone == "rt4dgs" else 0)
    xyz = torch.rand(n, 3, generator=g) * 2 - 1
    base = Gaussians4D.from_points(xyz, torch.rand(n, 3, generator=g), config, generator=g)
    values = {k: v.clone() for k, v in base.params.items()}
    for name in ("rotation", "rotation_r", "velocity"):
        if name in values:
            values[name] = values[name] + 0.3 * torch.randn(values[name].shape, generator=g)
    for name in ("scaling_t", "duration"):
        if name in values and time_scale is not None:
            values[name] = torch.full_like(values[name], float(np.log(time_scale)))
    values["features_rest"] = 0.2 * torch.randn(values["features_rest"].shape, generator=g)
    values["opacity"] = torch.randn(n, 1, generator=g)
    appearance = None
    if mlp:
        for name in ("opacity", "features_dc", "features_rest"):
            del values[name]
        values["f_static"], values["f_view"] = torch.randn(n, 3, generator=g), torch.randn(n, 3, generator=g)
        torch.manual_seed(seed)
        appearance = AppearanceMLP(num_inputs=config.schema.mlp_inputs).eval().to(dtype)
    values = {k: v.to(dtype) for k, v in values.items()}
    return WindowedModel(values, config, 3, config.sh_degree_t, appearance=appearance, windows=8)


CASES = [("rt4dgs", False, EXPLICIT), ("rt4dgs", True, MLP_POSITION_TERM), ("freetimegs", False, EXPLICIT),
         ("freetimegs", True, MLP_CONDITIONED)]


def both(fn):
    """``fn()`` with the fused kernels and with the reference."""
    fused = fn()
    with using_kernels("reference"):
        reference = fn()
    return fused, reference


def assert_same_frame(fused, reference, tol: float):
    (ra, sa), (rb, sb) = fused, reference
    assert torch.equal(sa.index, sb.index), "the fused cull keeps other Gaussians"
    for name in ("means", "covars", "colors", "opacities"):
        torch.testing.assert_close(getattr(sa, name), getattr(sb, name), rtol=tol, atol=tol, msg=name)
    for name in ("image", "alpha", "depth"):
        torch.testing.assert_close(getattr(ra, name), getattr(rb, name), rtol=tol, atol=tol, msg=name)
    torch.testing.assert_close(ra.radii, rb.radii)


@pytest.mark.parametrize("backbone, mlp, mode", CASES)
def test_a_float64_frame_is_the_references_to_rounding(backbone, mlp, mode):
    m = model(backbone, mlp, torch.float64)
    assert m.frame_kernel is not None and m.frame_kernel.mode == mode
    for tau in (0.0, 0.37, 1.5, 2.0):
        fused, reference = both(lambda: render_view(m, camera(), tau, backend="cpu"))
        assert fused[1].index.numel() > 20  # the frame shows something
        assert_same_frame(fused, reference, 1e-9)


@pytest.mark.parametrize("backbone, mlp, mode", CASES)
def test_a_float32_frame_is_the_references_to_float_tolerance(backbone, mlp, mode):
    """FreeTimeGS's MLPs encode the moved position at 2^15·π·x: in float32 those phases are ~1e5 rad, where two
    libraries' sines of the same float differ by up to 1e-2 (measured: 7.5e-3 at the top band, below 1e-6 in the
    lower half), so its colours agree to 2e-3; every other frame to 2e-5."""
    m = model(backbone, mlp, torch.float32, seed=1)
    fused, reference = both(lambda: render_view(m, camera(), 0.8, backend="cpu"))
    assert_same_frame(fused, reference, 2e-3 if mode == MLP_CONDITIONED else 2e-5)


@pytest.mark.parametrize("backbone, mlp, mode", CASES)
def test_several_views_at_their_times_are_the_references(backbone, mlp, mode):
    m = model(backbone, mlp, torch.float64, seed=2)
    cams, times = [camera(0.3, "a"), camera(-0.5, "b"), camera(0.0, "c")], [0.1, 1.2, 1.9]
    fused, reference = both(lambda: render_views(m, cams, times, backend="cpu"))
    assert fused[0].image.shape == (3, 48, 64, 3)
    assert torch.equal(fused[1].views, reference[1].views)
    assert_same_frame(fused, reference, 1e-9)


@pytest.mark.parametrize("time_scale, tau", [(1e-4, 1.234567), (1e4, 0.5), (1e4, 7.0), (0.3, -5.0), (0.3, -0.2),
                                             (0.3, 2.2)])
def test_the_edges_of_time(time_scale, tau):
    """Time scales tiny (almost nothing shown) and huge (everything, for ever), times far outside the clip."""
    for backbone in ("rt4dgs", "freetimegs"):
        m = model(backbone, True, torch.float64, seed=3, time_scale=time_scale)
        fused, reference = both(lambda: render_view(m, camera(), tau, backend="cpu"))
        assert_same_frame(fused, reference, 1e-9)


def test_a_frame_that_shows_nothing_is_the_background():
    m = model("rt4dgs", True, torch.float32, seed=4, time_scale=1e-3)
    background = torch.tensor([0.2, 0.4, 0.6])
    (rendered, sl), reference = both(lambda: render_view(m, camera(), 50.0, background=background, backend="cpu"))
    assert sl.index.numel() == 0 and reference[1].index.numel() == 0
    assert torch.equal(rendered.image, background.expand(48, 64, 3))


def test_one_gaussian():
    m = model("freetimegs", False, torch.float64, n=1, seed=5, time_scale=10.0)
    fused, reference = both(lambda: render_view(m, camera(), 1.0, backend="cpu"))
    assert fused[1].index.tolist() == [0]
    assert_same_frame(fused, reference, 1e-9)


def test_the_reference_switch_turns_the_fused_frame_off(monkeypatch):
    m = model("rt4dgs", False, torch.float32)
    calls = {"fused": 0, "torch": 0}
    fused_frame, torch_slice = type(m.frame_kernel).frame, type(m).slice_views

    def counted(name, fn):
        def wrapper(*args, **kwargs):
            calls[name] += 1
            return fn(*args, **kwargs)
        return wrapper

    monkeypatch.setattr(type(m.frame_kernel), "frame", counted("fused", fused_frame))
    monkeypatch.setattr(type(m), "slice_views", counted("torch", torch_slice))
    render_view(m, camera(), 0.5, backend="cpu")
    assert calls == {"fused": 1, "torch": 0}  # the default frame: the fused kernels, no torch slice
    with using_kernels("reference"):
        render_view(m, camera(), 0.5, backend="cpu")
    assert calls == {"fused": 1, "torch": 1}  # the reference frame: the torch slice, the fused kernels untouched
    render_view(m, camera(), 0.5, backend="cpu")
    assert calls == {"fused": 2, "torch": 1}  # the switch is undone on leaving
    with pytest.raises(ValueError, match="unknown kernels"):
        with using_kernels("fast"):
            pass


def test_the_active_sh_degrees_are_read_per_frame():
    m = model("rt4dgs", False, torch.float64, seed=6)
    m.active_sh_degree, m.active_sh_degree_t = 1, 0
    fused, reference = both(lambda: render_view(m, camera(), 0.9, backend="cpu"))
    assert_same_frame(fused, reference, 1e-9)


def test_a_camera_with_nan_is_refused_as_the_reference_refuses_it():
    from omg4.errors import OMG4Error

    m = model("rt4dgs", True, torch.float32, seed=7)
    bad = camera()
    bad.K[0, 0] = float("nan")
    for mode in ("fused", "reference"):
        with using_kernels(mode), pytest.raises(OMG4Error, match="contains NaN or infinite values"):
            render_view(m, bad, 0.5, backend="cpu")
