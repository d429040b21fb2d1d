"""FreeTimeGS Gaussians against independent float64 references (motion, temporal opacity, slice, gradients)."""

import math

import numpy as np
import pytest
import torch

from omg4.gaussians import GaussianConfig, Gaussians4D
from omg4.gaussians.freetime import opacity_regularizer, slice_geometry_ftgs

TIME_RANGE = (0.0, 2.0)


def ftgs_params(n: int, seed: int = 0, dtype=torch.float64) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)

    def r(*shape, scale=1.0):
        return (torch.randn(*shape, generator=g) * scale).to(dtype)

    return {"xyz": r(n, 3), "t": (torch.rand(n, 1, generator=g) * 2.0).to(dtype), "duration": r(n, 1, scale=0.3),
            "velocity": r(n, 3, scale=0.5), "scaling": r(n, 3, scale=0.3) - 1.5, "rotation": r(n, 4),
            "opacity": r(n, 1), "features_dc": r(n, 1, 3, scale=0.5), "features_rest": r(n, 15, 3, scale=0.2)}


def reference_slice(p: dict[str, torch.Tensor], tau: float, cull: float):
    """Per-Gaussian numpy loop: position, covariance, temporal opacity and the cull."""
    out = []
    for i in range(p["xyz"].shape[0]):
        mu_t = float(p["t"][i, 0])
        s = math.exp(float(p["duration"][i, 0]))
        p_t = math.exp(-0.5 * ((tau - mu_t) / s) ** 2)
        if p_t <= cull:
            continue
        mean = p["xyz"][i].numpy() + p["velocity"][i].numpy() * (tau - mu_t)
        w, x, y, z = p["rotation"][i].numpy() / np.linalg.norm(p["rotation"][i].numpy())
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        S = np.diag(np.exp(p["scaling"][i].numpy()))
        cov = R @ S @ S @ R.T
        opacity = 1.0 / (1.0 + math.exp(-float(p["opacity"][i, 0]))) * p_t
        out.append((i, mean, cov, p_t, opacity))
    return out


@pytest.mark.parametrize("tau", [0.1, 0.9, 1.7])
def test_slice_matches_the_float64_reference(tau):
    p = ftgs_params(40, seed=1)
    config = GaussianConfig(time_range=TIME_RANGE, sh_degree_t=0, backbone="freetimegs")
    model = Gaussians4D(p, config)
    sl = model.slice_at(tau, torch.tensor([0.0, 0.0, -4.0], dtype=torch.float64))
    ref = reference_slice(p, tau, config.time_cull)
    assert sl.index.tolist() == [r[0] for r in ref]
    assert len(ref) > 5  # the times leave several Gaussians visible, several culled
    np.testing.assert_allclose(sl.means.numpy(), np.stack([r[1] for r in ref]), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sl.covars.numpy(), np.stack([r[2] for r in ref]), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(sl.opacities.numpy(), [r[4] for r in ref], rtol=1e-12)


def test_several_views_in_one_pass_equal_one_view_each():
    p = ftgs_params(30, seed=2)
    geo = [slice_geometry_ftgs(p["xyz"], p["t"], p["duration"], p["velocity"], p["scaling"], p["rotation"], tau)
           for tau in (0.3, 1.2)]
    both = slice_geometry_ftgs(p["xyz"], p["t"], p["duration"], p["velocity"], p["scaling"], p["rotation"],
                               torch.tensor([0.3, 1.2], dtype=torch.float64))
    torch.testing.assert_close(both.means, torch.cat([g.means for g in geo]))
    torch.testing.assert_close(both.marginal, torch.cat([g.marginal for g in geo]))
    assert both.views.tolist() == [0] * len(geo[0].index) + [1] * len(geo[1].index)


def test_colours_are_3d_sh_seen_from_the_moved_position():
    p = ftgs_params(1, seed=3)
    p["t"][:] = 1.0
    p["duration"][:] = 2.0
    p["features_rest"][:] = 0.0
    p["features_rest"][0, 0] = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)  # degree-1, y-term
    config = GaussianConfig(time_range=TIME_RANGE, sh_degree_t=0, backbone="freetimegs")
    cam = torch.tensor([0.0, 0.0, -5.0], dtype=torch.float64)
    sl = Gaussians4D(p, config).slice_at(1.5, cam)
    d = sl.means[0] - cam
    d = d / d.norm()
    C0, C1 = 0.28209479177387814, 0.4886025119029199
    expected = (C0 * p["features_dc"][0, 0] - C1 * d[1] * p["features_rest"][0, 0] + 0.5).clamp_min(0)
    torch.testing.assert_close(sl.colors[0], expected)


