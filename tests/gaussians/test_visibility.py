"""The per-time-window visibility index never drops a Gaussian that passes the temporal cull."""

from __future__ import annotations

import pytest
import torch

from omg4.gaussians.covariance import scaled_rotation_4d, slice_geometry, temporal_variance
from omg4.gaussians.visibility import VisibilityIndex


def _gaussians(seed, n=3000, t_range=(0.0, 10.0)):
    g = torch.Generator().manual_seed(seed)
    t0, t1 = t_range
    return {
        "xyz": torch.randn(n, 3, generator=g),
        "t": (t0 - 2 + (t1 - t0 + 4) * torch.rand(n, 1, generator=g)),
        # time scales from a twentieth of a frame-ish to the whole clip
        "scales": torch.exp(torch.randn(n, 4, generator=g) * torch.tensor([0.5, 0.5, 0.5, 1.5]) - 1.0),
        "q_l": torch.randn(n, 4, generator=g),
        "q_r": torch.randn(n, 4, generator=g),
    }


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_index_keeps_every_gaussian_that_passes_the_cull(seed):
    p = _gaussians(seed)
    var_t = temporal_variance(scaled_rotation_4d(p["scales"], p["q_l"], p["q_r"], "flip"))
    index = VisibilityIndex.build(p["t"][:, 0], var_t, (0.0, 10.0), time_cull=0.05, windows=16)
    times = torch.cat([torch.rand(200, generator=torch.Generator().manual_seed(seed)) * 10.0,
                       index.edges])  # random times and every window edge
    sizes = []
    for tau in times.tolist():
        rows = index.rows_at(torch.tensor([tau], dtype=torch.float64))
        geom = slice_geometry(p["xyz"], p["t"], p["scales"], p["q_l"], p["q_r"], tau, time_cull=0.05)
        missing = set(geom.index.tolist()) - set(rows.tolist())
        assert not missing, f"time {tau}: {len(missing)} Gaussians passing the cull are not in the window"
        sizes.append(rows.numel())
    assert max(sizes) < 0.8 * p["t"].shape[0]  # the index does prune: it is not every Gaussian


def test_several_times_get_the_union_and_times_outside_get_none():
    p = _gaussians(3, n=500)
    var_t = temporal_variance(scaled_rotation_4d(p["scales"], p["q_l"], p["q_r"], "flip"))
    index = VisibilityIndex.build(p["t"][:, 0], var_t, (0.0, 10.0), time_cull=0.05, windows=8)
    a, b = (index.rows_at(torch.tensor([x], dtype=torch.float64)) for x in (0.5, 9.5))
    both = index.rows_at(torch.tensor([0.5, 9.5], dtype=torch.float64))
    assert both.tolist() == sorted(set(a.tolist()) | set(b.tolist()))
    assert index.rows_at(torch.tensor([10.5], dtype=torch.float64)) is None
    assert index.rows_at(torch.tensor([-0.1], dtype=torch.float64)) is None


def test_windowed_baseline_renders_the_frames_of_the_plain_model():
    """A checkpoint loaded for rendering (window rows gathered first) shows exactly the plain model's slices."""
    from omg4.gaussians import GaussianConfig, Gaussians4D
    from omg4.models.windowed import WindowedModel

    p = _gaussians(4, n=800)
    g = torch.Generator().manual_seed(4)
    cfg = GaussianConfig(time_range=(0.0, 10.0))
    params = {"xyz": p["xyz"], "t": p["t"], "scaling": p["scales"][:, :3].log(), "scaling_t": p["scales"][:, 3:].log(),
              "rotation": p["q_l"], "rotation_r": p["q_r"], "opacity": torch.randn(800, 1, generator=g),
              "features_dc": torch.randn(800, 1, 3, generator=g), "features_rest": torch.randn(800, 47, 3, generator=g)}
    plain = Gaussians4D(params, cfg, 3, 2)
    windowed = WindowedModel(plain.params, cfg, 3, 2, windows=16)
    center = torch.tensor([0.5, -0.2, -4.0])
    for tau in (0.0, 0.31, 3.7, 6.25, 9.99, 10.0, 12.0):
        a, b = plain.slice_at(tau, center), windowed.slice_at(tau, center)
        assert a.index.tolist() == b.index.tolist()
        for name in ("means", "covars", "colors", "opacities"):
            torch.testing.assert_close(getattr(b, name), getattr(a, name), rtol=1e-6, atol=1e-6)


