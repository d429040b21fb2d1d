"""Gaussian Merging (paper §4.3, omg4 §6a, §14.7): cluster building and proxies.

Cluster building is checked against a brute-force Python reference written from the spec
(loops over cells and pairs, numpy quantiles, the official greedy dedup/subset filter);
proxies against direct float64 weighted means and finite differences.
"""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np
import pytest
import torch

from omg4.compress.merging import (MergeConfig, MergeGroups, MergeProxy, build_merge_groups, build_star_clusters,
                                   make_disjoint)
from omg4.errors import OMG4Error
from omg4.gaussians.backbone import RT4DGS

TIME_RANGE = (0.0, 10.0)


# ------------------------------------------------------------------------- reference
def reference_clusters(xyz, t, dc, time_range, grid, cfg):
    """Maximal star clusters, brute force (loops), including the slab split of large cells."""
    x = xyz.double().numpy()
    tt = t.double().numpy().reshape(-1)
    f = dc.double().numpy().reshape(-1, 3)
    n = len(x)
    lo, hi = np.quantile(x, 0.001, axis=0), np.quantile(x, 0.999, axis=0)
    xn = (x - lo) / (hi - lo + 1e-6)
    fn = (f - f.min(0)) / (f.max(0) - f.min(0) + 1e-6)
    t0, t1 = time_range
    cells = defaultdict(list)
    for i in range(n):
        key = tuple(math.floor(x[i, k] / grid) for k in range(3))
        key += (math.floor((tt[i] - t0) / (cfg.time_cell_fraction * (t1 - t0))),)
        cells[key].append(i)
    blocks = []
    for members in cells.values():
        m = len(members)
        if m <= cfg.max_cell_size:
            blocks.append(members)
            continue
        by_x = sorted(members, key=lambda i: (x[i, 0], i))
        pieces = -(-m // cfg.max_cell_size)
        split = defaultdict(list)
        for r, i in enumerate(by_x):
            split[r * pieces // m].append(i)
        blocks.extend(sorted(s) for s in split.values())
    found = set()
    for members in blocks:
        if len(members) < 2:
            continue
        sims = {}
        for a in range(len(members)):
            for b in range(a + 1, len(members)):
                i, j = members[a], members[b]
                sims[i, j] = -np.sum((xn[i] - xn[j]) ** 2) - cfg.color_weight * np.sum((fn[i] - fn[j]) ** 2)
        thr = max(cfg.tau_sim, float(np.quantile(np.array(list(sims.values())), cfg.sim_quantile)))
        for i in members:
            c = {i} | {j for j in members if j > i and sims[i, j] >= thr}
            if len(c) >= 2:
                found.add(frozenset(c))
    kept = []
    for s in sorted(found, key=len, reverse=True):  # the official greedy: drop subsets of kept sets
        if not any(s <= k for k in kept):
            kept.append(s)
    return set(kept)


def reference_disjoint(clusters):
    """The documented rule, sequentially: by (size desc, smallest index), claim unclaimed members."""
    claimed, groups = set(), []
    for c in sorted(clusters, key=lambda s: (-len(s), min(s))):
        mine = set(c) - claimed
        claimed |= mine
        if len(mine) >= 2:
            groups.append(frozenset(mine))
    return set(groups)


def groups_as_sets(g: MergeGroups) -> set[frozenset[int]]:
    out = defaultdict(set)
    for m, gid in zip(g.members.tolist(), g.group_of.tolist()):
        out[gid].add(m)
    return {frozenset(s) for s in out.values()}


def blob_scene(seed: int, n_blobs: int = 6, per_blob: int = 70, n_background: int = 150, spread_scale: float = 1.0):
    """Tight same-coloured blobs (many merge candidates, cells of > 64 members) plus scattered points."""
    g = torch.Generator().manual_seed(seed)
    centres = torch.rand(n_blobs, 3, generator=g) * 0.6 - 0.3
    spread = spread_scale * torch.tensor([0.004, 0.01, 0.02, 0.004, 0.015, 0.008])[:n_blobs]
    xyz_b = (centres[:, None] + spread[:, None, None] * torch.randn(n_blobs, per_blob, 3, generator=g)).reshape(-1, 3)
    col_b = (torch.rand(n_blobs, 1, 3, generator=g) + 0.003 * torch.randn(n_blobs, per_blob, 3, generator=g))
    t_b = (torch.rand(n_blobs, 1, generator=g) * 8 + 1 + 0.6 * torch.rand(n_blobs, per_blob, generator=g))
    xyz = torch.cat([xyz_b, torch.rand(n_background, 3, generator=g) * 4 - 2])
    dc = torch.cat([col_b.reshape(-1, 3), torch.rand(n_background, 3, generator=g)]).reshape(-1, 1, 3)
    t = torch.cat([t_b.reshape(-1), torch.rand(n_background, generator=g) * 10]).reshape(-1, 1)
    perm = torch.randperm(len(xyz), generator=g)
    return xyz[perm].float(), t[perm].float(), dc[perm].float()


# ------------------------------------------------------------------ cluster building
@pytest.mark.parametrize("seed,grid,overrides,spread", [
    (0, 0.1, {}, 1.0),
    (5, 0.1, {}, 3.0),  # looser blobs: many cells keep thr = τ_sim
    (1, 0.12, {"pair_chunk": 97}, 1.0),  # many chunks
    (2, 0.1, {"max_cell_size": 40}, 1.0),  # large cells split into slabs along x
    (3, 0.3, {"tau_sim": -3e-3, "color_weight": 1.0, "sim_quantile": 0.5, "pair_chunk": 1000}, 1.0),
])
def test_star_clusters_match_brute_force(seed, grid, overrides, spread):
    xyz, t, dc = blob_scene(seed, spread_scale=spread)
    cfg = MergeConfig(**overrides)
    expected = reference_clusters(xyz, t, dc, TIME_RANGE, grid, cfg)
    got = build_star_clusters(xyz, t, dc, TIME_RANGE, grid, cfg)
    assert len(expected) >= 5  # the scene really produces clusters, some of them large
    assert max(len(s) for s in expected) > 3
    assert got.as_sets() == expected
    assert len(got.as_sets()) == len(got.centre)  # no duplicates
    assert got.centre.tolist() == sorted(min(s) for s in expected)
    groups = build_merge_groups(xyz, t, dc, TIME_RANGE, grid, cfg)
    assert groups_as_sets(groups) == reference_disjoint(expected)


@pytest.mark.parametrize("q", [0.7, 0.5, 0.93])
def test_cell_thresholds_match_numpy_quantiles(q):
    """thr_b = max(τ, Q_q(block sims)) on random sims (sizes 1..300, ties, values at τ exactly)."""
    from omg4.compress.merge_clusters import _cell_thresholds

    cfg = MergeConfig(sim_quantile=q)
    rng = np.random.default_rng(0)
    sizes = rng.integers(1, 300, size=120)
    sims = []
    for k, m in enumerate(sizes):
        share = k % 5 / 4  # fraction of sims above τ: 0, ¼, ½, ¾, 1
        v = np.where(rng.random(m) < share, -rng.random(m) * 2e-4, -3e-4 - rng.random(m) * 1e-3)
        if k % 7 == 0:
            v[: m // 2] = cfg.tau_sim  # exact ties at τ
        if k % 11 == 0:
            v = np.round(v, 5)  # many ties
        sims.append(v)
    block = torch.repeat_interleave(torch.arange(len(sizes)), torch.tensor(sizes))
    got = _cell_thresholds(torch.tensor(np.concatenate(sims)), block, torch.tensor(sizes), cfg)
    expected = [max(cfg.tau_sim, float(np.quantile(v, q))) for v in sims]
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-12, atol=0)
    assert sum(e > cfg.tau_sim for e in expected) > 20 and sum(e == cfg.tau_sim for e in expected) > 20


def test_reference_scene_has_overlapping_clusters():
    """The disjointness step is exercised: maximal clusters overlap in the test scene."""
    xyz, t, dc = blob_scene(0)
    sets = build_star_clusters(xyz, t, dc, TIME_RANGE, 0.1, MergeConfig()).as_sets()
    total = sum(len(s) for s in sets)
    assert total > len(set().union(*sets))


def test_groups_are_disjoint_and_well_formed():
    xyz, t, dc = blob_scene(4)
    g = build_merge_groups(xyz, t, dc, TIME_RANGE, 0.1, MergeConfig())
    assert g.num_groups > 0
    members = g.members.tolist()
    assert len(members) == len(set(members))  # disjoint
    assert g.group_of.tolist() == sorted(g.group_of.tolist())
    assert g.group_of.unique().tolist() == list(range(g.num_groups))
    for gid in range(g.num_groups):
        mine = g.members[g.group_of == gid].tolist()
        assert len(mine) >= 2
        assert mine == sorted(mine)
        assert int(g.representative[gid]) == min(mine)  # representative = smallest index
    assert g.representative.tolist() == sorted(g.representative.tolist())
    assert g.num_removed == len(members) - g.num_groups


def _scene_with(points_xyz, points_t, points_dc):
    """Given points plus fixed background corners (normalization: positions /4, colours [0, 1])."""
    corners = torch.tensor([[-2.0, -2.0, -2.0]] * 10 + [[2.0, 2.0, 2.0]] * 10)
    corner_dc = torch.tensor([[0.0, 0.0, 0.0]] * 10 + [[1.0, 1.0, 1.0]] * 10)
    xyz = torch.cat([corners, torch.tensor(points_xyz, dtype=torch.float32)])
    t = torch.cat([torch.full((20,), 5.0), torch.tensor(points_t, dtype=torch.float32)])
    dc = torch.cat([corner_dc, torch.tensor(points_dc, dtype=torch.float32)]).reshape(-1, 1, 3)
    return xyz, t, dc


def _pair_merged(points_xyz, points_t, points_dc) -> bool:
    xyz, t, dc = _scene_with(points_xyz, points_t, points_dc)
    g = build_merge_groups(xyz, t, dc, TIME_RANGE, 0.1, MergeConfig())
    return frozenset({20, 21}) in groups_as_sets(g)


def test_coincident_same_colour_pair_merges():
    assert _pair_merged([[0.5, 0.5, 0.5]] * 2, [3.0, 3.5], [[0.3, 0.4, 0.5]] * 2)


@pytest.mark.parametrize("dx,merged", [(0.04, True), (0.08, False)])
def test_spatial_distance_threshold(dx, merged):
    # normalized Δ = dx / 4: sim = −(dx/4)² = −1e-4 (≥ τ = −3e-4) or −4e-4 (< τ)
    assert _pair_merged([[0.505, 0.55, 0.55], [0.505 + dx, 0.55, 0.55]], [3.0, 3.0], [[0.3, 0.4, 0.5]] * 2) == merged


@pytest.mark.parametrize("df,merged", [(0.005, True), (0.02, False)])
def test_colour_difference_threshold(df, merged):
    # sim = −λ Δf² = −4 · 2.5e-5 = −1e-4 (merge) or −4 · 4e-4 = −1.6e-3 (no merge)
    assert _pair_merged([[0.55, 0.55, 0.55]] * 2, [3.0, 3.0], [[0.3, 0.4, 0.5], [0.3 + df, 0.4, 0.5]]) == merged


@pytest.mark.parametrize("times,merged", [((1.0, 1.9), True), ((1.9, 2.1), False), ((5.9, 6.0), False)])
def test_time_cells(times, merged):
    # time cell = 0.2 × 10 s = 2 s
    assert _pair_merged([[0.55, 0.55, 0.55]] * 2, list(times), [[0.3, 0.4, 0.5]] * 2) == merged


def test_spatial_cell_boundary_separates():
    assert not _pair_merged([[0.0995, 0.55, 0.55], [0.1005, 0.55, 0.55]], [3.0, 3.0], [[0.3, 0.4, 0.5]] * 2)


def test_three_coincident_form_one_group_subsets_removed():
    xyz, t, dc = _scene_with([[0.55, 0.55, 0.55]] * 3, [3.0] * 3, [[0.3, 0.4, 0.5]] * 3)
    clusters = build_star_clusters(xyz, t, dc, TIME_RANGE, 0.1, MergeConfig())
    assert frozenset({20, 21, 22}) in clusters.as_sets()
    assert frozenset({21, 22}) not in clusters.as_sets()


def test_disjoint_rule_largest_cluster_wins():
    """Hand-built overlapping clusters, ranked by (size desc, centre asc)."""
    from omg4.compress.merge_clusters import StarClusters

    sets = [[0, 1, 2, 3], [3, 4, 5], [5, 6], [7, 8, 9], [10, 11], [11, 12]]
    members = torch.tensor([i for s in sets for i in s])
    cluster_of = torch.tensor([c for c, s in enumerate(sets) for _ in s])
    centre = torch.tensor([s[0] for s in sets])
    g = make_disjoint(StarClusters(centre, members, cluster_of), 14)
    # {3,4,5} loses 3 to {0,1,2,3} and keeps {4,5}; {5,6} keeps only 6 → dropped;
    # {10,11} outranks the equal-sized {11,12} (smaller centre), which keeps only 12 → dropped
    expected = {frozenset({0, 1, 2, 3}), frozenset({4, 5}), frozenset({7, 8, 9}), frozenset({10, 11})}
    assert groups_as_sets(g) == expected == reference_disjoint({frozenset(s) for s in sets})
    assert g.representative.tolist() == [0, 4, 7, 10]


def test_empty_and_tiny_inputs():
    cfg = MergeConfig()
    for n in (0, 1):
        g = build_merge_groups(torch.zeros(n, 3), torch.zeros(n, 1), torch.zeros(n, 1, 3), TIME_RANGE, 0.1, cfg)
        assert g.num_groups == 0 and g.members.numel() == 0
    # all Gaussians alone in their cells
    xyz = torch.arange(5, dtype=torch.float32)[:, None].repeat(1, 3)
    g = build_merge_groups(xyz, torch.zeros(5), torch.zeros(5, 3), TIME_RANGE, 0.1, cfg)
    assert g.num_groups == 0
    params = _params(5)
    baked, mask = MergeProxy(g, 5, RT4DGS.merged).bake(params)  # a round without groups changes nothing
    assert mask.all() and all(torch.equal(baked[k], params[k]) for k in params)


def test_bad_inputs_raise():
    xyz, t, dc = blob_scene(0)
    xyz[3, 1] = float("nan")
    with pytest.raises(OMG4Error, match="non-finite"):
        build_merge_groups(xyz, t, dc, TIME_RANGE, 0.1, MergeConfig())
    xyz, t, dc = blob_scene(0)
    with pytest.raises(OMG4Error, match="cell sizes"):
        build_merge_groups(xyz, t, dc, TIME_RANGE, 0.0, MergeConfig())
    with pytest.raises(OMG4Error, match="cell sizes"):
        build_merge_groups(xyz, t, dc, (1.0, 1.0), 0.1, MergeConfig())
    with pytest.raises(OMG4Error, match="needs xyz"):
        build_merge_groups(xyz[:, :2], t, dc, TIME_RANGE, 0.1, MergeConfig())


# ---------------------------------------------------------------------------- proxies
def _params(n: int, seed: int = 0, dtype=torch.float32) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    shapes = {"xyz": (n, 3), "t": (n, 1), "scaling": (n, 3), "scaling_t": (n, 1), "rotation": (n, 4),
              "rotation_r": (n, 4), "opacity": (n, 1), "features_dc": (n, 1, 3), "features_rest": (n, 47, 3)}
    return {k: torch.randn(s, generator=g, dtype=dtype) for k, s in shapes.items()}


def _toy_groups() -> MergeGroups:
    # groups {1, 4, 6}, {2, 3}, {7, 9}; Gaussians 0, 5, 8 unmerged
    return MergeGroups(members=torch.tensor([1, 4, 6, 2, 3, 7, 9]), group_of=torch.tensor([0, 0, 0, 1, 1, 2, 2]),
                       representative=torch.tensor([1, 2, 7]))


def test_equal_weights_give_member_mean_and_keep_other_attributes():
    params = _params(10)
    proxy = MergeProxy(_toy_groups(), 10, RT4DGS.merged)
    values, keep = proxy.apply(params)
    assert keep.tolist() == [0, 1, 2, 5, 7, 8]
    for rep, members in ((1, [1, 4, 6]), (2, [2, 3]), (7, [7, 9])):
        for name in ("xyz", "features_dc", "features_rest"):
            expected = params[name][members].double().mean(0)
            torch.testing.assert_close(values[name][rep].double(), expected, rtol=1e-6, atol=1e-6)
    for name in ("t", "scaling", "scaling_t", "rotation", "rotation_r", "opacity"):
        assert torch.equal(values[name], params[name])  # representative's own attributes
    for name in ("xyz", "features_dc", "features_rest"):  # rows outside the groups are untouched
        assert torch.equal(values[name][[0, 5, 8]], params[name][[0, 5, 8]])


def test_weighted_proxy_matches_formula():
    params = _params(10, dtype=torch.float64)
    proxy = MergeProxy(_toy_groups(), 10, RT4DGS.merged).double()
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for p in proxy.logits.values():
            p.copy_(torch.randn(p.shape, generator=g, dtype=torch.float64) * 2)
    values, _ = proxy.apply(params)
    members, group_of = _toy_groups().members.tolist(), _toy_groups().group_of.tolist()
    for name, logit in (("xyz", "merge_xyz_logits"), ("features_dc", "merge_dc_logits"),
                        ("features_rest", "merge_rest_logits")):
        l = proxy.logits[logit].detach().tolist()
        for gid, rep in enumerate((1, 2, 7)):
            idx = [k for k in range(len(members)) if group_of[k] == gid]
            s = [1 / (1 + math.exp(-l[k])) + 1e-12 for k in idx]
            w = [v / (sum(s) + 1e-12) for v in s]
            expected = sum(wk * params[name][members[k]] for wk, k in zip(w, idx))
            torch.testing.assert_close(values[name][rep], expected, rtol=1e-12, atol=1e-12)


def test_bake_preserves_the_proxy_exactly():
    params = _params(10)
    proxy = MergeProxy(_toy_groups(), 10, RT4DGS.merged)
    with torch.no_grad():
        proxy.logits["merge_xyz_logits"].copy_(torch.linspace(-1, 2, 7))
        proxy.logits["merge_rest_logits"].copy_(torch.linspace(3, -2, 7))
    values, keep = proxy.apply(params)
    baked, mask = proxy.bake(params)
    assert mask.dtype == torch.bool and mask.shape == (10,)
    assert torch.nonzero(mask).squeeze(1).tolist() == keep.tolist()
    assert set(baked) == set(params)
    for name in params:
        assert not baked[name].requires_grad
        assert torch.equal(baked[name][mask], values[name][keep])
    assert not torch.equal(baked["xyz"][1], params["xyz"][1])  # the representative really changed


def test_bake_preserves_the_time_slice_exactly():
    """The renderer's input (a time slice of the Real-Time4DGS model) is identical after baking."""
    from omg4.gaussians import GaussianConfig, Gaussians4D

    xyz, t, dc = blob_scene(6)
    n = len(xyz)
    params = _params(n, seed=2)
    params.update(xyz=xyz, t=t, features_dc=dc, scaling=params["scaling"] * 0.1 - 4.0,
                  scaling_t=params["scaling_t"] * 0.1 + 1.0)
    proxy = MergeProxy(build_merge_groups(xyz, t, dc, TIME_RANGE, 0.1, MergeConfig()), n, RT4DGS.merged)
    assert proxy.num_groups > 10
    with torch.no_grad():
        for p in proxy.logits.values():
            p.copy_(torch.randn(p.shape, generator=torch.Generator().manual_seed(1)))
    values, keep = proxy.apply(params)
    baked, mask = proxy.bake(params)
    config = GaussianConfig(time_range=TIME_RANGE)
    live = Gaussians4D({k: v[keep] for k, v in values.items()}, config, 3, 2)
    merged = Gaussians4D({k: v[mask] for k, v in baked.items()}, config, 3, 2)
    for time in (2.0, 5.5):
        a = live.slice_at(time, torch.tensor([0.0, 0.0, 4.0]))
        b = merged.slice_at(time, torch.tensor([0.0, 0.0, 4.0]))
        assert len(a.index) > 50
        for name in ("means", "covars", "colors", "opacities", "index"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name


def test_gradients_reach_logits_and_all_members():
    params = {k: v.double().requires_grad_(True) for k, v in _params(10, seed=1).items()}
    proxy = MergeProxy(_toy_groups(), 10, RT4DGS.merged).double()
    probe = {k: torch.randn(v.shape, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
             for k, v in params.items()}

    def loss_fn():
        values, keep = proxy.apply(params)
        return sum((values[k][keep] * probe[k][keep]).sum() for k in values)

    loss_fn().backward()
    members = _toy_groups().members
    for name in ("xyz", "features_dc", "features_rest"):
        grad = params[name].grad
        assert (grad[members].abs().flatten(1).sum(1) > 0).all()
        assert (grad[[5, 8]] == 0).sum() == 0  # unmerged rows keep their own gradient
    assert (params["opacity"].grad[[4, 6, 3, 9]] == 0).all()  # removed members' other attributes unused
    for name, p in proxy.logits.items():
        assert (p.grad.abs() > 0).all(), name
    # finite differences on one logit of each vector
    for name, p in proxy.logits.items():
        analytic = float(p.grad[1])
        with torch.no_grad():
            p[1] += 1e-6
            up = float(loss_fn())
            p[1] -= 2e-6
            down = float(loss_fn())
            p[1] += 1e-6
        assert analytic == pytest.approx((up - down) / 2e-6, rel=1e-5, abs=1e-9)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_fused_proxy_matches_autograd_of_the_torch_form(dtype):
    """The proxy rows' numpy forward and backward (the CPU kernels' path) against the torch form (the reference),
    with random logits so the weights differ within each group."""
    from omg4.kernels import using_kernels

    g = torch.Generator().manual_seed(3)
    base = {k: v.to(dtype) for k, v in _params(10, seed=2).items()}
    probe = {k: torch.randn(v.shape, generator=g, dtype=dtype) for k, v in base.items()}
    logits = {name: torch.randn(7, generator=g, dtype=dtype) for name in RT4DGS.merged.values()}
    results = []
    for mode in ("reference", "fused"):
        proxy = MergeProxy(_toy_groups(), 10, RT4DGS.merged).to(dtype)
        with torch.no_grad():
            for name, p in proxy.logits.items():
                p.copy_(logits[name])
        params = {k: v.clone().requires_grad_(True) for k, v in base.items()}
        with using_kernels(mode):
            values, keep = proxy.apply(params)
            sum((values[k][keep] * probe[k][keep]).sum() for k in values).backward()
        results.append(({k: v.detach() for k, v in values.items()}, {k: p.grad for k, p in params.items()},
                        {k: p.grad for k, p in proxy.logits.items()}))
    (ref_values, ref_grads, ref_logits), (values, grads, logit_grads) = results
    tol = {"rtol": 1e-12, "atol": 1e-13} if dtype == torch.float64 else {"rtol": 2e-6, "atol": 1e-6}
    for name in ref_values:
        torch.testing.assert_close(values[name], ref_values[name], **tol, msg=name)
        torch.testing.assert_close(grads[name], ref_grads[name], **tol, msg=name)
    for name, want in ref_logits.items():
        assert want.abs().min() > 0
        torch.testing.assert_close(logit_grads[name], want, **tol, msg=name)


def test_param_groups_for_adam():
    proxy = MergeProxy(_toy_groups(), 10, RT4DGS.merged)
    groups = proxy.param_groups(0.01)
    assert [g["name"] for g in groups] == ["merge_xyz_logits", "merge_dc_logits", "merge_rest_logits"]
    assert all(g["lr"] == 0.01 and g["params"][0].shape == (7,) for g in groups)
    assert all((g["params"][0] == 0).all() for g in groups)  # initialised to 0
    torch.optim.Adam(groups, lr=0.0)  # accepted by the main optimizer


def test_proxy_rejects_wrong_row_count():
    with pytest.raises(ValueError):
        MergeProxy(_toy_groups(), 10, RT4DGS.merged).apply(_params(11))


def test_round_trip_on_built_groups():
    """End to end: groups from a scene, proxy, bake, and the merged count."""
    xyz, t, dc = blob_scene(5)
    groups = build_merge_groups(xyz, t, dc, TIME_RANGE, 0.1, MergeConfig())
    params = _params(len(xyz))
    params.update(xyz=xyz, t=t, features_dc=dc)
    baked, mask = MergeProxy(groups, len(xyz), RT4DGS.merged).bake(params)
    assert int(mask.sum()) == len(xyz) - groups.num_removed
    torch.testing.assert_close(baked["xyz"][groups.representative],
                               torch.stack([xyz[groups.members[groups.group_of == g]].mean(0)
                                            for g in range(groups.num_groups)]))
