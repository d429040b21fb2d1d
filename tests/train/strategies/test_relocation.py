"""FreeTimeGS relocation: the budget stays exact and only low-opacity Gaussians move."""

import math

import torch

from omg4.gaussians import GaussianConfig, Gaussians4D, build_rotation_3d
from omg4.train.strategies.densification import DensifyStats
from omg4.optimize.parameters import make_adam
from omg4.train.strategies.relocation import relocate


def _model(n: int, dead: list[int]) -> Gaussians4D:
    g = torch.Generator().manual_seed(0)
    params = {"xyz": torch.randn(n, 3, generator=g), "t": torch.rand(n, 1, generator=g),
              "duration": torch.zeros(n, 1), "velocity": torch.randn(n, 3, generator=g),
              "scaling": torch.full((n, 3), -2.0), "rotation": torch.randn(n, 4, generator=g),
              "opacity": torch.full((n, 1), 1.0), "features_dc": torch.randn(n, 1, 3, generator=g),
              "features_rest": torch.zeros(n, 15, 3)}
    params["opacity"][dead] = -8.0  # sigmoid ≈ 3e-4 < 0.005
    config = GaussianConfig(time_range=(0.0, 1.0), sh_degree_t=0, backbone="freetimegs")
    return Gaussians4D({k: v.requires_grad_(True) for k, v in params.items()}, config)


def test_relocation_keeps_the_budget_and_moves_only_dead_gaussians():
    n, dead = 50, [3, 7, 20, 41]
    model = _model(n, dead)
    optimizer = make_adam(model.params, {k: 1e-3 for k in model.params})
    loss = sum(v.square().sum() for v in model.params.values())
    loss.backward()
    optimizer.step()  # moments exist
    before = {k: v.detach().clone() for k, v in model.params.items()}
    stats = DensifyStats(n)
    stats.grad_sum[10] = 5.0  # a high-gradient Gaussian is a likely target
    stats.visible_views[:] = 1.0
    moved = relocate(model, optimizer, stats, min_opacity=0.005, generator=torch.Generator().manual_seed(1))
    assert moved == len(dead)
    assert model.num_gaussians == n and all(v.shape[0] == n for v in model.params.values())
    after = {k: v.detach() for k, v in model.params.items()}
    changed = {i for k in after for i in (after[k] != before[k]).reshape(n, -1).any(1).nonzero().squeeze(1).tolist()}
    assert set(dead) <= changed
    targets = changed - set(dead)
    assert targets
    shrink = math.log(1.6)  # a relocation splits its target: both halves shrink like a Real-Time4DGS split
    for i in targets:  # live rows change only in opacity (shared with their copies) and scale
        assert all(torch.equal(after[k][i], before[k][i]) for k in after if k not in ("opacity", "scaling"))
        torch.testing.assert_close(after["scaling"][i], before["scaling"][i] - shrink)
    for i in dead:  # each moved row copies a live Gaussian, placed inside that Gaussian's own footprint
        same = ("duration", "velocity", "rotation", "features_dc", "features_rest")
        sources = [j for j in targets if all(torch.equal(after[k][i], before[k][j]) for k in same)]
        assert len(sources) == 1
        j = sources[0]
        torch.testing.assert_close(after["scaling"][i], before["scaling"][j] - shrink)
        assert 0.0 <= float(after["t"][i]) <= 1.0  # inside the clip
        eps_t = (after["t"][i] - before["t"][j]) / before["duration"][j].exp()
        # on the target's trajectory at the copy's time, plus a draw from the target's spatial footprint
        on_path = before["xyz"][j] + before["velocity"][j] * (after["t"][i] - before["t"][j])
        R = build_rotation_3d(before["rotation"][j:j + 1])[0]
        eps = (R.T @ (after["xyz"][i] - on_path)) / before["scaling"][j].exp()
        assert 0 < float(eps.norm()) < 6 and 0 < float(eps_t.abs()) < 6
    # the k + 1 copies keep the target's peak opacity where they overlap: 1 − Π(1 − σ') = σ
    sigma = torch.sigmoid(before["opacity"][:, 0])
    for j in targets:
        copies = [i for i in dead if torch.equal(after["features_dc"][i], before["features_dc"][j])] + [j]
        combined = 1 - math.prod(1 - float(torch.sigmoid(after["opacity"][i, 0])) for i in copies)
        assert abs(combined - float(sigma[j])) < 1e-5
    # moved rows and targets restart their Adam moments; the others keep them
    state = optimizer.state[model.params["xyz"]]
    for i in range(n):
        zero = bool((state["exp_avg"][i] == 0).all())
        assert zero == (i in changed)


def test_copies_of_long_lived_gaussians_stay_in_the_clip():
    n, dead = 40, list(range(0, 40, 2))
    model = _model(n, dead)
    with torch.no_grad():
        model.params["duration"][:] = 12.0  # s = e^12: practically static, centre anywhere
    relocate(model, None, DensifyStats(n), min_opacity=0.005, generator=torch.Generator().manual_seed(2))
    t = model.params["t"].detach()[dead]
    assert float(t.min()) >= 0.0 and float(t.max()) <= 1.0 and float(t.std()) > 0.1


