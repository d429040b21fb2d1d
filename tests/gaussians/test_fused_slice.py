"""The fused time slice (one autograd function, numba + torch products) against autograd of the torch form in
float64: values and the gradients of every input, both backbones, stored SH or the appearance MLPs, and the edges."""

from __future__ import annotations

import pytest
import torch

from omg4.gaussians import GaussianConfig, fused_slice
from omg4.gaussians.appearance import AppearanceMLP
from omg4.gaussians.model import param_shapes, slice_values
from omg4.kernels import using_kernels

TIME_RANGE = (0.0, 2.0)


def _values(backbone: str, n: int, mlp: bool, seed: int, *, t_spread: float = 1.0):
    """Random raw values of ``n`` Gaussians near the origin, seen from cameras about 4 away."""
    g = torch.Generator().manual_seed(seed)
    config = GaussianConfig(time_range=TIME_RANGE, backbone=backbone, sh_degree_t=2 if backbone == "rt4dgs" else 0)
    shapes = param_shapes(n, config)
    values = {}
    for name, shape in shapes.items():
        values[name] = 0.3 * torch.randn(*shape, generator=g, dtype=torch.float64)
    values["xyz"] = 0.8 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    values["t"] = 1.0 + t_spread * (torch.rand(n, 1, generator=g, dtype=torch.float64) - 0.5)
    for name in ("scaling",):
        values[name] = values[name] - 2.0
    if backbone == "rt4dgs":
        values["scaling_t"] = torch.full((n, 1), -0.5, dtype=torch.float64) + 0.2 * torch.randn(n, 1, generator=g,
                                                                                                  dtype=torch.float64)
        values["rotation_r"][:, 0] += 1.0
    else:
        values["duration"] = torch.full((n, 1), -0.7, dtype=torch.float64)
    values["rotation"][:, 0] += 1.0
    appearance = None
    if mlp:
        for name in ("opacity", "features_dc", "features_rest"):
            values.pop(name)
        values["f_static"] = torch.randn(n, 3, generator=g, dtype=torch.float64)
        values["f_view"] = torch.randn(n, 3, generator=g, dtype=torch.float64)
        torch.manual_seed(seed)
        appearance = AppearanceMLP(num_rest=config.num_coeffs - 1, num_inputs=config.schema.mlp_inputs).double()
        with torch.no_grad():  # larger weights than the init, so the heads' outputs and their gradients are not tiny
            for p in appearance.parameters():
                p.mul_(3.0)
    return config, values, appearance


def _views(seed: int, v: int):
    g = torch.Generator().manual_seed(seed + 100)
    times = TIME_RANGE[0] + (TIME_RANGE[1] - TIME_RANGE[0]) * torch.rand(v, generator=g, dtype=torch.float64)
    centers = 4.0 * torch.nn.functional.normalize(torch.randn(v, 3, generator=g, dtype=torch.float64), dim=1)
    return times, centers


def _slice_and_grads(mode, config, values, appearance, times, centers, sh=(3, 2), seed=0, rows=None):
    leaves = {k: v.clone().requires_grad_(True) for k, v in values.items()}
    mlp = None
    if appearance is not None:
        mlp = AppearanceMLP(num_rest=appearance.num_rest, num_freqs=appearance.num_freqs,
                            num_inputs=appearance.num_inputs).double()
        mlp.load_state_dict(appearance.state_dict())
    degree_t = min(sh[1], config.sh_degree_t)
    with using_kernels(mode):
        sl = slice_values(leaves, config, sh[0], degree_t, times, centers, appearance=mlp, rows=rows)
    g = torch.Generator().manual_seed(seed + 7)
    outs = (sl.means, sl.covars, sl.colors, sl.opacities)
    loss = sum((o * torch.randn(o.shape, generator=g, dtype=o.dtype)).sum() for o in outs)
    if loss.requires_grad:
        loss.backward()
    grads = {k: v.grad for k, v in leaves.items()}
    if mlp is not None:
        grads.update({f"mlp.{k}": p.grad for k, p in mlp.named_parameters()})
    return sl, grads


