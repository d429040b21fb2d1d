"""4D covariance, conditioning on time and the temporal cull (rt4dgs §1.3–1.4).

Oracles: the 4D covariance from the quaternion-product rotation, the conditional from the
precision matrix (inverse of Σ4) instead of the Schur complement, and a Monte-Carlo
conditioning of samples of the 4D Gaussian.
"""

import math

import numpy as np
import pytest
import torch

from omg4.gaussians import condition_on_time, covariance, covariance_4d, slice_geometry
from test_rotation4d import oracle_rotation_4d


def random_gaussians(n, seed=0):
    g = np.random.default_rng(seed)
    return dict(xyz=g.normal(size=(n, 3)), t=g.uniform(0, 10, size=(n, 1)), scales=np.exp(g.normal(size=(n, 4)) * 0.5),
                ql=g.normal(size=(n, 4)), qr=g.normal(size=(n, 4)))


def oracle_cov4(p, convention):
    R = oracle_rotation_4d(p["ql"], p["qr"], convention)
    return R @ (p["scales"][:, :, None] ** 2 * np.swapaxes(R, 1, 2))


def oracle_condition(xyz, t, cov4, tau):
    """Conditional of a Gaussian via the precision matrix Λ = Σ4⁻¹: Σ_x|t = Λxx⁻¹, μ = μx − Λxx⁻¹ Λxt (τ − μt)."""
    lam = np.linalg.inv(cov4)
    cov3 = np.linalg.inv(lam[:, :3, :3])
    dt = tau - t[:, 0]
    mean3 = xyz - np.einsum("nij,nj->ni", cov3, lam[:, :3, 3]) * dt[:, None]
    p_t = np.exp(-0.5 * dt**2 / cov4[:, 3, 3])
    return mean3, cov3, p_t


def T(a):
    return torch.from_numpy(np.ascontiguousarray(a))


@pytest.mark.parametrize("convention", ["flip", "legacy"])
def test_covariance_4d_matches_oracle(convention):
    p = random_gaussians(50)
    cov = covariance_4d(T(p["scales"]), T(p["ql"]), T(p["qr"]), convention).numpy()
    np.testing.assert_allclose(cov, oracle_cov4(p, convention), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.linalg.eigvalsh(cov), np.sort(p["scales"] ** 2, axis=1), rtol=1e-9)


