"""Real-Time4DGS density control, decision by decision (rt4dgs §3.4): hand-built Gaussians whose fate is known.

Each Gaussian is placed on one side of a threshold (size, gradient, opacity, screen radius, world size)
and the test states, from the rule written out here, what must become of it: kept as it was, cloned
(an exact copy appended), split (two children drawn from its 4D Gaussian replace it) or pruned.
"""

from __future__ import annotations

import math

import pytest
import torch

from omg4.gaussians import GaussianConfig, Gaussians4D, build_rotation_4d
from omg4.train.strategies import densification as densify
from omg4.train.strategies.densification import DensifyStats, densify_and_prune, reset_opacity
from omg4.optimize.parameters import make_adam

GRAD_THRESHOLD = 2.0 ** -12  # exactly representable in float32, so "at the threshold" is exact
EXTENT = 2.0
PERCENT_DENSE = 0.01  # size threshold: max scale ≤ 0.02 is small
PRUNE_OPACITY = 0.005


def _logit(p: float) -> float:
    return math.log(p / (1 - p))


def make_model(rows: list[dict]) -> Gaussians4D:
    """One Real-Time4DGS Gaussian per row: ``scale`` (x, y, z), ``scale_t``, ``opacity``, position ``xyz``, ``t``,
    quaternions ``q_l`` / ``q_r``; every other value distinct per row so that copies can be told apart."""
    n = len(rows)
    params = {
        "xyz": torch.tensor([r.get("xyz", (0.1 * i, -0.2 * i, 0.3)) for i, r in enumerate(rows)]),
        "t": torch.tensor([[r.get("t", 0.5)] for r in rows]),
        "scaling": torch.tensor([[math.log(s) for s in r["scale"]] for r in rows]),
        "scaling_t": torch.tensor([[math.log(r.get("scale_t", 0.1))] for r in rows]),
        "rotation": torch.tensor([r.get("q_l", (1.0, 0.0, 0.0, 0.0)) for r in rows]),
        "rotation_r": torch.tensor([r.get("q_r", (1.0, 0.0, 0.0, 0.0)) for r in rows]),
        "opacity": torch.tensor([[_logit(r.get("opacity", 0.5))] for r in rows]),
        "features_dc": torch.arange(n * 3, dtype=torch.float32).reshape(n, 1, 3),
        "features_rest": torch.arange(n * 47 * 3, dtype=torch.float32).reshape(n, 47, 3) / 100,
    }
    return Gaussians4D({k: v.requires_grad_(True) for k, v in params.items()}, GaussianConfig(time_range=(0.0, 1.0)))


def stats_with(grads: list[float], radii: list[float] | None = None) -> DensifyStats:
    """Statistics whose mean gradient is ``grads`` (each seen in one view) and max radii ``radii``."""
    stats = DensifyStats(len(grads))
    stats.grad_sum = torch.tensor(grads, dtype=torch.float32)
    stats.visible_views = torch.ones(len(grads))
    if radii is not None:
        stats.max_radii = torch.tensor(radii, dtype=torch.float32)
    return stats


def run(model, stats, *, max_screen_size=None, prune_world_size=0.1, max_gaussians=0, seed=0):
    optimizer = make_adam(model.params, {k: 1e-3 for k in model.params})
    before = {k: v.detach().clone() for k, v in model.params.items()}
    counts = densify_and_prune(model, optimizer, stats, grad_threshold=GRAD_THRESHOLD, percent_dense=PERCENT_DENSE,
                               extent=EXTENT, prune_opacity=PRUNE_OPACITY, max_screen_size=max_screen_size,
                               prune_world_size=prune_world_size, max_gaussians=max_gaussians,
                               generator=torch.Generator().manual_seed(seed))
    return before, {k: v.detach() for k, v in model.params.items()}, counts, optimizer


