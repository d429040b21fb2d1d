"""CPU backend (numba kernels) vs the dense reference: values, every gradient, edge cases."""

from __future__ import annotations

import pytest
import torch
from dense_reference import dense_rasterize, random_scene

from omg4.errors import OMG4Error
from omg4.render import Rendered, rasterize
from omg4.render.api import resolve_backend

GRAD_NAMES = ("means", "covars", "colors", "opacities", "background")


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """max |a − b| / max |b| (b must not vanish)."""
    b = b.detach().double()
    scale = float(b.abs().max())
    assert scale > 0, "reference is identically zero: the comparison would be vacuous"
    return float((a.detach().double() - b).abs().max()) / scale


def _loss(r, seed=5):
    """A loss touching every output with random weights, so every gradient path is exercised."""
    g = torch.Generator().manual_seed(seed)
    h, w, c = r.image.shape
    wi = torch.randn(h, w, c, generator=g, dtype=torch.float64).to(r.image.dtype)
    wa = torch.randn(h, w, 1, generator=g, dtype=torch.float64).to(r.image.dtype)
    wd = torch.randn(h, w, 1, generator=g, dtype=torch.float64).to(r.image.dtype)
    return (r.image * wi).sum() + (r.alpha * wa).sum() + 0.3 * (r.depth * wd).sum()


SCENES = {
    "sparse": dict(seed=0, n=60, size=(37, 29)),
    "saturated": dict(seed=1, n=300, size=(37, 29), opacity=(0.6, 0.99), scale=0.15),
    "tile_borders": dict(seed=2, n=120, size=(40, 33), pixel_grid=8),
    "one_channel": dict(seed=3, n=80, size=(29, 37), channels=1),
    "five_channels": dict(seed=4, n=80, size=(33, 18), channels=5, scale=0.12),
}


def _compare(name, dtype, tile_size=8, alpha_max=0.999):
    spec = dict(SCENES[name])
    seed, n, (w, h) = spec.pop("seed"), spec.pop("n"), spec.pop("size")
    sc = random_scene(seed, n, w, h, **spec)
    a, b = sc.tensors(dtype), sc.tensors(torch.float64)
    ra = rasterize(**a, tile_size=tile_size, alpha_max=alpha_max, backend="cpu")
    rb = dense_rasterize(**b, alpha_max=alpha_max)
    _loss(ra).backward()
    _loss(rb).backward()
    values = {k: rel_err(getattr(ra, k), getattr(rb, k)) for k in ("image", "alpha", "depth")}
    grads = {k: rel_err(a[k].grad, b[k].grad) for k in GRAD_NAMES}
    grads["means2d"] = rel_err(ra.means2d.grad, rb.means2d.grad)
    return ra, rb, values, grads


@pytest.mark.parametrize("name", sorted(SCENES))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cpu_matches_dense_reference(name, dtype):
    ra, rb, values, grads = _compare(name, dtype)
    assert ra.image.dtype == dtype and ra.image.shape == rb.image.shape
    vtol, gtol = (1e-5, 1e-4) if dtype == torch.float32 else (1e-11, 1e-10)
    assert max(values.values()) < vtol, values
    assert max(grads.values()) < gtol, grads
    if name == "saturated":
        assert rb.n_terminated > 0.3 * ra.image.shape[0] * ra.image.shape[1]


@pytest.mark.parametrize("alpha_max", [0.99, 0.999])
def test_cpu_matches_dense_reference_with_active_alpha_clamp(alpha_max):
    """Opacities up to 1 and means on pixel centres: many Gaussians hit the alpha cap (zero gradient)."""
    sc = random_scene(12, 200, 31, 23, opacity=(0.98, 1.0), scale=0.15, pixel_centres=True)
    assert int((sc.opacities > alpha_max).sum()) >= 8
    a, b = sc.tensors(), sc.tensors()
    ra = rasterize(**a, tile_size=16, alpha_max=alpha_max, backend="cpu")
    rb = dense_rasterize(**b, alpha_max=alpha_max)
    _loss(ra).backward()
    _loss(rb).backward()
    assert rel_err(ra.image, rb.image) < 1e-11 and rel_err(ra.alpha, rb.alpha) < 1e-11
    for k in GRAD_NAMES:
        assert rel_err(a[k].grad, b[k].grad) < 1e-10, k
    assert rel_err(ra.means2d.grad, rb.means2d.grad) < 1e-10
    assert rb.n_terminated > 0


