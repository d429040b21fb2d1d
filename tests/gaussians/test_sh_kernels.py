"""The SH colour kernels (numba, CPU): the gather-fused weighted sum and the basis, against independent references."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from omg4.gaussians.sh import _basis_16, basis_by_table
from omg4.gaussians.sh_kernels import contract_coefficients, torch_contraction


def _case(seed: int, n: int = 30, m: int = 70, rest: int = 47, k: int = 48, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    dc = torch.randn(n, 1, 3, generator=g, dtype=dtype)
    others = torch.randn(n, rest, 3, generator=g, dtype=dtype)
    weights = torch.randn(m, k, generator=g, dtype=dtype)
    rows = torch.randint(n, (m,), generator=g)  # repeats and any order, as rows of several views
    return dc, others, weights, rows


def _numpy_reference(dc, rest, weights, rows):
    coeffs = np.concatenate([dc.numpy(), rest.numpy()], axis=1)[rows.numpy(), : weights.shape[1]]
    return np.einsum("mk,mkc->mc", weights.numpy(), coeffs)


@pytest.mark.parametrize("k", [48, 16, 1])
def test_forward_matches_a_numpy_gather_and_sum(k):
    dc, rest, weights, rows = _case(0, k=k)
    out = contract_coefficients(dc, rest, weights, rows)
    np.testing.assert_allclose(out.numpy(), _numpy_reference(dc, rest, weights, rows), rtol=1e-12, atol=1e-12)


def test_gradients_match_torch_autograd_of_the_gather_and_sum():
    dc, rest, weights, rows = _case(1)
    grads = []
    for fused in (True, False):
        leaves = [t.clone().requires_grad_(True) for t in (dc, rest, weights)]
        if fused:
            out = contract_coefficients(*leaves, rows)
        else:
            coeffs = torch.cat(leaves[:2], dim=1).index_select(0, rows)
            out = (leaves[2].unsqueeze(-1) * coeffs[:, : weights.shape[1]]).sum(1)
        (out.sin() * torch.arange(3, dtype=out.dtype)).sum().backward()
        grads.append([t.grad for t in leaves])
    for got, want in zip(*grads):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_gradcheck_with_fewer_weights_than_coefficients():
    dc, rest, weights, rows = _case(2, n=5, m=9, rest=8, k=6)
    inputs = [t.requires_grad_(True) for t in (dc, rest, weights)]
    assert torch.autograd.gradcheck(lambda a, b, w: contract_coefficients(a, b, w, rows), inputs)


@pytest.mark.parametrize("k", [48, 16, 1])
def test_unused_gaussians_and_coefficients_past_k_get_exact_zeros(k):
    """Gaussians in no row, and coefficients past ``K``, get exact zeros (also when freed buffers are reused)."""
    dc, rest, weights, rows = _case(7, n=40, m=25, k=k)
    rows = rows % 20  # Gaussians 20..39 are in no row
    for _ in range(3):  # later backward passes reuse the freed (non-zero) buffers of earlier ones
        a, b = dc.clone().requires_grad_(True), rest.clone().requires_grad_(True)
        contract_coefficients(a, b, weights, rows).square().sum().backward()
        want_dc = torch.zeros_like(dc)
        want_rest = torch.zeros_like(rest)
        out = torch.from_numpy(_numpy_reference(dc, rest, weights, rows))
        want_dc.index_add_(0, rows, (2 * out[:, None, :] * weights[:, :1, None]))
        want_rest[:, : k - 1].index_add_(0, rows, 2 * out[:, None, :] * weights[:, 1:, None])
        torch.testing.assert_close(a.grad, want_dc, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(b.grad, want_rest, rtol=1e-12, atol=0)
        assert not b.grad[20:].any() and not b.grad[:, max(k - 1, 0):].any()


def test_only_the_needed_gradients_and_rows_default_to_identity():
    dc, rest, weights, _ = _case(3, n=12, m=12)
    w = weights.clone().requires_grad_(True)
    contract_coefficients(dc, rest, w).sum().backward()
    coeffs = torch.cat([dc, rest], dim=1)
    torch.testing.assert_close(w.grad, coeffs.sum(-1), rtol=1e-12, atol=1e-12)


def test_float32_agrees_with_float64():
    dc, rest, weights, rows = _case(4, n=500, m=2000)
    want = contract_coefficients(dc, rest, weights, rows)
    got = contract_coefficients(dc.float(), rest.float(), weights.float(), rows)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got.double(), want, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("bad", ["too_few", "dtype", "rows", "row_out_of_range", "negative_row"])
def test_mismatched_inputs_are_refused(bad):
    dc, rest, weights, rows = _case(5, n=4, m=4, rest=3, k=4)
    rows = None
    if bad == "too_few":
        weights = torch.zeros(4, 5, dtype=weights.dtype)
    elif bad == "dtype":
        weights = weights.float()
    elif bad == "rows":
        dc, rest = dc[:3], rest[:3]
    else:
        rows = torch.tensor([0, 1, 4 if bad == "row_out_of_range" else -1, 2])
    with pytest.raises(ValueError):
        contract_coefficients(dc, rest, weights, rows)


def test_the_torch_form_for_other_devices_agrees_with_the_kernels():
    """The form CUDA runs (checked here on CPU tensors): same values and gradients."""
    dc, rest, weights, rows = _case(6, k=32)
    grads = []
    for fn in (contract_coefficients, torch_contraction):
        leaves = [t.clone().requires_grad_(True) for t in (dc, rest, weights)]
        out = fn(*leaves, rows)
        (out * out).sum().backward()
        grads.append([out.detach()] + [t.grad for t in leaves])
    for got, want in zip(*grads):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_without_rows_weight_row_m_takes_coefficient_row_m():
    """rows=None (coefficients predicted per slice row, as by the appearance MLPs) in the kernels and the torch
    form: an einsum over the joined coefficients, values and gradients (float64)."""
    g = torch.Generator().manual_seed(12)
    dc, rest = torch.randn(30, 1, 3, generator=g, dtype=torch.float64), torch.randn(30, 47, 3, generator=g,
                                                                                       dtype=torch.float64)
    weights = torch.randn(30, 32, generator=g, dtype=torch.float64)
    upstream = torch.randn(30, 3, generator=g, dtype=torch.float64)
    results = []
    for fn in (contract_coefficients, torch_contraction,
               lambda d, r, w: torch.einsum("mk,mkc->mc", w, torch.cat([d, r], dim=1)[:, :32])):
        leaves = [t.clone().requires_grad_(True) for t in (dc, rest, weights)]
        out = fn(*leaves)
        (out * upstream).sum().backward()
        results.append([out.detach()] + [t.grad for t in leaves])
    for got in results[:2]:
        for a, b in zip(got, results[2]):
            torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="weight rows"):
        contract_coefficients(dc[:29], rest[:29], weights)


def test_other_dtypes_take_the_torch_form():
    dc, rest, weights, rows = _case(11, n=20, m=40, dtype=torch.float64)
    want = contract_coefficients(dc, rest, weights, rows)
    got = contract_coefficients(dc.bfloat16(), rest.bfloat16(), weights.bfloat16(), rows)
    assert got.dtype == torch.bfloat16
    torch.testing.assert_close(got.double(), want, rtol=0.05, atol=0.3)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_basis_kernels_equal_the_monomial_table_values_and_direction_gradients(degree):
    g = torch.Generator().manual_seed(20 + degree)
    dirs = torch.nn.functional.normalize(torch.randn(300, 3, generator=g, dtype=torch.float64), dim=1)
    upstream = torch.randn(300, 16, generator=g, dtype=torch.float64)
    results = []
    for fn in (_basis_16, basis_by_table):
        d = dirs.clone().requires_grad_(True)
        y = fn(d, degree)
        (y * upstream).sum().backward()
        results.append((y.detach(), d.grad))
    (y_kernel, g_kernel), (y_table, g_table) = results
    torch.testing.assert_close(y_kernel, y_table, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(g_kernel, g_table, rtol=1e-12, atol=1e-12)
    assert torch.count_nonzero(y_kernel[:, (degree + 1) ** 2:]) == 0  # inactive functions are zero
    assert torch.count_nonzero(y_kernel[:, : (degree + 1) ** 2]) > 0


def test_basis_gradcheck_and_float32():
    g = torch.Generator().manual_seed(30)
    dirs = torch.randn(7, 3, generator=g, dtype=torch.float64).requires_grad_(True)  # not unit: any polynomial input
    assert torch.autograd.gradcheck(lambda d: _basis_16(d, 3), (dirs,))
    d32 = dirs.detach().float()
    torch.testing.assert_close(_basis_16(d32, 3).double(), _basis_16(dirs.detach(), 3), rtol=1e-5, atol=1e-5)