@pytest.mark.parametrize("tau", [0.0, 3.3, 10.0])
def test_condition_on_time_matches_precision_form(tau):
    p = random_gaussians(50, seed=2)
    cov4 = oracle_cov4(p, "flip")
    mean3, cov3, p_t = condition_on_time(T(p["xyz"]), T(p["t"]), T(cov4), tau)
    m_ref, c_ref, p_ref = oracle_condition(p["xyz"], p["t"], cov4, tau)
    np.testing.assert_allclose(mean3.numpy(), m_ref, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(cov3.numpy(), c_ref, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(p_t.numpy(), p_ref, rtol=1e-12)


def test_conditioning_matches_monte_carlo_samples():
    """Sample the 4D Gaussian, keep samples with |t − τ| < h, and compare their statistics."""
    cov4 = np.array([[1.0, 0.3, -0.2, 0.6], [0.3, 0.8, 0.1, -0.4], [-0.2, 0.1, 0.5, 0.2], [0.6, -0.4, 0.2, 1.5]])
    mu = np.array([0.5, -1.0, 2.0, 4.0])
    tau, h, n = 4.9, 0.03, 2_000_000
    rng = np.random.default_rng(7)
    x = rng.multivariate_normal(mu, cov4, size=n)
    sel = x[np.abs(x[:, 3] - tau) < h, :3]
    mean3, cov3, p_t = condition_on_time(T(mu[None, :3]), T(mu[None, 3:]), T(cov4[None]), tau)
    cov3 = cov3[0].numpy()
    # mean: 6 standard errors of the sample mean
    se = np.sqrt(np.diag(cov3) / len(sel))
    assert np.all(np.abs(sel.mean(0) - mean3[0].numpy()) < 6 * se + 1e-3)
    # covariance: relative error of a sample covariance with ~100k samples is ~0.5 %
    np.testing.assert_allclose(np.cov(sel.T), cov3, atol=0.02 * np.abs(cov3).max())
    # the temporal marginal is the unnormalized density: p_t / sqrt(2π Σtt) ≈ fraction / (2h)
    density = len(sel) / n / (2 * h)
    assert density == pytest.approx(float(p_t[0]) / math.sqrt(2 * math.pi * cov4[3, 3]), rel=0.02)


def test_slice_geometry_culls_where_marginal_at_most_threshold():
    """Identity rotations: Σtt = s_t²; the cull edge is |dt| = sqrt(2 ln 20) σ_t (rt4dgs §1.4)."""
    s_t = np.array([0.5, 1.0, 2.0, 0.3, 1.0])
    edge = math.sqrt(2 * math.log(20.0)) * s_t
    dt = edge * np.array([0.999, 1.001, -0.999, -1.001, 0.0])
    tau = 5.0
    n = len(s_t)
    q = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).repeat(n, 1)
    scales = torch.ones(n, 4, dtype=torch.float64)
    scales[:, 3] = T(s_t)
    geom = slice_geometry(torch.zeros(n, 3, dtype=torch.float64), T(tau - dt[:, None]), scales, q, q, tau)
    assert geom.index.tolist() == [0, 2, 4]
    assert geom.index.dtype == torch.int64
    assert torch.all(geom.marginal > 0.05)
    np.testing.assert_allclose(geom.marginal.numpy(), np.exp(-0.5 * (dt[[0, 2, 4]] / s_t[[0, 2, 4]]) ** 2))
    np.testing.assert_allclose(geom.dt.numpy(), -dt[[0, 2, 4]])


@pytest.mark.parametrize("form", ["kernels", "torch"])
@pytest.mark.parametrize("convention", ["flip", "legacy"])
def test_slice_geometry_equals_conditioning_of_survivors(convention, form, monkeypatch):
    """On the CPU the conditioning terms come from the numba kernels; the torch form (what CUDA runs) too."""
    if form == "torch":
        monkeypatch.setattr(covariance, "conditioning_terms", covariance.torch_conditioning_terms)
    p = random_gaussians(200, seed=3)
    tau = 4.0
    geom = slice_geometry(T(p["xyz"]), T(p["t"]), T(p["scales"]), T(p["ql"]), T(p["qr"]), tau, convention=convention,
                          time_cull=0.05)
    m_ref, c_ref, p_ref = oracle_condition(p["xyz"], p["t"], oracle_cov4(p, convention), tau)
    keep = np.nonzero(p_ref > 0.05)[0]
    assert 0 < len(keep) < 200
    np.testing.assert_array_equal(geom.index.numpy(), keep)
    np.testing.assert_allclose(geom.means.numpy(), m_ref[keep], rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(geom.covars.numpy(), c_ref[keep], rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(geom.marginal.numpy(), p_ref[keep], rtol=1e-12)


def test_static_gaussian_does_not_move_with_flip_convention():
    """q_l == q_r under the flip convention: Σ12 = 0, so the conditional mean stays at μ_xyz."""
    p = random_gaussians(20, seed=4)
    cov4 = covariance_4d(T(p["scales"]), T(p["ql"]), T(p["ql"]), "flip")
    for tau in (0.0, 7.0):
        mean3, _, _ = condition_on_time(T(p["xyz"]), T(p["t"]), cov4, tau)
        np.testing.assert_allclose(mean3.numpy(), p["xyz"], atol=1e-12)
    legacy = covariance_4d(T(p["scales"]), T(p["ql"]), T(p["ql"]), "legacy")
    assert legacy[:, :3, 3].abs().max() > 0.05