def expected_children(before: dict, parents: list[int], seed: int) -> dict[str, torch.Tensor]:
    """The rule of a 4D split: two children per parent (all first children, then all second children),
    (xyz, t) = μ + R4 · (s ⊙ ε) with ε ~ N(0, I) drawn as one [2K, 4] normal from the seeded generator, the
    spatial and temporal log-scales shrunk by log(0.8 · 2), every other value the parent's."""
    idx = torch.tensor(parents + parents)
    eps = torch.randn(len(idx), 4, generator=torch.Generator().manual_seed(seed))
    scales = torch.cat([before["scaling"][idx], before["scaling_t"][idx]], 1).exp()
    rot = build_rotation_4d(before["rotation"][idx], before["rotation_r"][idx])
    offset = (rot @ (scales * eps)[:, :, None])[:, :, 0]
    out = {k: v[idx].clone() for k, v in before.items()}
    out["xyz"] = out["xyz"] + offset[:, :3]
    out["t"] = out["t"] + offset[:, 3:]
    out["scaling"] = out["scaling"] - math.log(1.6)
    out["scaling_t"] = out["scaling_t"] - math.log(1.6)
    return out


def rows_of(values: dict, idx: list[int]) -> dict[str, torch.Tensor]:
    return {k: v[idx] for k, v in values.items()}


def assert_rows_equal(actual: dict, expected: dict, atol: float = 0.0) -> None:
    for k in expected:
        torch.testing.assert_close(actual[k], expected[k], atol=atol, rtol=0, msg=k)


def test_each_gaussian_is_kept_cloned_split_or_pruned_by_the_rule():
    small, large = 0.9 * PERCENT_DENSE * EXTENT, 1.1 * PERCENT_DENSE * EXTENT
    rows = [
        dict(scale=(small, 0.001, 0.001)),                       # 0 small, gradient exactly at the threshold: clone
        dict(scale=(0.001, large, 0.001)),                       # 1 large (y), gradient above: split
        dict(scale=(small, small, small)),                       # 2 small, gradient just below: kept as is
        dict(scale=(0.001, 0.001, large), opacity=0.5),          # 3 large, gradient below: kept as is
        dict(scale=(small, 0.001, 0.001), opacity=0.004),        # 4 transparent, no gradient: pruned
        dict(scale=(0.001, 0.001, large), q_l=(0.8, 0.2, -0.4, 0.4), q_r=(0.6, 0.0, 0.8, 0.0),
             scale_t=0.3),                                       # 5 large, rotated in 4D, gradient far above: split
        dict(scale=(small, 0.001, 0.001), opacity=0.004),        # 6 transparent but densified: its clone is pruned too
        dict(scale=(0.001, PERCENT_DENSE * EXTENT, 0.001)),      # 7 exactly at the size threshold: small, cloned
    ]
    assert torch.exp(torch.tensor(math.log(PERCENT_DENSE * EXTENT))) == PERCENT_DENSE * EXTENT  # exact in float32
    model = make_model(rows)
    below = float(torch.tensor(GRAD_THRESHOLD).nextafter(torch.tensor(0.0)))
    before, after, counts, _ = run(model, stats_with([GRAD_THRESHOLD, 2 * GRAD_THRESHOLD, below, below, 0.0,
                                                      100 * GRAD_THRESHOLD, GRAD_THRESHOLD, GRAD_THRESHOLD]))
    assert counts == {"cloned": 3, "split": 2, "pruned": 2 + 2 + 1}  # two parents, two transparent rows, a clone
    # order: survivors of the original rows, then surviving clones, then the children
    kept, clones = [0, 2, 3, 7], [0, 7]
    n_kept = len(kept) + len(clones)
    assert after["xyz"].shape[0] == n_kept + 4
    assert_rows_equal(rows_of(after, list(range(len(kept)))), rows_of(before, kept))
    assert_rows_equal(rows_of(after, list(range(len(kept), n_kept))), rows_of(before, clones))
    children = rows_of(after, list(range(n_kept, n_kept + 4)))
    assert_rows_equal(children, expected_children(before, [1, 5], seed=0), atol=1e-6)