def test_gradients_of_every_parameter_by_finite_differences():
    names = ["xyz", "t", "duration", "velocity", "scaling", "rotation", "opacity", "features_dc", "features_rest"]
    base = ftgs_params(3, seed=4)
    base["t"][:, 0] = torch.tensor([0.9, 1.0, 1.1], dtype=torch.float64)
    base["duration"][:] = 0.0
    config = GaussianConfig(time_range=TIME_RANGE, sh_degree_t=0, backbone="freetimegs")
    cam = torch.tensor([0.2, 0.1, -3.0], dtype=torch.float64)

    def f(*tensors):
        sl = Gaussians4D(dict(zip(names, tensors)), config).slice_at(1.0, cam)
        assert sl.index.numel() == 3
        return sl.means, sl.covars, sl.colors, sl.opacities

    inputs = tuple(base[k].clone().requires_grad_(True) for k in names)
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_regularizer_is_mean_opacity_times_detached_temporal_opacity():
    p = {k: v.requires_grad_(True) for k, v in ftgs_params(5, seed=5).items()}
    times = torch.tensor([0.5, 1.5], dtype=torch.float64)
    reg = opacity_regularizer(p["opacity"], p["t"], p["duration"], times)
    sigma = torch.sigmoid(p["opacity"][:, 0]).detach().tolist()
    mu, s = p["t"][:, 0].tolist(), p["duration"][:, 0].exp().tolist()
    expected = np.mean([[sigma[i] * math.exp(-0.5 * ((tau - mu[i]) / s[i]) ** 2) for i in range(5)]
                        for tau in times.tolist()])
    assert float(reg.detach()) == pytest.approx(expected, rel=1e-12)
    reg.backward()
    assert p["opacity"].grad is not None and bool((p["opacity"].grad != 0).all())
    assert p["t"].grad is None and p["duration"].grad is None  # the temporal opacity is detached


def test_the_backbone_requires_3d_sh():
    with pytest.raises(ValueError, match="sh_degree_t"):
        GaussianConfig(time_range=TIME_RANGE, backbone="freetimegs")
    with pytest.raises(ValueError, match="unknown backbone"):
        GaussianConfig(time_range=TIME_RANGE, backbone="4dgs")


def test_initial_model_spreads_repeated_points_over_the_clip_with_their_own_scale():
    g = torch.Generator().manual_seed(6)
    xyz = torch.randn(40, 3, generator=g)
    rgb = torch.rand(40, 3, generator=g)
    repeated = torch.cat([xyz, xyz, xyz])
    config = GaussianConfig(time_range=(1.0, 3.0), sh_degree_t=0, backbone="freetimegs")
    model = Gaussians4D.from_points(repeated, torch.cat([rgb, rgb, rgb]), config, generator=g)
    once = Gaussians4D.from_points(xyz, rgb, config, generator=torch.Generator().manual_seed(0))
    # a copy's scale comes from the distinct points around it, not from its own copies
    torch.testing.assert_close(model.params["scaling"], once.params["scaling"].repeat(3, 1))
    t = model.params["t"][:, 0]
    assert bool(((t >= 1.0) & (t <= 3.0)).all()) and float(t.std()) > 0.4
    assert torch.equal(model.params["velocity"], torch.zeros(120, 3))
    # three copies share the 2-s clip: duration min(√(D/5), D/(2·3)) = 1/3 s; one copy: √(2/5)
    torch.testing.assert_close(model.params["duration"], torch.full((120, 1), math.log(2.0 / 6.0)))
    torch.testing.assert_close(once.params["duration"], torch.full((40, 1), 0.5 * math.log(2.0 / 5.0)))