def _mlp_model(monkeypatch=None, limit=None):
    from omg4.gaussians import GaussianConfig
    from omg4.gaussians.appearance import AppearanceMLP
    from omg4.models import windowed
    from omg4.models.windowed import WindowedModel

    if limit is not None:
        monkeypatch.setattr(windowed, "MAX_CACHED_TERMS", limit)
    p = _gaussians(5, n=600)
    g = torch.Generator().manual_seed(5)
    values = {"xyz": p["xyz"], "t": p["t"], "scaling": p["scales"][:, :3].log(), "scaling_t": p["scales"][:, 3:].log(),
              "rotation": p["q_l"], "rotation_r": p["q_r"], "f_static": torch.randn(600, 3, generator=g),
              "f_view": torch.randn(600, 3, generator=g)}
    torch.manual_seed(5)
    return WindowedModel(values, GaussianConfig(time_range=(0.0, 10.0)), 3, 2, appearance=AppearanceMLP().eval(),
                         windows=16)


def test_cached_position_term_renders_the_frames_of_the_uncached_model(monkeypatch):
    """The MLPs' position part cached at load = computed per frame (and a model above the cache budget has none)."""
    cached, uncached = _mlp_model(), _mlp_model(monkeypatch, limit=100)
    assert cached.position_term is not None and cached.position_term.shape == (600, 64)
    assert uncached.position_term is None
    centers = torch.tensor([[0.5, -0.2, -4.0], [1.0, 0.3, -3.5]])
    for times in ([0.31], [6.25, 9.0], [12.0]):  # one view, two views, a time outside the range
        ts = torch.tensor(times, dtype=torch.float64)
        a, b = (m.slice_views(ts, centers[: len(times)]) for m in (cached, uncached))
        assert a.index.tolist() == b.index.tolist() and a.index.numel() > 0
        torch.testing.assert_close(a.colors, b.colors, rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(a.opacities, b.opacities, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("seed", [6, 7])
def test_culling_window_rows_gives_the_whole_sets_geometry(seed):
    """condition_and_cull over a window's candidate rows = over every Gaussian, bit for bit, for 1 and 3 views."""
    from omg4.gaussians.covariance import condition_and_cull, conditioning_terms

    p = _gaussians(seed, n=2000)
    gain, cov3, var_t = conditioning_terms(p["scales"], p["q_l"], p["q_r"], "flip")
    index = VisibilityIndex.build(p["t"][:, 0], var_t, (0.0, 10.0), time_cull=0.05, windows=16)
    g = torch.Generator().manual_seed(seed)
    for times in ([float(x) for x in torch.rand(3, generator=g) * 10], [2.5], [0.0], [10.0]):
        ts = torch.tensor(times, dtype=torch.float64)
        rows = index.rows_at(ts)
        assert rows.numel() < 2000
        whole = condition_and_cull(p["xyz"], p["t"], gain, cov3, var_t, ts.float(), time_cull=0.05)
        window = condition_and_cull(p["xyz"], p["t"], gain, cov3, var_t, ts.float(), time_cull=0.05, rows=rows)
        assert whole.index.numel() > 50
        assert torch.equal(window.index, whole.index) and torch.equal(window.views, whole.views)
        for name in ("means", "covars", "marginal", "dt"):
            assert torch.equal(getattr(window, name), getattr(whole, name)), name


def test_only_the_candidate_rows_can_pass():
    """Rows left out of the candidates never appear; the others keep the whole set's values."""
    from omg4.gaussians.covariance import condition_and_cull, conditioning_terms

    p = _gaussians(8, n=1000)
    terms = conditioning_terms(p["scales"], p["q_l"], p["q_r"], "flip")
    ts = torch.tensor([4.0, 6.5])
    whole = condition_and_cull(p["xyz"], p["t"], *terms, ts)
    rows = torch.arange(0, 1000, 3)
    part = condition_and_cull(p["xyz"], p["t"], *terms, ts, rows=rows)
    kept = (whole.index % 3) == 0
    assert 0 < int(kept.sum()) < whole.index.numel()
    assert torch.equal(part.index, whole.index[kept]) and torch.equal(part.views, whole.views[kept])
    assert torch.equal(part.means, whole.means[kept]) and torch.equal(part.marginal, whole.marginal[kept])


def test_windowed_freetimegs_renders_the_frames_of_the_plain_model():
    """A FreeTimeGS checkpoint loaded for rendering (motion computed at load) shows the plain model's slices."""
    from omg4.gaussians import GaussianConfig, Gaussians4D
    from omg4.models.windowed import WindowedModel

    g = torch.Generator().manual_seed(9)
    n = 700
    params = {"xyz": torch.randn(n, 3, generator=g), "t": torch.rand(n, 1, generator=g) * 2.0,
              "duration": torch.randn(n, 1, generator=g) * 0.8 - 1.5, "velocity": torch.randn(n, 3, generator=g) * 0.5,
              "scaling": torch.randn(n, 3, generator=g) * 0.3 - 1.5, "rotation": torch.randn(n, 4, generator=g),
              "opacity": torch.randn(n, 1, generator=g), "features_dc": torch.randn(n, 1, 3, generator=g),
              "features_rest": torch.randn(n, 15, 3, generator=g)}
    cfg = GaussianConfig(time_range=(0.0, 2.0), sh_degree_t=0, backbone="freetimegs")
    plain = Gaussians4D(params, cfg, 3, 0)
    windowed = WindowedModel(plain.params, cfg, 3, 0, windows=16)
    centers = torch.tensor([[0.5, -0.2, -4.0], [-1.0, 0.4, -3.0]])
    for times in ([0.0], [0.37], [1.25, 1.9], [2.0]):
        ts = torch.tensor(times, dtype=torch.float64)
        a, b = plain.slice_views(ts, centers[: len(times)]), windowed.slice_views(ts, centers[: len(times)])
        assert a.index.tolist() == b.index.tolist() and 0 < a.index.numel() < n
        assert a.views.tolist() == b.views.tolist()
        for name in ("means", "covars", "colors", "opacities"):
            torch.testing.assert_close(getattr(b, name), getattr(a, name), rtol=1e-6, atol=1e-6)


def test_windowed_mlp_model_renders_the_frames_of_the_plain_values():
    """A decoded model (MLP appearance, terms cached at load) = the same values sliced with no window and no cache."""
    from omg4.gaussians.model import slice_values

    model = _mlp_model()
    centers = torch.tensor([[0.5, -0.2, -4.0], [1.0, 0.3, -3.5]])
    for times in ([0.31], [6.25, 9.0], [10.0]):
        ts = torch.tensor(times, dtype=torch.float64)
        with torch.no_grad():
            a = slice_values(model.values, model.config, 3, 2, ts, centers[: len(times)], appearance=model.appearance)
        b = model.slice_views(ts, centers[: len(times)])
        assert a.index.tolist() == b.index.tolist() and 0 < a.index.numel() < model.num_gaussians
        for name in ("means", "covars", "colors", "opacities"):
            torch.testing.assert_close(getattr(b, name), getattr(a, name), rtol=1e-5, atol=1e-6)