def test_children_are_spread_by_the_parents_scale_not_the_unit_gaussian():
    rows = [dict(scale=(0.5, 0.05, 0.05), scale_t=0.02, xyz=(1.0, 2.0, 3.0))] * 400
    before, after, counts, _ = run(make_model(rows), stats_with([1.0] * 400))
    assert counts["split"] == 400 and after["xyz"].shape[0] == 800
    offset = after["xyz"] - before["xyz"][:1]
    std = offset.std(0)
    # axis-aligned parent: offsets ~ N(0, s²) per axis
    assert 0.4 < float(std[0]) < 0.6 and 0.04 < float(std[1]) < 0.06 and 0.04 < float(std[2]) < 0.06
    assert 0.016 < float((after["t"] - before["t"][:1]).std()) < 0.024


def test_growth_stops_at_the_cap_with_the_largest_gradients_first():
    rows = [dict(scale=(0.001,) * 3)] * 2 + [dict(scale=(1.0, 0.001, 0.001))] * 2
    grads = [5.0, 1.0, 4.0, 3.0]  # all candidates: clone 0, 1; split 2, 3
    before, after, counts, _ = run(make_model(rows), stats_with(grads), max_gaussians=6)
    # budget 6 − 4 = 2: the two largest gradients, rows 0 (clone) and 2 (split)
    assert counts == {"cloned": 1, "split": 1, "pruned": 1}
    assert after["xyz"].shape[0] == 4 - 1 + 1 + 2
    assert_rows_equal(rows_of(after, [0, 1, 2, 3]), rows_of(before, [0, 1, 3, 0]))


def test_an_unbounded_run_may_grow_by_every_candidate():
    rows = [dict(scale=(0.001,) * 3)] * 5
    _, after, counts, _ = run(make_model(rows), stats_with([1.0] * 5), max_gaussians=0)
    assert counts["cloned"] == 5 and after["xyz"].shape[0] == 10


def test_screen_and_world_size_prune_only_when_a_screen_limit_is_given():
    world = 0.1 * EXTENT
    rows = [dict(scale=(0.001,) * 3),                 # 0 radius above the limit
            dict(scale=(0.001,) * 3),                 # 1 radius exactly at the limit: kept (strictly larger goes)
            dict(scale=(1.01 * world, 0.001, 0.001)),  # 2 larger than the world limit
            dict(scale=(0.99 * world, 0.001, 0.001))]  # 3 just inside it
    radii = [21.0, 20.0, 1.0, 1.0]
    _, after, counts, _ = run(make_model(rows), stats_with([0.0] * 4, radii), max_screen_size=20.0)
    assert counts["pruned"] == 2 and after["xyz"].shape[0] == 2
    torch.testing.assert_close(after["features_dc"], make_model(rows).params["features_dc"].detach()[[1, 3]])
    _, after, counts, _ = run(make_model(rows), stats_with([0.0] * 4, radii), max_screen_size=None)
    assert counts["pruned"] == 0 and after["xyz"].shape[0] == 4


def test_opacity_pruning_is_strictly_below_the_threshold():
    rows = [dict(scale=(0.001,) * 3, opacity=0.5)] * 3
    model = make_model(rows)
    with torch.no_grad():  # sigmoid(0) is exactly 0.5: at, just below and just above a threshold of 0.5
        model.params["opacity"][:, 0] = torch.tensor([0.0, -1e-6, 1e-6])
    assert torch.sigmoid(model.params["opacity"].detach()[0, 0]) == 0.5
    before = {k: v.detach().clone() for k, v in model.params.items()}
    optimizer = make_adam(model.params, {k: 1e-3 for k in model.params})
    counts = densify_and_prune(model, optimizer, stats_with([0.0] * 3), grad_threshold=GRAD_THRESHOLD,
                               percent_dense=PERCENT_DENSE, extent=EXTENT, prune_opacity=0.5, max_screen_size=None,
                               prune_world_size=0.1, max_gaussians=0, generator=torch.Generator().manual_seed(0))
    assert counts["pruned"] == 1
    assert_rows_equal({k: v.detach() for k, v in model.params.items()}, rows_of(before, [0, 2]))


