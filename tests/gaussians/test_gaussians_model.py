"""Gaussians4D: initialization, slice_at against a float64 oracle, culling, gradients (rt4dgs §1–3.5)."""

import math

import numpy as np
import pytest
import torch

from omg4.gaussians import GaussianConfig, Gaussians4D, sh_to_rgb
from omg4.gaussians.backbone import RT4DGS
from test_covariance4d import oracle_condition
from test_rotation4d import oracle_rotation_4d
from test_sh4d import real_sh_scipy


def random_params(n, seed=0, t_range=(0.0, 10.0), dtype=torch.float64):
    g = np.random.default_rng(seed)
    raw = {
        "xyz": g.normal(size=(n, 3)),
        "t": g.uniform(*t_range, size=(n, 1)),
        "scaling": g.normal(size=(n, 3)) * 0.3 - 1.0,
        "scaling_t": g.normal(size=(n, 1)) * 0.3 + 0.3,
        "rotation": g.normal(size=(n, 4)),
        "rotation_r": g.normal(size=(n, 4)),
        "opacity": g.normal(size=(n, 1)),
        "features_dc": g.normal(size=(n, 1, 3)) + 1.0,
        "features_rest": g.normal(size=(n, 47, 3)) * 0.2,
    }
    return {k: torch.tensor(v, dtype=dtype) for k, v in raw.items()}


def oracle_slice(params, cfg, tau, cam, degree, degree_t):
    """Independent float64 slice: quaternion-product rotation, precision-form conditioning, scipy SH."""
    p = {k: v.detach().double().numpy() for k, v in params.items()}
    scales = np.exp(np.concatenate([p["scaling"], p["scaling_t"]], 1))
    R = oracle_rotation_4d(p["rotation"], p["rotation_r"], cfg.rotation_convention)
    cov4 = R @ (scales[:, :, None] ** 2 * np.swapaxes(R, 1, 2))
    mean3, cov3, p_t = oracle_condition(p["xyz"], p["t"], cov4, tau)
    keep = np.nonzero(p_t > cfg.time_cull)[0]
    origin = mean3 if cfg.sh_direction == "conditioned" else p["xyz"]
    d = origin[keep] - np.asarray(cam, dtype=np.float64)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    Y = real_sh_scipy(d, degree)
    coeffs = np.concatenate([p["features_dc"], p["features_rest"]], 1)[keep]
    dt = p["t"][keep, 0] - tau
    nb = Y.shape[1]
    rgb = sum(np.cos(2 * np.pi * b * dt / cfg.period)[:, None] * np.einsum("nk,nkc->nc", Y, coeffs[:, 16 * b:16 * b + nb])
              for b in range(degree_t + 1))
    opac = 1 / (1 + np.exp(-p["opacity"][keep, 0])) * p_t[keep]
    return keep, mean3[keep], cov3[keep], np.maximum(rgb + 0.5, 0), opac