def test_cpu_backend_matches_finite_differences():
    sc = random_scene(6, 6, 9, 7, scale=0.4, opacity=(0.3, 0.99))
    t = sc.tensors(torch.float64)

    proj = torch.randn(4, 7 * 9 * 5, generator=torch.Generator().manual_seed(1), dtype=torch.float64)

    def fn(*args):  # four random projections of (image, alpha, depth): one backward each
        r = rasterize(**{**t, **dict(zip(GRAD_NAMES, args))}, tile_size=4, backend="cpu")
        return proj @ torch.cat([r.image, r.alpha, r.depth], -1).flatten()

    assert rasterize(**t, backend="cpu").alpha.max() > 0.5
    assert torch.autograd.gradcheck(fn, tuple(t[k] for k in GRAD_NAMES), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_tile_size_does_not_change_the_result():
    sc = random_scene(7, 200, 45, 31, scale=0.15)
    base = rasterize(**sc.tensors(requires_grad=False), tile_size=16)
    for ts in (1, 7, 8, 64):
        r = rasterize(**sc.tensors(requires_grad=False), tile_size=ts)
        assert rel_err(r.image, base.image) < 1e-13 and rel_err(r.depth, base.depth) < 1e-13
        assert torch.equal(r.radii, base.radii)


def test_means2d_grad_is_pixel_gradient():
    """∂L/∂means2d by finite differences of the 3D mean along the camera's x axis.

    The covariances are flat along the camera z axis, so ``J Σ Jᵀ`` does not depend on the
    mean's x: a shift of ``δ·z/fx`` moves means2d by exactly δ pixels and nothing else.
    """
    sc = random_scene(8, 20, 24, 20, scale=0.2)
    R = sc.viewmat[:3, :3]
    flat = sc.covars.clone()
    flat[:, 2, :] = 0
    flat[:, :, 2] = 0
    sc.covars = R.T @ flat @ R
    t = sc.tensors(torch.float64)
    r = rasterize(**t)
    _loss(r).backward()
    i = int(torch.argmax(r.means2d.grad.norm(dim=-1)))
    z = float((R @ sc.means[i] + sc.viewmat[:3, 3])[2])
    step = 1e-5  # pixels along x
    shift = R.T @ torch.tensor([step * z / float(sc.K[0, 0]), 0.0, 0.0], dtype=torch.float64)
    losses = []
    for sgn in (1, -1):
        m = sc.means.clone()
        m[i] += sgn * shift
        losses.append(float(_loss(rasterize(**{**sc.tensors(requires_grad=False), "means": m}))))
    fd = (losses[0] - losses[1]) / (2 * step)
    g = float(r.means2d.grad[i, 0])
    assert abs(g) > 1e-2 and abs(fd - g) < 1e-6 * max(1.0, abs(g))


# --------------------------------------------------------------------------- edge cases

def _empty_like(n, channels=3, dtype=torch.float32):
    return dict(means=torch.zeros(n, 3, dtype=dtype), covars=torch.eye(3, dtype=dtype).repeat(n, 1, 1) * 0.01,
                colors=torch.ones(n, channels, dtype=dtype), opacities=torch.full((n,), 0.5, dtype=dtype))


def test_no_gaussians():
    bg = torch.tensor([0.2, 0.4, 0.6], requires_grad=True)
    K = torch.tensor([[20.0, 0, 10], [0, 20, 8], [0, 0, 1]])
    r = rasterize(**_empty_like(0), viewmat=torch.eye(4), K=K, width=21, height=17, background=bg)
    assert isinstance(r, Rendered)
    assert r.image.shape == (17, 21, 3) and r.alpha.shape == (17, 21, 1) and r.depth.shape == (17, 21, 1)
    assert torch.equal(r.image, bg.detach().expand(17, 21, 3)) and r.alpha.abs().max() == 0
    assert r.means2d.shape == (0, 2) and r.radii.shape == (0,)
    r.image.sum().backward()
    assert torch.allclose(bg.grad, torch.full((3,), 17.0 * 21.0))


def test_single_gaussian_and_one_pixel_image():
    inputs = _empty_like(1)
    inputs["means"] = torch.tensor([[0.0, 0.0, 3.0]])
    K = torch.tensor([[10.0, 0, 0.5], [0, 10, 0.5], [0, 0, 1]])
    r = rasterize(**inputs, viewmat=torch.eye(4), K=K, width=1, height=1)
    assert r.image.shape == (1, 1, 3) and int(r.radii[0]) > 0
    # centred on the pixel centre (0.5, 0.5): alpha = opacity, depth = alpha·z
    assert abs(float(r.alpha) - 0.5) < 1e-6 and abs(float(r.depth) - 1.5) < 1e-5
    assert torch.allclose(r.image, torch.full((1, 1, 3), 0.5))


@pytest.mark.parametrize("where", ["behind", "off_screen", "beyond_far"])
def test_invisible_gaussians_render_background(where):
    g = torch.Generator().manual_seed(9)
    n = 50
    means = torch.randn(n, 3, generator=g)
    if where == "behind":
        means[:, 2] = -torch.rand(n, generator=g) * 3  # includes z = 0 neighbourhood
        means[0] = torch.tensor([0.0, 0.0, 0.0])
    elif where == "off_screen":
        means[:, 2] = 3.0
        means[:, 0] = 50.0 + means[:, 0]
    else:
        means[:, 2] = 200.0
    inputs = _empty_like(n)
    inputs["means"] = means.requires_grad_()
    bg = torch.tensor([0.1, 0.2, 0.3])
    K = torch.tensor([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]])
    r = rasterize(**inputs, viewmat=torch.eye(4), K=K, width=32, height=24, background=bg, far=100.0)
    assert torch.equal(r.image, bg.expand(24, 32, 3)) and torch.all(r.radii == 0)
    r.image.sum().backward()
    assert torch.all(means.grad == 0)