def test_a_scene_is_never_pruned_to_nothing():
    rows = [dict(scale=(0.001,) * 3, opacity=p) for p in (0.001, 0.003, 0.002)]
    before, after, counts, _ = run(make_model(rows), stats_with([0.0] * 3))
    assert counts["pruned"] == 2
    assert_rows_equal(after, rows_of(before, [1]))  # the most opaque one stays


def test_statistics_restart_after_an_event_and_moments_follow_the_rows():
    rows = [dict(scale=(0.001,) * 3), dict(scale=(1.0, 0.001, 0.001)), dict(scale=(0.001,) * 3)]
    model = make_model(rows)
    optimizer = make_adam(model.params, {k: 1e-3 for k in model.params})
    sum(v.square().sum() for v in model.params.values()).backward()
    optimizer.step()
    moments = {k: optimizer.state[v]["exp_avg"].clone() for k, v in model.params.items()}
    stats = stats_with([1.0, 1.0, 0.0])
    densify_and_prune(model, optimizer, stats, grad_threshold=0.5, percent_dense=PERCENT_DENSE, extent=EXTENT,
                      prune_opacity=0.0, max_screen_size=None, prune_world_size=0.1, max_gaussians=0,
                      generator=torch.Generator().manual_seed(0))
    n = model.num_gaussians
    assert n == 3 - 1 + 1 + 2
    assert all(float(getattr(stats, f).abs().sum()) == 0 and getattr(stats, f).shape == (n,)
               for f in ("grad_sum", "visible_views", "max_radii"))
    for k, v in model.params.items():
        m = optimizer.state[v]["exp_avg"]
        assert m.shape == v.shape
        torch.testing.assert_close(m[:2], moments[k][[0, 2]])  # kept rows keep their moments
        assert float(m[2:].abs().sum()) == 0  # a clone and children start from zero


def test_view_statistics_are_ndc_gradients_of_visible_gaussians():
    stats = DensifyStats(4)
    index = torch.tensor([0, 1, 2, 0])
    grad = torch.tensor([[3.0, 4.0], [1.0, 1.0], [6.0, 8.0], [0.0, 2.0]])
    radii = torch.tensor([5, 0, 7, 9])  # row 1 is not visible in its view
    stats.add_view(index, grad, radii, width=100, height=50, batch_size=2)
    # pixel gradient × (W/2, H/2) × B: (3·50, 4·25)·2 = (300, 200); (0, 2·25)·2 = (0, 100)
    expected_sum = torch.tensor([math.hypot(300, 200) + 100.0, 0.0, math.hypot(600, 400), 0.0])
    torch.testing.assert_close(stats.grad_sum, expected_sum)
    torch.testing.assert_close(stats.visible_views, torch.tensor([2.0, 0.0, 1.0, 0.0]))
    torch.testing.assert_close(stats.max_radii, torch.tensor([9.0, 0.0, 7.0, 0.0]))
    torch.testing.assert_close(stats.mean_grad(), torch.tensor([(math.hypot(300, 200) + 100.0) / 2, 0.0,
                                                                math.hypot(600, 400), 0.0]))


