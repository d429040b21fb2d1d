"""Spherical harmonics (rt4dgs §2) against closed forms and scipy's complex SH."""

import math

import numpy as np
import pytest
import torch
from scipy.special import sph_harm_y

from omg4.gaussians import colors_from_sh, eval_sh_4d, fold_time_sh, rgb_to_sh, sh_basis, sh_to_rgb
from omg4.gaussians.sh import C0, C1


def real_sh_scipy(dirs, degree):
    """Real SH with the Condon–Shortley phase (the 3DGS basis), index l² + l + m, from scipy's complex Y_l^m."""
    theta, phi = np.arccos(np.clip(dirs[:, 2], -1, 1)), np.arctan2(dirs[:, 1], dirs[:, 0])
    cols = []
    for l in range(degree + 1):
        for m in range(-l, l + 1):
            y = sph_harm_y(l, abs(m), theta, phi)
            cols.append(math.sqrt(2) * y.real if m > 0 else math.sqrt(2) * y.imag if m < 0 else y.real)
    return np.stack(cols, axis=1)


def unit_dirs(n, seed=0):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_basis_matches_scipy_real_sh(degree):
    d = unit_dirs(100)
    np.testing.assert_allclose(sh_basis(torch.from_numpy(d), degree).numpy(), real_sh_scipy(d, degree), atol=1e-12)


def test_constant_coefficient_gives_c0_times_value():
    n = 7
    coeffs = torch.zeros(n, 48, 3, dtype=torch.float64)
    coeffs[:, 0] = torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)
    out = eval_sh_4d(coeffs, torch.from_numpy(unit_dirs(n)), torch.zeros(n, dtype=torch.float64), 10.0, 3, 2)
    np.testing.assert_allclose(out.numpy(), np.tile([0.3 * C0, -C0, 2 * C0], (n, 1)), atol=1e-15)


def test_degree_one_closed_form():
    """Y1 = −C1 y, Y2 = C1 z, Y3 = −C1 x (3DGS signs)."""
    d = unit_dirs(20, seed=3)
    c = np.random.default_rng(4).normal(size=(20, 4, 2))
    out = eval_sh_4d(torch.from_numpy(c), torch.from_numpy(d), torch.zeros(20, dtype=torch.float64), 1.0, 1, 0,
                     band_size=4).numpy()
    x, y, z = d.T
    expected = C0 * c[:, 0] - C1 * y[:, None] * c[:, 1] + C1 * z[:, None] * c[:, 2] - C1 * x[:, None] * c[:, 3]
    np.testing.assert_allclose(out, expected, atol=1e-13)


@pytest.mark.parametrize("dt_fraction, weights", [(0.0, (1, 1, 1)), (0.25, (1, 0, -1)), (0.5, (1, -1, 1)),
                                                  (-0.5, (1, -1, 1))])
def test_temporal_cosine_terms(dt_fraction, weights):
    """cos(2π n Δt / T) at Δt = 0, T/4, T/2: band weights (1,1,1), (1,0,−1), (1,−1,1)."""
    period, n = 10.0, 5
    d = torch.from_numpy(unit_dirs(n, seed=5))
    c = torch.from_numpy(np.random.default_rng(6).normal(size=(n, 48, 3)))
    dt = torch.full((n,), dt_fraction * period, dtype=torch.float64)
    out = eval_sh_4d(c, d, dt, period, 3, 2).numpy()
    Y = real_sh_scipy(d.numpy(), 3)
    expected = sum(w * np.einsum("nk,nkc->nc", Y, c[:, 16 * b:16 * b + 16].numpy()) for b, w in enumerate(weights))
    np.testing.assert_allclose(out, expected, atol=1e-12)


def test_inactive_coefficients_are_ignored():
    n = 6
    d = torch.from_numpy(unit_dirs(n, seed=8))
    dt = torch.linspace(-3, 3, n, dtype=torch.float64)
    c = torch.from_numpy(np.random.default_rng(9).normal(size=(n, 48, 3)))
    for degree, degree_t in [(0, 0), (1, 0), (2, 1), (3, 1)]:
        active = torch.zeros_like(c)
        for b in range(degree_t + 1):
            active[:, 16 * b:16 * b + (degree + 1) ** 2] = c[:, 16 * b:16 * b + (degree + 1) ** 2]
        noisy = active.clone()
        noisy[active == 0] = 1e6
        a = eval_sh_4d(noisy, d, dt, 7.0, degree, degree_t)
        b = eval_sh_4d(active, d, dt, 7.0, 3, 2)
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_fold_time_sh_equals_explicit_sum():
    n = 4
    c = torch.from_numpy(np.random.default_rng(10).normal(size=(n, 48, 3)))
    dt = torch.tensor([0.0, 1.0, 2.5, -4.0], dtype=torch.float64)
    folded = fold_time_sh(c, dt, 10.0, 3, 2).numpy()
    w = np.cos(2 * np.pi * np.outer(dt.numpy(), [0, 1, 2]) / 10.0)
    expected = sum(w[:, b, None, None] * c[:, 16 * b:16 * (b + 1)].numpy() for b in range(3))
    np.testing.assert_allclose(folded, expected, atol=1e-13)


def test_colors_add_half_and_clamp_at_zero():
    c = torch.zeros(2, 48, 3, dtype=torch.float64)
    c[0, 0] = 1.0
    c[1, 0] = -10.0
    out = colors_from_sh(c, torch.tensor([[0, 0, 1.0]] * 2, dtype=torch.float64), torch.zeros(2, dtype=torch.float64),
                         1.0, 3, 2)
    np.testing.assert_allclose(out[0].numpy(), [0.5 + C0] * 3, atol=1e-15)
    assert torch.equal(out[1], torch.zeros(3, dtype=torch.float64))


def test_rgb_sh_round_trip_and_known_values():
    rgb = torch.tensor([[0.5, 0.0, 1.0]], dtype=torch.float64)
    np.testing.assert_allclose(rgb_to_sh(rgb).numpy(), [[0.0, -0.5 / C0, 0.5 / C0]], atol=1e-15)
    torch.testing.assert_close(sh_to_rgb(rgb_to_sh(rgb)), rgb, rtol=0, atol=1e-15)
    assert C0 == pytest.approx(0.5 / math.sqrt(math.pi), rel=1e-15)


def test_layout_too_small_is_rejected():
    with pytest.raises(ValueError, match="do not hold"):
        eval_sh_4d(torch.zeros(1, 16, 3), torch.tensor([[0, 0, 1.0]]), torch.zeros(1), 1.0, 3, 1)


def test_folded_coefficients_evaluate_like_4d_sh():
    """eval_sh(fold_time_sh(c, Δt)) == eval_sh_4d(c, Δt): what the PLY export relies on."""
    from omg4.gaussians import eval_sh

    n = 9
    c = torch.from_numpy(np.random.default_rng(11).normal(size=(n, 48, 3)))
    d = torch.from_numpy(unit_dirs(n, seed=12))
    dt = torch.linspace(-5, 5, n, dtype=torch.float64)
    for degree, degree_t in [(3, 2), (2, 1), (0, 2)]:
        folded = fold_time_sh(c, dt, 10.0, degree, degree_t)
        torch.testing.assert_close(eval_sh(folded, d, degree), eval_sh_4d(c, d, dt, 10.0, degree, degree_t),
                                   rtol=1e-12, atol=1e-12)