def test_no_grad_inputs_give_no_means2d_grad():
    sc = random_scene(10, 30, 20, 16)
    r = rasterize(**sc.tensors(torch.float32, requires_grad=False))
    assert not r.means2d.requires_grad and r.means2d.grad is None
    colors_only = sc.tensors(torch.float32, requires_grad=False)
    colors_only["colors"].requires_grad_()
    r = rasterize(**colors_only)
    r.image.sum().backward()
    assert colors_only["colors"].grad.abs().sum() > 0 and r.means2d.grad is None


def test_bad_inputs():
    sc = random_scene(11, 10, 16, 12)
    t = sc.tensors(torch.float32, requires_grad=False)
    t["means"][3, 1] = float("nan")
    with pytest.raises(OMG4Error, match="means"):
        rasterize(**t)
    t = sc.tensors(torch.float32, requires_grad=False)
    with pytest.raises(ValueError, match="covars"):
        rasterize(**{**t, "covars": t["covars"][:, :2]})
    with pytest.raises(ValueError, match="backend"):
        rasterize(**t, backend="opengl")
    with pytest.raises(ValueError, match="alpha_max"):
        rasterize(**t, alpha_max=1.0)
    with pytest.raises(ValueError, match="alpha_max=0.999"):
        rasterize(**t, backend="gsplat", alpha_max=0.99)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
@pytest.mark.parametrize("name", ["means", "covars", "colors", "opacities", "viewmat", "K", "background"])
def test_a_non_finite_value_in_any_input_is_named(name, bad):
    t = random_scene(12, 10, 16, 12).tensors(torch.float32, requires_grad=False)
    t["background"] = torch.zeros(3)
    t[name].view(-1)[-1] = bad
    with pytest.raises(OMG4Error, match=f"rasterize: {name} contains NaN"):
        rasterize(**t)


def test_finite_float64_values_whose_sum_overflows_pass_the_check():
    """The finiteness check sums each input in float64; huge finite float64 values overflow that sum, not the check."""
    t = random_scene(13, 10, 16, 12).tensors(torch.float64, requires_grad=False)
    t["colors"][:2] = 1.5e308
    r = rasterize(**t)
    assert r.image.shape == (12, 16, 3)
    far_background = torch.tensor([1.7e308, 1.7e308, 0.0], dtype=torch.float64)
    rasterize(**{**t, "background": far_background})  # the last input checked, no views: not a bad view
    t["colors"][3, 0] = -float("inf")  # +inf and −inf would sum to NaN: still named
    with pytest.raises(OMG4Error, match="colors"):
        rasterize(**t)


def test_views_out_of_range_are_refused():
    from omg4.render.api import rasterize_views

    t = random_scene(14, 10, 16, 12).tensors(torch.float32, requires_grad=False)
    viewmats, Ks = torch.stack([t["viewmat"]] * 2), torch.stack([t["K"]] * 2)
    views = torch.zeros(10, dtype=torch.int64)
    rasterize_views(t["means"], t["covars"], t["colors"], t["opacities"], views, viewmats, Ks, 16, 12)
    for wrong in (2, -1):
        views[4] = wrong
        with pytest.raises(ValueError, match=r"views must lie in \[0, 2\)"):
            rasterize_views(t["means"], t["covars"], t["colors"], t["opacities"], views, viewmats, Ks, 16, 12)


def test_auto_backend_is_cpu_for_cpu_tensors():
    assert resolve_backend("auto", torch.device("cpu")) == "cpu"
    assert resolve_backend("gsplat", torch.device("cpu")) == "gsplat"