def _compare(backbone, mlp, n=40, v=3, seed=0, sh=(3, 2), rows=None, **kw):
    config, values, appearance = _values(backbone, n, mlp, seed, **kw)
    times, centers = _views(seed, v)
    ref, ref_grads = _slice_and_grads("reference", config, values, appearance, times, centers, sh, seed, rows)
    got, got_grads = _slice_and_grads("fused", config, values, appearance, times, centers, sh, seed, rows)
    assert torch.equal(got.index, ref.index) and torch.equal(got.views, ref.views)
    for name in ("means", "covars", "colors", "opacities"):  # float64 sums in another order: relative to the largest
        want = getattr(ref, name)
        scale = float(want.detach().abs().max()) if want.numel() else 1.0
        torch.testing.assert_close(getattr(got, name), want, rtol=1e-12, atol=1e-12 * scale, msg=name)
    assert set(got_grads) == set(ref_grads)
    for name, want in ref_grads.items():
        have = got_grads[name]
        if want is None:
            assert have is None or not have.any(), name
            continue
        assert have is not None, name
        scale = float(want.abs().max())
        torch.testing.assert_close(have, want, rtol=1e-10, atol=1e-12 * max(scale, 1.0), msg=name)
    return ref, ref_grads


@pytest.mark.parametrize("backbone", ["rt4dgs", "freetimegs"])
@pytest.mark.parametrize("mlp", [False, True])
def test_fused_slice_matches_autograd_of_the_torch_form(backbone, mlp):
    ref, grads = _compare(backbone, mlp)
    assert ref.index.numel() > 40  # several views, most Gaussians in each
    assert all(g is not None and g.abs().max() > 0 for g in grads.values())  # every input gets a gradient


def test_fused_slice_at_lower_sh_degrees_and_one_view():
    _compare("rt4dgs", False, v=1, sh=(1, 0))
    _compare("rt4dgs", True, v=1, sh=(2, 1))


def test_edges_one_gaussian_none_in_view_and_a_time_outside_the_clip():
    _compare("rt4dgs", True, n=1, v=2)
    config, values, appearance = _values("rt4dgs", 10, True, 3, t_spread=0.2)
    far = torch.tensor([9.0, 11.0], dtype=torch.float64)  # far outside the clip: every Gaussian culled
    centers = torch.tensor([[4.0, 0.0, 0.0], [0.0, 4.0, 0.0]], dtype=torch.float64)
    sl, grads = _slice_and_grads("fused", config, values, appearance, far, centers)
    assert sl.index.numel() == 0 and sl.means.shape == (0, 3)
    _compare("rt4dgs", True, n=30, v=2, t_spread=3.0)  # Gaussians that live outside the clip


@pytest.mark.parametrize("mlp", [False, True])
def test_a_slice_of_some_rows_is_the_slice_of_those_rows_gathered(mlp):
    """A merge round renders all rows but the merged-away members (paper §4.3): sliced in place, the rows and
    values are the slice of the gathered rows, the index refers to the model's rows, the others get no gradient."""
    n = 40
    rows = torch.tensor([i for i in range(n) if i % 3 != 1 and i != 38])
    ref, ref_grads = _compare("rt4dgs", mlp, n=n, rows=rows)  # fused in place against the torch form
    config, values, appearance = _values("rt4dgs", n, mlp, 0)
    times, centers = _views(0, 3)
    gathered, gathered_grads = _slice_and_grads("reference", config, {k: v[rows] for k, v in values.items()},
                                                appearance, times, centers)
    assert torch.equal(ref.index, rows[gathered.index]) and torch.equal(ref.views, gathered.views)
    assert ref.num_total == n and gathered.index.numel() > 40
    for name in ("means", "covars", "colors", "opacities"):
        torch.testing.assert_close(getattr(ref, name), getattr(gathered, name), rtol=0, atol=0)
    left_out = torch.ones(n, dtype=torch.bool)
    left_out[rows] = False
    for name, grad in ref_grads.items():
        if name.startswith("mlp."):
            torch.testing.assert_close(grad, gathered_grads[name], rtol=1e-12, atol=1e-14)
            continue
        assert not grad[left_out].any(), name
        torch.testing.assert_close(grad[rows], gathered_grads[name], rtol=1e-12, atol=1e-14)


def test_the_fused_function_serves_cpu_models_of_one_float_dtype_only():
    config, values, appearance = _values("rt4dgs", 5, True, 1)
    assert fused_slice.runs(values, appearance)
    assert not fused_slice.runs(values, appearance.float())
    with using_kernels("reference"):
        assert not fused_slice.runs(values, None)
