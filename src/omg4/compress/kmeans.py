"""k-means for the sub-vector quantization codebooks (paper §4.4; omg4 §7).

OMG4 runs cuML ``KMeans(n_clusters=K, max_iter=1000, n_init=1)`` with scalable k-means++
initialization. This is the CPU equivalent, vectorized throughout:

* duplicates are merged first (by bit pattern) and the rest is *weighted* k-means on the
  distinct points, so repeated sub-vectors cost nothing and ``k ≥ #distinct`` is exact;
* initialization is batched D² sampling (k-means++ / k-means|| style): each round draws a
  batch of new centres with probability ∝ weight·D² without replacement, the batch
  doubling up to ``k/32`` centres, so there are O(log k + 32) rounds instead of k;
* Lloyd iterations with an early stop on the relative inertia change (``tol``, as cuML);
  an empty cluster is re-seeded at the point farthest from its centroid;
* nearest-centroid search is exact: a binary search between sorted centroids in 1-D, a
  KD-tree (scipy) for low dimension — the SVQ sub-vectors have length 1 or 2 — and chunked
  ``‖x‖² − 2x·c + ‖c‖²`` matrix products otherwise, never materializing more than
  ``chunk`` distances at once;
* beyond the paper, an optional rate term (``rate_weight`` > 0): entropy-constrained VQ (Chou,
  Lookabaugh & Gray 1989) continues from the k-means solution, assigning each point to the centroid
  of least ``‖x − c‖² + λ·log2(1/p_c)`` (p_c the cluster's share of the points) and re-estimating
  centroids and shares until that cost stops falling. Index usage becomes skewed and unused
  codewords disappear, so the indices entropy-code to fewer bits (omg4 §8, "compact" codec) at
  some distortion; ``rate_weight = 0`` is the paper's plain k-means.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree

KDTREE_MAX_DIM = 4


def nearest_centroid(x: torch.Tensor, c: torch.Tensor, chunk: int = 1 << 23) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact nearest centroid of every point.

    Args:
        x: points [n, d]; c: centroids [k, d]; chunk: most distances held at once (mm path).
    Returns:
        (squared distances [n] float64, labels [n] int64).
    """
    n, d = x.shape
    if d == 1:
        sorted_c, order = torch.sort(c[:, 0].double())
        pos = torch.searchsorted((sorted_c[1:] + sorted_c[:-1]) / 2, x[:, 0].double().contiguous())
        return (x[:, 0].double() - sorted_c[pos]).square(), order[pos]
    if d <= KDTREE_MAX_DIM:
        dist, labels = cKDTree(c.double().numpy()).query(x.double().numpy(), k=1, workers=torch.get_num_threads())
        return torch.from_numpy(np.square(dist)), torch.from_numpy(labels.astype(np.int64))
    cf = c.float()
    labels = _argmin_by_products(x.float(), cf, (cf * cf).sum(1), chunk)
    sq = (x.double() - c.double()[labels]).square().sum(1)
    return sq, labels


