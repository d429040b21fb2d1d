"""The conditioning-terms kernels (numba, CPU) against the torch form and finite differences (rt4dgs §1.3–1.4).

The torch reference builds Σ4 = R4 diag(s²) R4ᵀ from the quaternion-product table and a batched
matrix product (:func:`omg4.gaussians.covariance_4d`, itself tested against an independent oracle
in ``test_covariance4d.py``) and lets autograd differentiate it.
"""

from __future__ import annotations

import pytest
import torch

from omg4.gaussians import covariance_4d
from omg4.gaussians.covariance import conditioning_terms
from omg4.gaussians.covariance_kernels import kernel_conditioning_terms


def _inputs(seed: int, n: int = 64, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    scales = torch.exp(0.5 * torch.randn(n, 4, generator=g, dtype=dtype))
    q_l = torch.randn(n, 4, generator=g, dtype=dtype) * 2.0  # unnormalized, as stored
    q_r = torch.randn(n, 4, generator=g, dtype=dtype) * 0.5
    return scales, q_l, q_r


def _torch_reference(scales, q_l, q_r, convention):
    cov4 = covariance_4d(scales, q_l, q_r, convention)
    var_t = cov4[:, 3, 3]
    gain = cov4[:, :3, 3] / var_t[:, None]
    cov3 = cov4[:, :3, :3] - cov4[:, :3, 3, None] * cov4[:, None, 3, :3] / var_t[:, None, None]
    return gain, cov3, var_t


@pytest.mark.parametrize("convention", ["flip", "legacy"])
def test_values_match_the_torch_form(convention):
    inputs = _inputs(0)
    for got, want in zip(kernel_conditioning_terms(*inputs, convention), _torch_reference(*inputs, convention)):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("convention", ["flip", "legacy"])
@pytest.mark.parametrize("used", [(0, 1, 2), (1,), (0, 2)])
def test_gradients_match_torch_autograd(convention, used):
    """Every input's gradient for a loss on all outputs or only some of them (the others get no gradient)."""
    inputs = _inputs(1)
    g = torch.Generator().manual_seed(2)
    weights = [torch.randn(s, generator=g, dtype=torch.float64) for s in ((64, 3), (64, 3, 3), (64,))]
    grads = []
    for form in (kernel_conditioning_terms, _torch_reference):
        leaves = [x.clone().requires_grad_(True) for x in inputs]
        outputs = form(*leaves, convention)
        sum((outputs[i] * weights[i]).sum() for i in used).backward()
        grads.append([x.grad for x in leaves])
    for got, want in zip(*grads):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)


def test_gradcheck():
    inputs = [x.requires_grad_(True) for x in _inputs(3, n=6)]
    assert torch.autograd.gradcheck(lambda s, a, b: kernel_conditioning_terms(s, a, b, "flip"), inputs)


def test_float32_agrees_with_float64():
    inputs = _inputs(4, n=500)
    single = kernel_conditioning_terms(*(x.float() for x in inputs), "flip")
    double = kernel_conditioning_terms(*inputs, "flip")
    for got, want in zip(single, double):
        assert got.dtype == torch.float32
        torch.testing.assert_close(got.double(), want, rtol=1e-4, atol=1e-5)


def test_dispatch_kernels_on_cpu_torch_form_for_other_dtypes():
    inputs = _inputs(5, n=20)
    kernel_fn = conditioning_terms(*(x.clone().requires_grad_(True) for x in inputs))
    assert type(kernel_fn[0].grad_fn).__name__ == "_ConditioningTermsBackward"
    half = conditioning_terms(*(x.to(torch.bfloat16) for x in inputs))  # no kernel for bfloat16: the torch form
    for got, want in zip(half, _torch_reference(*inputs, "flip")):
        assert got.dtype == torch.bfloat16
        torch.testing.assert_close(got.double(), want, rtol=0.1, atol=0.1)