def test_render_view_renders_a_time_slice():
    """The lead's ``render_view`` drives ``rasterize`` through a model's ``slice_at``."""
    from omg4.data.scene import Camera
    from omg4.render import TimeSlice, render_view

    sc = random_scene(13, 40, 24, 18)

    class Model:
        def slice_at(self, timestamp, camera_center):
            return TimeSlice(means=sc.means.float(), covars=sc.covars.float(), colors=sc.colors.float(),
                             opacities=sc.opacities.float(), index=torch.arange(40), num_total=40)

    camera = Camera(K=sc.K.numpy(), viewmat=sc.viewmat.numpy(), width=24, height=18, name="cam")
    rendered, sl = render_view(Model(), camera, 0.5, background=sc.background.float())
    direct = rasterize(sc.means.float(), sc.covars.float(), sc.colors.float(), sc.opacities.float(),
                       sc.viewmat.float(), sc.K.float(), 24, 18, background=sc.background.float())
    assert sl.num_total == 40 and rendered.image.shape == (18, 24, 3)
    assert torch.equal(rendered.image, direct.image) and rendered.alpha.max() > 0.3


def _box_values(start):
    """Walk the kernels' recurrence from :func:`_box_exp`'s start values over a 64×64 box (rows of pixels)."""
    e_row, s_row, s_step, r_row, r_step, step, _ = start
    out = []
    for _ in range(64):
        e, r = e_row, r_row
        e_row, s_row, r_row = e_row * s_row, s_row * s_step, r_row * r_step
        row = []
        for _ in range(64):
            row.append(e)
            e, r = e * r, r * step
        out.append(row)
    return out


def test_box_exp_recurrence_matches_exp_and_falls_back_beyond_its_range():
    """e^{−σ} over a pixel box by the kernels' recurrence equals exp(−σ) per pixel (float64, 64×64 boxes); boxes
    whose σ exceeds 600 at a corner, or conics that are not positive definite, are refused (the kernels then
    call exp per pixel)."""
    import math

    from omg4.render.cpu_kernels import _box_exp

    g = torch.Generator().manual_seed(3)
    worst, used = 0.0, 0
    for _ in range(120):
        a, c = (10 ** (torch.rand(2, generator=g, dtype=torch.float64) * 4 - 4)).tolist()  # 1e-4 … 1
        b = float((torch.rand(1, generator=g, dtype=torch.float64) * 2 - 1) * math.sqrt(a * c))  # positive definite
        dx0, dy0 = (torch.rand(2, generator=g, dtype=torch.float64) * 80 - 40).tolist()
        start = _box_exp(a, b, c, dx0, dx0 - 63, dy0, dy0 - 63)

        def sigma(i, j):
            x, y = dx0 - i, dy0 - j
            return 0.5 * (a * x * x + c * y * y) + b * x * y
        if max(sigma(i, j) for i in (0, 63) for j in (0, 63)) > 600:
            assert not start[-1]
            continue
        assert start[-1]
        used += 1
        for j, row in enumerate(_box_values(start)):
            for i, e in enumerate(row):
                worst = max(worst, abs(e - math.exp(-sigma(i, j))) / math.exp(-sigma(i, j)))
    assert used > 30 and worst < 1e-11, (used, worst)  # the error grows with the square of the box side
    assert not _box_exp(0.0, 0.0, 1.0, 3.0, 0.0, 1.0, 0.0)[-1]  # a = 0
    assert not _box_exp(-0.5, 0.0, 1.0, 3.0, 0.0, 1.0, 0.0)[-1]  # a < 0
    assert not _box_exp(100.0, 0.0, -200.0, 7.5, -7.5, 5.0, 5.0)[-1]  # a > 0, c < 0
    assert not _box_exp(1.0, 2.0, 1.0, 1.0, -1.0, 0.5, -0.5)[-1]  # b² > a·c
    assert not _box_exp(1.0, 0.0, 1.0, 40.0, 0.0, 0.0, 0.0)[-1]  # σ = 800 at a corner
    assert _box_exp(1.0, 0.0, 1.0, 30.0, 0.0, 0.0, 0.0)[-1]  # σ ≤ 450


def test_no_views_and_an_alpha_limit_at_the_threshold_are_refused():
    from omg4.render.api import rasterize_views
    from omg4.render.projection import ALPHA_THRESHOLD

    t = random_scene(15, 10, 16, 12).tensors(torch.float32, requires_grad=False)
    views = torch.zeros(10, dtype=torch.int64)
    with pytest.raises(ValueError, match=r"viewmats must be \[V, 4, 4\]"):
        rasterize_views(t["means"], t["covars"], t["colors"], t["opacities"], views, torch.zeros(0, 4, 4),
                        torch.zeros(0, 3, 3), 16, 12)
    with pytest.raises(ValueError, match="alpha_max must lie in"):
        rasterize(**t, alpha_max=ALPHA_THRESHOLD)  # the interval (1/255, 1) is open at both ends
    assert float(rasterize(**t, alpha_max=2 * ALPHA_THRESHOLD).alpha.max()) > 0