def _argmin_by_products(x: torch.Tensor, c: torch.Tensor, offset: torch.Tensor, chunk: int) -> torch.Tensor:
    """Labels [n] minimizing ``offset_j − 2 x·c_j`` (``offset = ‖c‖²`` plus any per-centroid penalty; ‖x‖² is the
    same for every j), from chunked matrix products holding at most ``chunk`` values, in ``x``'s dtype."""
    rows = max(1, chunk // max(1, c.shape[0]))
    labels = torch.empty(x.shape[0], dtype=torch.int64)
    for start in range(0, x.shape[0], rows):
        labels[start:start + rows] = torch.addmm(offset[None, :], x[start:start + rows], c.T, alpha=-2.0).argmin(1)
    return labels


def _cluster_sums(x: torch.Tensor, w: torch.Tensor, labels: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(weight [k], weighted sum of the points [k, d]) of each of ``k`` clusters, float64."""
    mass = torch.zeros(k, dtype=torch.float64).index_add_(0, labels, w)
    sums = torch.zeros(k, x.shape[1], dtype=torch.float64).index_add_(0, labels, x * w[:, None])
    return mass, sums


def _distinct_rows(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Distinct rows of ``x: [n, d]`` by bit pattern: (points [m, d], inverse [n], counts [m])."""
    a = np.ascontiguousarray(x.numpy())
    rows = a.view(np.dtype((np.void, a.dtype.itemsize * a.shape[1]))).ravel()
    unique, inverse, counts = np.unique(rows, return_inverse=True, return_counts=True)
    points = np.frombuffer(unique.tobytes(), dtype=a.dtype).reshape(-1, a.shape[1])
    return torch.from_numpy(points.copy()), torch.from_numpy(inverse.reshape(-1)), torch.from_numpy(counts)


def _init_centres(x: torch.Tensor, w: torch.Tensor, k: int, gen: torch.Generator, chunk: int) -> torch.Tensor:
    """Batched D² sampling (k-means++ with batches doubling up to k/32); returns centre rows [k] into ``x``."""
    chosen = [torch.multinomial(w, 1, generator=gen)]
    d2, _ = nearest_centroid(x, x[chosen[0]], chunk)
    total, max_batch = 1, max(1, k // 32)
    while total < k:
        p = w * d2
        available = int((p > 0).sum())
        batch = min(total, max_batch, k - total, available)
        new = torch.multinomial(p, batch, replacement=False, generator=gen)
        chosen.append(new)
        total += batch
        d2 = torch.minimum(d2, nearest_centroid(x, x[new], chunk)[0])
    return torch.cat(chosen)


def _update(x: torch.Tensor, w: torch.Tensor, labels: torch.Tensor, d2: torch.Tensor,
            centroids: torch.Tensor) -> torch.Tensor:
    """Weighted means of the clusters; empty clusters re-seeded at the farthest points. [k, d] float64."""
    mass, sums = _cluster_sums(x, w, labels, centroids.shape[0])
    new = torch.where(mass[:, None] > 0, sums / mass.clamp_min(1e-300)[:, None], centroids)
    empty = torch.nonzero(mass == 0).squeeze(1)
    if empty.numel():
        far = torch.topk(d2, empty.numel()).indices
        new[empty] = x[far]
    return new


def kmeans(x: torch.Tensor, k: int, iters: int = 100, seed: int = 0, chunk: int = 1 << 23,
           tol: float = 1e-4, rate_weight: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Cluster ``x: [n, d]`` into at most ``k`` centroids.

    Args:
        x: points [n, d] (finite). k: number of clusters. iters: most Lloyd iterations (and, with a rate
            term, most entropy-constrained iterations after them).
        seed: RNG seed of the initialization. chunk: most distances in memory at once.
        tol: stop when the inertia (or the rate-constrained cost) falls by less than this fraction in one
            iteration.
        rate_weight: β ≥ 0; with β > 0 the k-means solution is refined by :func:`entropy_constrained` with
            λ = β × its mean squared distance per bit (a bit of index is worth β times the mean distortion).
    Returns:
        (centroids [k', d] (float64 for float64 input, else float32), labels [n] int64) with k' = min(k, #distinct
        points) — possibly fewer with a rate term, which drops the codewords nobody uses (it acts only where k-means
        had to share codewords: with at most ``k`` distinct points the fit is exact and returned as is); every label
        is the nearest centroid (float64 distances, before the cast); with a rate term the labels are the last
        assignment of least penalized distance and the centroids their clusters' means.
    """
    if x.ndim != 2 or x.shape[0] == 0:
        raise ValueError(f"kmeans needs a non-empty [n, d] tensor, got shape {tuple(x.shape)}")
    if k < 1:
        raise ValueError(f"kmeans needs k >= 1, got {k}")
    if not (math.isfinite(rate_weight) and rate_weight >= 0):
        raise ValueError(f"kmeans needs a finite rate_weight >= 0, got {rate_weight}")
    if not torch.isfinite(x).all():
        raise ValueError("kmeans input contains NaN or Inf")
    x = x.detach().cpu()
    if x.dtype not in (torch.float32, torch.float64):
        x = x.float()
    points, inverse, counts = _distinct_rows(x)
    if points.shape[0] <= k:
        return points, inverse
    pts, w = points.double(), counts.double()
    gen = torch.Generator().manual_seed(int(seed))
    centroids = pts[_init_centres(pts, w, k, gen, chunk)]
    previous = math.inf
    for _ in range(iters):
        d2, labels = nearest_centroid(pts, centroids, chunk)
        current = float((w * d2).sum())
        if math.isfinite(previous) and previous - current <= tol * previous:
            break
        previous = current
        centroids = _update(pts, w, labels, d2, centroids)
    d2, labels = nearest_centroid(pts, centroids, chunk)
    if rate_weight > 0:
        lam = rate_weight * float((w * d2).sum() / w.sum())
        centroids, labels = entropy_constrained(pts, w, centroids, labels, lam, iters, chunk, tol)
    return centroids.to(x.dtype), labels[inverse]


def penalized_nearest(x: torch.Tensor, c: torch.Tensor, penalty: torch.Tensor, chunk: int = 1 << 23) -> torch.Tensor:
    """Labels [n] int64 minimizing ``‖x − c_j‖² + penalty_j`` (float64; x [n, d], c [k, d], penalty [k])."""
    cd = c.double()
    return _argmin_by_products(x.double(), cd, (cd * cd).sum(1) + penalty.double(), chunk)


def entropy_constrained(x: torch.Tensor, w: torch.Tensor, centroids: torch.Tensor, labels: torch.Tensor, lam: float,
                        iters: int = 100, chunk: int = 1 << 23, tol: float = 1e-4) -> tuple[torch.Tensor, torch.Tensor]:
    """Entropy-constrained VQ (Chou, Lookabaugh & Gray 1989) from a starting codebook.

    Minimizes ``J = Σ_i w_i (‖x_i − c_{l_i}‖² + λ·log2(W / W_{l_i}))`` (W_l the weight of cluster l, W the
    total) by alternating its three exact minimizations — labels for fixed codewords and code lengths,
    codewords as the weighted means of their points, code lengths as the shares' self-information —
    so J never rises; clusters left empty are dropped. Stops when J falls by less than ``tol·J``.

    Args:
        x: points [n, d] float64; w: weights [n]; centroids: [k, d]; labels: [n] a starting assignment;
        lam: λ > 0, squared distance per bit.
    Returns:
        (centroids [k', d] float64 of the clusters in use, labels [n] into them).
    """
    total, previous = float(w.sum()), math.inf
    for _ in range(iters):
        centroids, labels, mass = _means_of_used(x, w, labels, centroids.shape[0])
        bits = torch.log2(total / mass)
        cost = float((w * ((x - centroids[labels]).square().sum(1) + lam * bits[labels])).sum())
        if math.isfinite(previous) and previous - cost <= tol * previous:
            return centroids, labels
        previous = cost
        labels = penalized_nearest(x, centroids, lam * bits, chunk)
    centroids, labels, _ = _means_of_used(x, w, labels, centroids.shape[0])
    return centroids, labels


def _means_of_used(x: torch.Tensor, w: torch.Tensor, labels: torch.Tensor, k: int
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(weighted means [k', d], labels renumbered [n], weights [k']) of the k' non-empty clusters of ``labels`` < k."""
    mass, sums = _cluster_sums(x, w, labels, k)
    used = mass > 0
    return sums[used] / mass[used][:, None], (torch.cumsum(used.long(), 0) - 1)[labels], mass[used]


def inertia(x: torch.Tensor, centroids: torch.Tensor, labels: torch.Tensor) -> float:
    """Sum of squared distances of ``x: [n, d]`` to their assigned ``centroids[labels]`` (float64)."""
    return float((x.double() - centroids.double()[labels]).square().sum())