def test_nothing_moves_without_dead_gaussians():
    model = _model(20, [])
    before = {k: v.detach().clone() for k, v in model.params.items()}
    moved = relocate(model, None, DensifyStats(20), min_opacity=0.005, generator=torch.Generator().manual_seed(0))
    assert moved == 0
    assert all(torch.equal(before[k], model.params[k].detach()) for k in before)


def _two_live(n_dead: int, opacity_a: float, opacity_b: float):
    """Rows 0 and 1 alive (opacities given), the rest dead; row 0 carries the largest view gradient."""
    model = _model(n_dead + 2, list(range(2, n_dead + 2)))
    with torch.no_grad():
        model.params["opacity"][0, 0] = math.log(opacity_a / (1 - opacity_a))
        model.params["opacity"][1, 0] = math.log(opacity_b / (1 - opacity_b))
    stats = DensifyStats(n_dead + 2)
    stats.grad_sum[0] = 3.0
    stats.visible_views[:] = 1.0
    return model, stats


def test_targets_are_drawn_in_proportion_to_half_gradient_plus_half_opacity():
    n_dead = 4000
    model, stats = _two_live(n_dead, 0.5, 0.9)
    dc = model.params["features_dc"].detach().clone()
    relocate(model, None, stats, min_opacity=0.005, generator=torch.Generator().manual_seed(3))
    copies_of_a = int((model.params["features_dc"].detach()[2:] == dc[0]).all(-1).all(-1).sum())
    # score: 0.5 · ĝ + 0.5 · σ, ĝ normalized to its maximum → A: 0.5 + 0.25, B: 0 + 0.45
    p_a = 0.75 / (0.75 + 0.45)
    assert abs(copies_of_a / n_dead - p_a) < 0.03  # 3.4 standard deviations of 4000 draws


def test_a_gaussian_exactly_at_the_opacity_threshold_is_alive():
    model = _model(4, [])
    with torch.no_grad():
        model.params["opacity"][:, 0] = torch.tensor([0.0, -1e-6, 1e-6, 0.0])  # sigmoid(0) is exactly 0.5
    assert relocate(model, None, DensifyStats(4), min_opacity=0.5, generator=torch.Generator().manual_seed(0)) == 1


def test_copies_are_spread_by_the_targets_scale_rotation_and_duration():
    n_dead = 3000
    model, stats = _two_live(n_dead, 0.99, 0.01 + 1e-3)
    scales, duration = torch.tensor([0.2, 0.02, 0.05]), 0.05
    with torch.no_grad():
        model.params["scaling"][0] = scales.log()
        model.params["rotation"][0] = torch.tensor([1.0, 0.0, 0.0, 0.0])
        model.params["duration"][0] = math.log(duration)
        model.params["t"][0] = 0.5
        model.params["opacity"][1, 0] = -20.0  # row 1 dies too: every copy comes from row 0
    before = {k: v.detach().clone() for k, v in model.params.items()}
    relocate(model, None, stats, min_opacity=0.005, generator=torch.Generator().manual_seed(4))
    after = {k: v.detach() for k, v in model.params.items()}
    moved = torch.arange(1, n_dead + 2)
    dt = after["t"][moved, 0] - 0.5
    assert abs(float(dt.std()) / duration - 1) < 0.06 and abs(float(dt.mean())) < 0.005
    spatial = after["xyz"][moved] - before["xyz"][0] - before["velocity"][0] * dt[:, None]
    ratio = spatial.std(0) / scales
    assert float((ratio - 1).abs().max()) < 0.06, ratio
    assert bool((spatial.mean(0).abs() < 4 * scales / math.sqrt(n_dead)).all())  # centred on the trajectory
    torch.testing.assert_close(after["scaling"][moved], (scales.log() - math.log(1.6)).expand(n_dead + 1, 3))


def test_the_freetimegs_regularizer_weighs_in_until_densification_ends():
    from omg4.gaussians.freetime import opacity_regularizer
    from omg4.train import make_config
    from omg4.train.strategies.relocation import Relocation

    model = _model(10, [])
    cfg = make_config("cpu-small", backbone="freetimegs", densify_until=100, lambda_reg=0.25)
    times = torch.tensor([0.2, 0.7], dtype=torch.float64)
    p = model.params
    expected = 0.25 * opacity_regularizer(p["opacity"], p["t"], p["duration"], times)
    assert type(cfg.strategy) is Relocation
    torch.testing.assert_close(cfg.strategy.regularizer(p, times, 99), expected)
    assert cfg.strategy.regularizer(p, times, 100) is None
    assert cfg.with_strategy(lambda_reg=0.0).strategy.regularizer(p, times, 5) is None