@pytest.mark.parametrize("convention", ["flip", "legacy"])
@pytest.mark.parametrize("sh_direction", ["conditioned", "canonical"])
@pytest.mark.parametrize("degrees", [(3, 2), (1, 0), (3, 1)])
def test_slice_at_matches_float64_oracle(convention, sh_direction, degrees):
    cfg = GaussianConfig(time_range=(0.0, 10.0), rotation_convention=convention, sh_direction=sh_direction)
    params = random_params(300, seed=1)
    model = Gaussians4D(params, cfg, *degrees)
    cam = torch.tensor([0.3, -4.0, 1.0], dtype=torch.float64)
    sl = model.slice_at(6.5, cam)
    keep, mean3, cov3, rgb, opac = oracle_slice(params, cfg, 6.5, cam.numpy(), *degrees)
    assert 0 < len(keep) < 300 and sl.num_total == 300
    np.testing.assert_array_equal(sl.index.numpy(), keep)
    np.testing.assert_allclose(sl.means.numpy(), mean3, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(sl.covars.numpy(), cov3, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(sl.colors.numpy(), rgb, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(sl.opacities.numpy(), opac, rtol=1e-11)


def test_slice_at_float32_close_to_oracle():
    cfg = GaussianConfig(time_range=(0.0, 1.0))
    params = random_params(200, seed=2, t_range=(0.0, 1.0), dtype=torch.float32)
    params["scaling_t"] -= 1.5
    sl = Gaussians4D(params, cfg).slice_at(0.4, torch.tensor([0.0, 0.0, -4.0]))
    keep, mean3, cov3, rgb, opac = oracle_slice(params, cfg, 0.4, [0.0, 0.0, -4.0], 3, 2)
    np.testing.assert_array_equal(sl.index.numpy(), keep)
    np.testing.assert_allclose(sl.means.numpy(), mean3, atol=1e-5)
    np.testing.assert_allclose(sl.colors.numpy(), rgb, atol=1e-5)
    np.testing.assert_allclose(sl.opacities.numpy(), opac, atol=1e-6)
    assert sl.means.dtype == torch.float32


def test_cull_threshold_and_empty_slice():
    cfg = GaussianConfig(time_range=(0.0, 10.0), time_cull=0.05)
    params = random_params(4, seed=3)
    params["rotation"] = params["rotation_r"] = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).repeat(4, 1)
    params["scaling_t"][:] = 0.0  # σ_t = 1: visible while |dt| < sqrt(2 ln 20)
    params["t"][:, 0] = torch.tensor([1.0, 2.0, 5.0, 9.0], dtype=torch.float64)
    model = Gaussians4D(params, cfg)
    edge = math.sqrt(2 * math.log(20.0))
    assert model.slice_at(2.0 + edge * 0.99, torch.zeros(3)).index.tolist() == [1, 2]
    assert model.slice_at(1.0 - edge * 1.01, torch.zeros(3)).index.tolist() == []
    empty = model.slice_at(-100.0, torch.zeros(3))
    assert empty.means.shape == (0, 3) and empty.covars.shape == (0, 3, 3) and empty.colors.shape == (0, 3)
    cfg_strict = GaussianConfig(time_range=(0.0, 10.0), time_cull=0.9)
    assert Gaussians4D(params, cfg_strict).slice_at(2.3, torch.zeros(3)).index.tolist() == [1]


def test_gradcheck_every_parameter():
    cfg = GaussianConfig(time_range=(0.0, 2.0))
    base = random_params(3, seed=4, t_range=(0.8, 1.2))
    names = list(RT4DGS.param_names)
    cam = torch.tensor([0.2, 0.1, -3.0], dtype=torch.float64)

    def f(*tensors):
        sl = Gaussians4D(dict(zip(names, tensors)), cfg, 3, 2).slice_at(1.0, cam)
        assert sl.index.numel() == 3
        return sl.means, sl.covars, sl.colors, sl.opacities

    inputs = tuple(base[k].clone().requires_grad_(True) for k in names)
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_every_parameter_receives_gradient():
    cfg = GaussianConfig(time_range=(0.0, 2.0))
    params = {k: v.requires_grad_(True) for k, v in random_params(5, seed=5, t_range=(0.5, 1.5)).items()}
    sl = Gaussians4D(params, cfg, 3, 2).slice_at(1.1, torch.tensor([0.0, 0.0, -3.0]))
    (sl.means.sum() + sl.covars.sum() + sl.colors.sum() + sl.opacities.sum()).backward()
    for k, v in params.items():
        assert v.grad is not None and v.grad.abs().sum() > 0, k


def brute_force_knn_sq(xyz, k=3):
    d2 = ((xyz[:, None, :] - xyz[None, :, :]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    return np.sort(d2, axis=1)[:, :k].mean(1)


def test_from_points_initialization():
    g = np.random.default_rng(6)
    xyz = g.normal(size=(500, 3)).astype(np.float32)
    xyz[1] = xyz[0]  # duplicates: clamped distance
    xyz[2] = xyz[0]
    xyz[3] = xyz[0]
    rgb = g.uniform(size=(500, 3)).astype(np.float32)
    cfg = GaussianConfig(time_range=(2.0, 12.0))
    m = Gaussians4D.from_points(torch.from_numpy(xyz), torch.from_numpy(rgb), cfg,
                                generator=torch.Generator().manual_seed(0))
    p = m.params
    assert m.num_gaussians == 500 and (m.active_sh_degree, m.active_sh_degree_t) == (0, 0)
    assert torch.equal(p["xyz"], torch.from_numpy(xyz))
    t = p["t"][:, 0].numpy()
    assert t.min() >= 1.0 and t.max() <= 13.0 and t.min() < 1.2 and t.max() > 12.8
    ref = 0.5 * np.log(np.maximum(brute_force_knn_sq(xyz.astype(np.float64)), 1e-7))
    np.testing.assert_allclose(p["scaling"].numpy(), np.repeat(ref[:, None], 3, 1), rtol=1e-5, atol=1e-6)
    assert p["scaling"][0, 0].item() == pytest.approx(0.5 * math.log(1e-7), rel=1e-6)
    np.testing.assert_allclose(p["scaling_t"].numpy(), 0.5 * math.log(10.0 / 5.0), rtol=1e-6)
    assert torch.equal(p["rotation"], torch.tensor([[1.0, 0, 0, 0]]).repeat(500, 1))
    assert torch.equal(p["rotation_r"], p["rotation"])
    np.testing.assert_allclose(torch.sigmoid(p["opacity"]).numpy(), 0.1, rtol=1e-6)
    np.testing.assert_allclose(sh_to_rgb(p["features_dc"][:, 0]).numpy(), rgb, atol=1e-6)
    assert p["features_rest"].shape == (500, 47, 3) and not p["features_rest"].any()
    again = Gaussians4D.from_points(torch.from_numpy(xyz), torch.from_numpy(rgb), cfg,
                                    generator=torch.Generator().manual_seed(0))
    assert torch.equal(again.params["t"], p["t"])


def test_from_points_bad_input():
    from omg4.errors import DataError

    cfg = GaussianConfig(time_range=(0.0, 1.0))
    with pytest.raises(DataError, match="empty"):
        Gaussians4D.from_points(torch.zeros(0, 3), torch.zeros(0, 3), cfg)
    with pytest.raises(DataError, match="NaN"):
        Gaussians4D.from_points(torch.tensor([[0.0, float("nan"), 0.0]]), torch.zeros(1, 3), cfg)
    single = Gaussians4D.from_points(torch.zeros(1, 3), torch.zeros(1, 3), cfg)
    assert single.params["scaling"][0, 0].item() == pytest.approx(0.5 * math.log(1e-7), rel=1e-6)


def test_activations_and_detach_copy():
    cfg = GaussianConfig(time_range=(0.0, 10.0))
    params = random_params(10, seed=7)
    m = Gaussians4D(params, cfg, 2, 1)
    torch.testing.assert_close(m.opacity(), torch.sigmoid(params["opacity"][:, 0]))
    torch.testing.assert_close(m.scales(), torch.cat([params["scaling"], params["scaling_t"]], 1).exp())
    c = m.detach_copy()
    c.params["xyz"] += 1.0
    assert not torch.equal(c.params["xyz"], m.params["xyz"])
    assert (c.active_sh_degree, c.active_sh_degree_t, c.config) == (2, 1, cfg)


def test_constructor_validates_shapes_and_degrees():
    cfg = GaussianConfig(time_range=(0.0, 10.0))
    params = random_params(3)
    params["features_rest"] = params["features_rest"][:, :15]
    with pytest.raises(ValueError, match="features_rest"):
        Gaussians4D(params, cfg)
    with pytest.raises(ValueError, match="exceed"):
        Gaussians4D(random_params(3), cfg, 4, 0)
    with pytest.raises(ValueError, match="time_range"):
        GaussianConfig(time_range=(1.0, 1.0))


def test_moving_a_model_keeps_leaf_parameters():
    """A model moved to another device (here "meta") holds leaves whose flags can still be changed
    (the SD score toggles requires_grad; a plain .to() of a grad-requiring leaf is a non-leaf)."""
    model = Gaussians4D({k: v.requires_grad_(True) for k, v in random_params(5, dtype=torch.float32).items()},
                        GaussianConfig(time_range=(0.0, 10.0)))
    moved = model.to("meta")
    for name, p in moved.params.items():
        assert p.device.type == "meta" and p.is_leaf and p.requires_grad, name
        p.requires_grad_(False)
    same = model.to("cpu")
    assert all(same.params[k] is model.params[k] for k in model.params)


@pytest.mark.parametrize("degrees", [(4, 0), (3, 3), (-1, 0), (3, -1)])
def test_sh_degrees_outside_their_ranges_are_refused(degrees):
    """Spatial SH degree in 0..3 and temporal in 0..2, each on its own."""
    with pytest.raises(ValueError, match="SH degrees"):
        GaussianConfig(time_range=(0.0, 1.0), sh_degree=degrees[0], sh_degree_t=degrees[1])


def test_centre_colour_is_the_dc_summed_over_the_temporal_bands():
    """At Δt = 0 every temporal cosine is 1 and the view average keeps the DC: colour = C0·Σ_n DC_n + 0.5 over the
    active temporal bands n (band n's DC is coefficient 16·n), clamped to [0, 1]."""
    from omg4.gaussians.model import centre_appearance

    cfg = GaussianConfig(time_range=(0.0, 10.0))
    params = {k: v.float() for k, v in random_params(5).items()}
    coeffs = torch.cat([params["features_dc"], params["features_rest"]], dim=1).double()
    for degree_t in (0, 1, 2):
        rgb, opacity = centre_appearance(params, cfg, degree_t)
        dc = sum(coeffs[:, 16 * n] for n in range(degree_t + 1))
        torch.testing.assert_close(rgb.double(), (0.28209479177387814 * dc + 0.5).clamp(0, 1), rtol=0, atol=1e-5)
        torch.testing.assert_close(opacity, torch.sigmoid(params["opacity"][:, 0]))
