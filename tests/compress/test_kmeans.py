"""k-means for SVQ codebooks: exact recovery, inertia vs. a brute-force reference, edge cases."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from omg4.compress.kmeans import entropy_constrained, inertia, kmeans, nearest_centroid, penalized_nearest


def _lloyd_reference(x: np.ndarray, k: int, seed: int, iters: int = 100) -> float:
    """Plain Lloyd with random (Forgy) initialization, brute-force float64 distances: the simple reference."""
    rng = np.random.default_rng(seed)
    c = x[rng.choice(len(x), k, replace=False)].copy()
    for _ in range(iters):
        d = ((x[:, None, :] - c[None, :, :]) ** 2).sum(-1)
        labels = d.argmin(1)
        for j in range(k):
            if (labels == j).any():
                c[j] = x[labels == j].mean(0)
    d = ((x[:, None, :] - c[None, :, :]) ** 2).sum(-1)
    return float(d.min(1).sum())


def _blobs(n_per: int, centres: np.ndarray, std: float, seed: int = 0) -> tuple[torch.Tensor, np.ndarray]:
    rng = np.random.default_rng(seed)
    truth = np.repeat(np.arange(len(centres)), n_per)
    x = centres[truth] + std * rng.normal(size=(len(truth), centres.shape[1]))
    perm = rng.permutation(len(truth))
    return torch.from_numpy(x[perm]).float(), truth[perm]


@pytest.mark.parametrize("d", [1, 2, 3, 6])
def test_recovers_well_separated_clusters_exactly(d):
    rng = np.random.default_rng(d)
    centres = rng.uniform(-100, 100, size=(12, d))
    centres[:, 0] += 20 * np.arange(12)  # at least ~20 apart along x, clusters have std 0.1
    x, truth = _blobs(50, centres, 0.1, seed=d)
    c, labels = kmeans(x, 12, seed=3)
    assert c.shape == (12, d) and labels.shape == (600,)
    # the partition matches the truth up to a relabelling
    pairs = set(zip(truth.tolist(), labels.tolist()))
    assert len(pairs) == 12 and len({a for a, _ in pairs}) == 12 and len({b for _, b in pairs}) == 12
    # and the centroids are the clusters' means (float64 reference)
    xd = x.double().numpy()
    for t, lab in pairs:
        np.testing.assert_allclose(c[lab].double().numpy(), xd[truth == t].mean(0), atol=1e-4)


@pytest.mark.parametrize("d,k", [(1, 16), (2, 32), (6, 16)])
def test_inertia_not_worse_than_plain_lloyd(d, k):
    """k blobs of unequal size and spread: where random initialization tends to miss clusters."""
    rng = np.random.default_rng(d)
    centres, sizes = rng.uniform(-10, 10, (k, d)), rng.integers(5, 120, k)
    x = torch.from_numpy(np.concatenate([c + rng.uniform(0.05, 0.5) * rng.normal(size=(s, d))
                                         for c, s in zip(centres, sizes)])).float()
    seeds = range(6)  # single runs vary with the seed: compare averages
    ours = np.mean([inertia(x, *kmeans(x, k, seed=s)) for s in seeds])
    reference = np.mean([_lloyd_reference(x.double().numpy(), k, s) for s in seeds])
    assert ours <= reference


def test_inertia_falls_as_k_grows():
    x = torch.randn(4000, 2, generator=torch.Generator().manual_seed(0))
    values = [inertia(x, *kmeans(x, k, seed=1)) for k in (2, 8, 32, 128, 512)]
    assert all(b < 0.8 * a for a, b in zip(values, values[1:]))


@pytest.mark.parametrize("d", [2, 8])
def test_labels_are_the_nearest_centroid(d):
    gen = torch.Generator().manual_seed(d)
    x = torch.randn(2000, d, generator=gen)
    c, labels = kmeans(x, 64, seed=0)
    dist = ((x.double()[:, None, :] - c.double()[None, :, :]) ** 2).sum(-1)
    assigned = dist.gather(1, labels[:, None]).squeeze(1)
    torch.testing.assert_close(assigned, dist.min(1).values, rtol=1e-6, atol=1e-9)
    assert torch.bincount(labels, minlength=64).min() > 0  # no empty cluster survives


@pytest.mark.parametrize("d", [2, 8])
def test_nearest_centroid_matches_brute_force_for_any_chunk(d):
    gen = torch.Generator().manual_seed(10 + d)
    x, c = torch.randn(3000, d, generator=gen), torch.randn(300, d, generator=gen)
    brute = ((x.double()[:, None, :] - c.double()[None, :, :]) ** 2).sum(-1)
    for chunk in (1, 1000, 1 << 23):
        sq, labels = nearest_centroid(x, c, chunk=chunk)
        torch.testing.assert_close(sq, brute.min(1).values, rtol=1e-9, atol=1e-9)
        assert (brute.gather(1, labels[:, None]).squeeze(1) == brute.min(1).values).all()


def test_k_at_least_number_of_points_is_exact():
    x = torch.randn(50, 2, generator=torch.Generator().manual_seed(0))
    for k in (50, 51, 1000):
        c, labels = kmeans(x, k)
        assert c.shape == (50, 2)
        torch.testing.assert_close(c[labels], x, rtol=0, atol=0)


def test_duplicates_collapse_and_share_labels():
    gen = torch.Generator().manual_seed(1)
    distinct = torch.randn(30, 2, generator=gen)
    x = distinct[torch.randint(0, 30, (3000,), generator=gen)]
    c, labels = kmeans(x, 64)  # fewer distinct points than clusters: exact
    assert c.shape == (30, 2)
    assert inertia(x, c, labels) == 0.0
    c, labels = kmeans(x, 10, seed=2)  # more distinct points than clusters: equal points, equal labels
    _, inv = torch.unique(x, dim=0, return_inverse=True)
    for j in range(30):
        assert labels[inv == j].unique().numel() == 1


def test_weighted_duplicates_pull_the_centroid():
    x = torch.tensor([[0.0], [0.0], [0.0], [4.0], [100.0]])
    c, labels = kmeans(x, 2, seed=0)
    assert sorted(c.squeeze(1).tolist()) == [1.0, 100.0]  # mean of 0,0,0,4 counts the duplicates


def test_empty_clusters_are_reseeded():
    """Heavy duplication plus a few outliers makes clusters go empty; every centroid must still be used."""
    gen = torch.Generator().manual_seed(3)
    x = torch.cat([torch.zeros(5000, 2), torch.randn(40, 2, generator=gen) * 50])
    c, labels = kmeans(x, 30, seed=0)
    assert c.shape == (30, 2)
    assert torch.bincount(labels, minlength=30).min() > 0


def test_deterministic_for_a_seed():
    x = torch.randn(3000, 2, generator=torch.Generator().manual_seed(4))
    a, b = kmeans(x, 100, seed=7), kmeans(x, 100, seed=7)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_invalid_inputs():
    with pytest.raises(ValueError):
        kmeans(torch.zeros(0, 2), 3)
    with pytest.raises(ValueError):
        kmeans(torch.zeros(5), 3)
    with pytest.raises(ValueError):
        kmeans(torch.tensor([[0.0], [float("nan")]]), 1)
    with pytest.raises(ValueError):
        kmeans(torch.zeros(5, 1), 0)
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            kmeans(torch.zeros(5, 1), 3, rate_weight=bad)


# ----------------------------------------------------------- entropy-constrained k-means (rate term)

def _rd_cost(x: np.ndarray, c: np.ndarray, labels: np.ndarray, lam: float) -> tuple[float, float, float]:
    """(Σ‖x − c_l‖², Σ log2(n / n_l), their λ-weighted sum), computed directly in float64 numpy."""
    counts = np.bincount(labels, minlength=len(c)).astype(np.float64)
    distortion = float(((x - c[labels]) ** 2).sum())
    rate = float(np.log2(len(x) / counts[labels]).sum())
    return distortion, rate, distortion + lam * rate


def _entropy(labels: np.ndarray) -> float:
    p = np.bincount(labels) / len(labels)
    p = p[p > 0]
    return float(-(p * np.log2(p)).sum())


@pytest.mark.parametrize("d", [1, 2, 3])
def test_penalized_nearest_matches_brute_force(d):
    gen = torch.Generator().manual_seed(20 + d)
    x, c = torch.randn(2000, d, generator=gen), torch.randn(100, d, generator=gen)
    penalty = torch.rand(100, generator=gen, dtype=torch.float64) * 2
    brute = ((x.double()[:, None, :] - c.double()[None]) ** 2).sum(-1) + penalty[None]
    for chunk in (1, 777, 1 << 23):
        labels = penalized_nearest(x, c, penalty, chunk=chunk)
        torch.testing.assert_close(brute.gather(1, labels[:, None]).squeeze(1), brute.min(1).values,
                                   rtol=1e-12, atol=1e-12)


def test_entropy_constrained_cost_never_rises():
    """Each iteration minimizes J = D + λR exactly in one block of variables, so J after i + 1 iterations
    is at most J after i (J recomputed from the returned codebook and labels)."""
    rng = np.random.default_rng(5)
    x = np.concatenate([rng.normal(size=(1500, 2)), rng.normal(size=(300, 2)) * 0.2 + 3])
    xt = torch.from_numpy(x)
    c0, l0 = kmeans(xt, 64, seed=0)
    lam = 3 * inertia(xt, c0, l0) / len(x)
    w = torch.ones(len(x), dtype=torch.float64)
    costs = [_rd_cost(x, c0.numpy(), l0.numpy(), lam)[2]]
    for iters in (1, 2, 3, 5, 8, 13, 40):
        c, labels = entropy_constrained(xt, w, c0, l0, lam, iters=iters, tol=0.0)
        assert torch.bincount(labels).min() > 0 and labels.max() < len(c)
        costs.append(_rd_cost(x, c.numpy(), labels.numpy(), lam)[2])
    assert all(b <= a * (1 + 1e-12) for a, b in zip(costs, costs[1:]))
    assert costs[-1] < 0.9 * costs[0]


def test_rate_weight_trades_distortion_for_index_entropy():
    """A larger β gives fewer codewords in use, a lower index entropy and a higher distortion; the
    rate-distortion cost at each β is below that of the plain k-means solution it started from."""
    rng = np.random.default_rng(6)
    x = torch.from_numpy(rng.normal(size=(4000, 2)) * np.array([1.0, 0.3]))
    c0, l0 = kmeans(x, 256, seed=1)
    base_d = inertia(x, c0, l0) / len(x)
    entropies, distortions, sizes = [_entropy(l0.numpy())], [base_d], [len(c0)]
    for beta in (1.0, 10.0, 100.0):
        c, labels = kmeans(x, 256, seed=1, rate_weight=beta)
        assert torch.bincount(labels).min() > 0
        lam = beta * base_d
        assert _rd_cost(x.numpy(), c.numpy(), labels.numpy(), lam)[2] < _rd_cost(
            x.numpy(), c0.numpy(), l0.numpy(), lam)[2]
        entropies.append(_entropy(labels.numpy()))
        distortions.append(inertia(x, c, labels) / len(x))
        sizes.append(len(c))
    assert all(b < a for a, b in zip(entropies, entropies[1:]))
    assert all(b > a for a, b in zip(distortions, distortions[1:]))
    assert sizes[-1] < sizes[0] // 4 and entropies[-1] < entropies[0] - 2


def test_rate_weight_keeps_exact_fits_and_the_plain_path():
    x = torch.randn(50, 2, generator=torch.Generator().manual_seed(0))
    c, labels = kmeans(x, 64, rate_weight=10.0)  # no more points than clusters: exact, nothing to trade
    torch.testing.assert_close(c[labels], x, rtol=0, atol=0)
    y = torch.randn(3000, 2, generator=torch.Generator().manual_seed(1))
    a, b = kmeans(y, 100, seed=3), kmeans(y, 100, seed=3, rate_weight=0.0)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


@pytest.mark.parametrize("k", [5, 64, 256, 300])
def test_initial_centres_are_drawn_in_batches_doubling_up_to_k_over_32(k, monkeypatch):
    """Batched D² sampling: batches of 1, 1, 2, 4, … (the centres so far), at most max(1, k // 32), never beyond k
    nor beyond the points with positive probability; k centres in all."""
    from omg4.compress import kmeans as module

    batches = []
    real = torch.multinomial
    monkeypatch.setattr(module.torch, "multinomial",
                        lambda p, n, **kw: batches.append(n) or real(p, n, **kw))
    g = torch.Generator().manual_seed(k)
    x = torch.randn(4 * k + 50, 2, generator=g, dtype=torch.float64)
    centres = module._init_centres(x, torch.ones(len(x), dtype=torch.float64), k, torch.Generator().manual_seed(0),
                                   1 << 20)
    expected, total = [1], 1
    while total < k:
        expected.append(min(total, max(1, k // 32), k - total))
        total += expected[-1]
    assert batches == expected and len(centres) == k and len(set(centres.tolist())) == k


def test_a_model_missing_any_quantized_attribute_or_its_mlps_is_not_written():
    """build_payload refuses a model unless every SVQ attribute and the appearance MLPs are present."""
    from types import SimpleNamespace

    from omg4.compress.api import build_payload
    from omg4.errors import OMG4Error
    from omg4.gaussians.backbone import RT4DGS

    config = SimpleNamespace(schema=RT4DGS)
    all_groups = {g.name: object() for g in RT4DGS.svq_groups}
    for appearance, quantizers in ((object(), {k: v for k, v in all_groups.items() if k != "rotation_r"}),
                                   (None, all_groups)):
        model = SimpleNamespace(config=config, appearance=appearance, quantizers=quantizers)
        with pytest.raises(OMG4Error, match="not fully compressed"):
            build_payload(model, {})