def test_opacity_reset_caps_at_one_percent_and_clears_only_the_opacity_moments():
    rows = [dict(scale=(0.001,) * 3, opacity=p) for p in (0.5, 0.005, 0.9)]
    model = make_model(rows)
    optimizer = make_adam(model.params, {k: 1e-3 for k in model.params})
    sum(v.square().sum() for v in model.params.values()).backward()
    optimizer.step()
    reset_opacity(model, optimizer)
    opacity = torch.sigmoid(model.params["opacity"].detach()[:, 0])
    torch.testing.assert_close(opacity, torch.tensor([0.01, 0.005, 0.01]))
    assert float(optimizer.state[model.params["opacity"]]["exp_avg"].abs().sum()) == 0
    assert float(optimizer.state[model.params["xyz"]]["exp_avg"].abs().sum()) > 0


# ------------------------------------------------------------------ when the trainer calls them
def _trainer_with_recorders(tiny_scene, tmp_path, monkeypatch, backbone="rt4dgs", **overrides):
    from omg4.train import Trainer, make_config

    own = dict(max_gaussians=700) if backbone == "freetimegs" else dict(max_gaussians=0, opacity_reset_interval=6)
    cfg = make_config("cpu-small", iterations=20, batch_size=1, densify_from=2, densify_interval=3, densify_until=16,
                      checkpoint_interval=0, backend="cpu", backbone=backbone, **own, **overrides)
    trainer = Trainer(tiny_scene, cfg, tmp_path / "run", progress=False, log=lambda *_: None)
    calls = []
    monkeypatch.setattr(densify, "densify_and_prune", lambda *a, **k: calls.append(("densify", k)) or {})
    monkeypatch.setattr(densify, "reset_opacity", lambda *a, **k: calls.append(("reset", k)))
    import omg4.train.strategies.relocation as relocate_module

    monkeypatch.setattr(relocate_module, "relocate", lambda *a, **k: calls.append(("relocate", k)) or 0)
    return trainer, cfg, calls


def _events(trainer, calls, steps):
    """(step, hook called, its keyword arguments) of the backbone's density control over ``steps``."""
    events = []
    for step in steps:
        calls.clear()
        trainer.strategy.after_step(trainer.model, trainer.optimizer, trainer.stats, step, trainer.extent)
        events += [(step, name, k) for name, k in calls]
    return events


def test_the_trainer_densifies_and_resets_at_the_scheduled_steps(tiny_scene, tmp_path, monkeypatch):
    trainer, cfg, calls = _trainer_with_recorders(tiny_scene, tmp_path, monkeypatch)
    events = _events(trainer, calls, range(1, 21))
    # densify when densify_from < step < densify_until and step % interval == 0; reset every 6 steps before
    # densify_until; the screen-size limit only once the first reset has passed
    assert [(s, n) for s, n, _ in events] == [(3, "densify"), (6, "densify"), (6, "reset"), (9, "densify"),
                                              (12, "densify"), (12, "reset"), (15, "densify")]
    limits = {s: k["max_screen_size"] for s, n, k in events if n == "densify"}
    assert limits == {3: None, 6: None, 9: cfg.strategy.prune_screen_size, 12: cfg.strategy.prune_screen_size,
                      15: cfg.strategy.prune_screen_size}
    k = events[0][2]
    assert (k["grad_threshold"], k["percent_dense"], k["prune_opacity"], k["prune_world_size"],
            k["max_gaussians"]) == (cfg.strategy.densify_grad_threshold, cfg.strategy.percent_dense,
                                    cfg.strategy.prune_opacity, cfg.strategy.prune_world_size,
                                    cfg.strategy.max_gaussians)
    assert k["extent"] == pytest.approx(tiny_scene.extent)


def test_a_freetimegs_trainer_relocates_on_the_same_steps_and_never_resets(tiny_scene, tmp_path, monkeypatch):
    trainer, cfg, calls = _trainer_with_recorders(tiny_scene, tmp_path, monkeypatch, backbone="freetimegs")
    steps = [(step, name) for step, name, _ in _events(trainer, calls, range(1, 21))]
    assert steps == [(3, "relocate"), (6, "relocate"), (9, "relocate"), (12, "relocate"), (15, "relocate")]
