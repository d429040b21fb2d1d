"""FreeTimeGS relocation: the budget stays exact and only low-opacity Gaussians move."""

import math

import torch

from omg4.gaussians import GaussianConfig, Gaussians4D, build_rotation_3d
from omg4.train.densify import DensifyStats
from omg4.train.optim import make_adam
from omg4.train.relocate import relocate


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
