"""The ``compiled`` kernels (``--kernels compiled``: the per-Gaussian torch forms through ``torch.compile``, inductor's
Triton kernels on CUDA) run here through inductor's CPU backend, against the eager forms (``--kernels reference``)
in float64: values and gradients of a training step's slice — both backbones, Gaussians outside the time window,
tiny and huge scales, near-degenerate rotations, an empty set and one Gaussian."""

from __future__ import annotations

import shutil

import pytest
import torch
from torch._dynamo.utils import counters

from omg4.gaussians import GaussianConfig, Gaussians4D
from omg4.kernels import torch_form, using_kernels

pytestmark = pytest.mark.skipif(shutil.which("c++") is None and shutil.which("g++") is None,
                                reason="inductor's CPU backend needs a C++ compiler")

TIME_RANGE = (0.0, 2.0)
VIEW_TIMES = torch.tensor([0.3, 1.1, 1.9], dtype=torch.float64)
CENTERS = torch.tensor([[0.0, 0.0, -4.0], [1.0, 0.5, -3.5], [-2.0, 0.0, -3.0]], dtype=torch.float64)


def gaussians(backbone: str, n: int, seed: int = 0) -> Gaussians4D:
    """A random float64 model of ``backbone`` whose rows include the edges: a Gaussian far outside the time window,
    tiny and huge spatial scales, a near-degenerate (tiny-norm) rotation, and equal left and right rotations."""
    g = torch.Generator().manual_seed(seed)
    config = GaussianConfig(time_range=TIME_RANGE, backbone=backbone, sh_degree_t=2 if backbone == "rt4dgs" else 0)
    base = Gaussians4D.from_points(torch.rand(n, 3, generator=g) * 2 - 1, torch.rand(n, 3, generator=g), config,
                                   generator=g)
    p = {k: v.double().clone() for k, v in base.params.items()}
    for name in ("rotation", "rotation_r", "velocity"):
        if name in p:
            p[name] += 0.3 * torch.randn(p[name].shape, generator=g, dtype=torch.float64)
    p["features_rest"] = 0.2 * torch.randn(p["features_rest"].shape, generator=g, dtype=torch.float64)
    p["opacity"] = torch.randn(n, 1, generator=g, dtype=torch.float64)
    if n >= 5:
        p["t"][0] = 40.0  # far outside the clip: culled at every view time
        p["scaling"][1] = -9.0  # tiny
        p["scaling"][2] = 4.0  # huge
        p["rotation"][3] = 1e-9 * p["rotation"][3]  # near-degenerate
        if "rotation_r" in p:
            p["rotation_r"][4] = p["rotation"][4]
    return Gaussians4D({k: v.requires_grad_() for k, v in p.items()}, config)


def slice_and_grads(model: Gaussians4D, mode: str):
    """The slice's rows and values at :data:`VIEW_TIMES` and the gradients of a loss of all its values."""
    with using_kernels(mode):
        s = model.slice_views(VIEW_TIMES, CENTERS)
    values = [s.means, s.covars, s.colors, s.opacities]
    weights = [torch.linspace(-1, 1, v.numel(), dtype=v.dtype).reshape(v.shape) for v in values]
    loss = sum((w * v.sin()).sum() for w, v in zip(weights, values))
    names = sorted(model.params)
    grads = torch.autograd.grad(loss, [model.params[k] for k in names], allow_unused=True) if values[0].numel() else ()
    return s, values, dict(zip(names, grads))


@pytest.mark.parametrize("backbone", ["rt4dgs", "freetimegs"])
def test_compiled_slice_equals_the_eager_forms(backbone):
    model = gaussians(backbone, 300)
    graphs_before = counters["stats"]["unique_graphs"]
    compiled, values, grads = slice_and_grads(model, "compiled")
    assert counters["stats"]["unique_graphs"] > graphs_before, "the compiled kernels ran eagerly"
    reference, ref_values, ref_grads = slice_and_grads(model, "reference")
    assert torch.equal(compiled.index, reference.index) and torch.equal(compiled.views, reference.views)
    assert 0 not in compiled.index.tolist(), "a Gaussian outside the time window was kept"
    for name, a, b in zip(("means", "covars", "colors", "opacities"), values, ref_values):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12, msg=name)
    for name, g in ref_grads.items():
        if g is None:
            assert grads[name] is None, name
            continue
        assert g.abs().max() > 0, f"the loss does not reach {name}"
        torch.testing.assert_close(grads[name], g, rtol=1e-9, atol=1e-12, msg=f"d loss / d {name}")


@pytest.mark.parametrize("case", ["no Gaussian", "none in the time window", "one Gaussian"])
def test_empty_and_one_gaussian_slices_run_eagerly_and_agree(case):
    model = gaussians("rt4dgs", 4)
    keep = {"no Gaussian": 0, "none in the time window": 4, "one Gaussian": 1}[case]
    params = {k: v.detach()[:keep].clone() for k, v in model.params.items()}
    if case == "none in the time window":
        params["t"].fill_(40.0)
    model = Gaussians4D({k: v.requires_grad_() for k, v in params.items()}, model.config)
    _, values, grads = slice_and_grads(model, "compiled")
    _, ref_values, ref_grads = slice_and_grads(model, "reference")
    assert values[0].shape[0] == (3 if case == "one Gaussian" else 0)
    for a, b in zip(values, ref_values):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    for name, g in ref_grads.items():
        assert (g is None) == (grads[name] is None) and (g is None or torch.equal(g, grads[name])), name


def test_torch_form_is_the_function_itself_outside_the_compiled_mode():
    def form(x):
        return x * 2

    for mode in ("fused", "reference"):
        with using_kernels(mode):
            assert torch_form(form) is form
    with using_kernels("compiled"):
        assert torch_form(form) is not form
        x = torch.arange(6.0)
        assert torch.equal(torch_form(form)(x), x * 2)
