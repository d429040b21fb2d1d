"""OMG4 Gaussian Merging, cluster building (paper §4.3 "Gaussian Clustering", Eq. 3–4, Alg. 1).

Gaussians are binned into 4D cells ``(⌊x/g⌋, ⌊y/g⌋, ⌊z/g⌋, ⌊(t − t0)/(φ·D)⌋)`` (g: spatial cell in
normalized units, φ: time cell as a fraction of the duration D). Within a cell, for pairs i < j
(omg4 §6a):

    sim_ij = −‖x̂_i − x̂_j‖² − λ‖f̂_i − f̂_j‖²    (x̂: robust-normalized positions, f̂: min-max DC)
    thr    = max(τ_sim, Q_0.7(sims of the cell))
    C_i    = {i} ∪ {j > i : sim_ij ≥ thr}          (star clusters, kept when |C_i| ≥ 2)

Duplicates and subsets are removed, leaving the maximal clusters (omg4 §6a), which may
overlap; :func:`make_disjoint` then gives every Gaussian to one group (omg4 §14.7).

Everything is vectorized in torch (one algorithm, read top to bottom, which is why the module runs past 400
lines). The work is organised in *chunks of whole cells* whose pair count is bounded by ``MergeConfig.pair_chunk``
(a Python loop over chunks, never over cells):

* pairs of a cell are enumerated by a segmented ``repeat_interleave`` scheme;
* per-cell quantiles come from a segmented sort (by similarity, then stably by cell) of only the
  pairs above τ_sim (:func:`_cell_thresholds`);
* neighbour sets N(i) = C_i \\ {i} are bit rows (32 bits per int64 word, one row per centre);
* subset/duplicate removal is local: ``C_i ⊆ C_k`` needs ``i ∈ C_k``, i.e. an edge k → i with
  k < i, and then ``C_i ⊆ C_k ⇔ N(i) ⊆ N(k)`` (k ∉ C_i because k < i). So C_i is dropped iff
  some edge k → i has ``N(i) & ~N(k) = 0`` on every nonzero word of N(i). This removes strict
  subsets and, among equal sets, every copy but the one with the smallest centre — exactly the
  maximal distinct sets the official greedy (dedup, sort by size, drop subsets of kept sets)
  returns, since a subset of a dropped set is also a subset of the set that dropped it.

Pathological cells: a cell with more than ``max_cell_size`` members is split deterministically
into ``⌈m / max_cell_size⌉`` near-equal slabs along x (members ranked by x, ties by index); each
slab is then treated as a cell (its own pairs and quantile). This bounds the pairs per cell
(the official code instead falls back to ``thr = τ_sim`` when a cell has more than 16M pairs).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from omg4.errors import OMG4Error
from omg4.settings import knob

_WORD_BITS = 32  # bits used per int64 word of a neighbour bit row (no sign-bit arithmetic)


@dataclass
class MergeConfig:
    """Gaussian Merging hyperparameters (paper §4.3, §5.1; official configs, omg4 §6a)."""

    grid_size: float = knob(0.1, "spatial cell g of the first round (normalized units)")
    time_cell_fraction: float = knob(0.2, "temporal cell φ as a fraction of the clip (official 2.0 s of 10 s)")
    grid_growth: float = knob(1.2, "the spatial cell grows by this factor each round")
    color_weight: float = knob(4.0, "λ: weight of the colour distance in the similarity")
    tau_sim: float = knob(-3e-4, "similarity floor τ_sim of the per-cell threshold (the configs' sign)")
    sim_quantile: float = knob(0.7, "per-cell quantile of the similarities")
    logit_lr: float = knob(0.01, "learning rate of the merge weights")
    max_cell_size: int = knob(2048, "larger cells are split into slabs along x")
    pair_chunk: int = knob(2_000_000, "pairs processed at once (bounds memory, not the result)")


@dataclass
class MergeGroups:
    """Disjoint merge groups; each Gaussian is in at most one group.

    members: [M] int64 Gaussian indices, grouped contiguously, ascending within a group
    group_of: [M] int64 group id of each member (0..G-1), sorted
    representative: [G] int64 Gaussian index of each group's representative (its smallest index);
        groups are ordered by representative
    """

    members: torch.Tensor
    group_of: torch.Tensor
    representative: torch.Tensor

    @property
    def num_groups(self) -> int:
        return int(self.representative.shape[0])

    @property
    def num_removed(self) -> int:
        """Gaussians removed when the groups are baked (members − representatives)."""
        return int(self.members.shape[0]) - self.num_groups


@dataclass
class StarClusters:
    """Maximal star clusters before the disjointness step (may overlap).

    centre: [C] int64 Gaussian index of each cluster's centre i (ascending; also its smallest member)
    members: [K] int64 Gaussian indices, cluster-contiguous, ascending within a cluster (centre first)
    cluster_of: [K] int64 cluster id (0..C-1) of each member, sorted
    """

    centre: torch.Tensor
    members: torch.Tensor
    cluster_of: torch.Tensor

    def as_sets(self) -> set[frozenset[int]]:
        """The clusters as a set of frozensets (for inspection and tests)."""
        bounds = torch.cumsum(torch.bincount(self.cluster_of, minlength=len(self.centre)), 0).tolist()
        flat = self.members.tolist()
        return {frozenset(flat[a:b]) for a, b in zip([0] + bounds[:-1], bounds)}


# ---------------------------------------------------------------------------- normalization
def _sorted_quantile(sorted_values: torch.Tensor, q: float) -> torch.Tensor:
    """Linear-interpolation q-quantile (torch.quantile's rule) along dim 0 of sorted values.

    sorted_values: [N, ...] ascending along dim 0 → [...]
    """
    pos = q * (sorted_values.shape[0] - 1)
    lo = int(pos)
    hi = min(lo + 1, sorted_values.shape[0] - 1)
    return torch.lerp(sorted_values[lo], sorted_values[hi], pos - lo)


def robust_normalize_positions(xyz: torch.Tensor) -> torch.Tensor:
    """x̂ = (x − Q_0.001) / (Q_0.999 − Q_0.001 + 1e-6) per axis over all Gaussians (omg4 §6a).

    xyz: [N, 3] → [N, 3] float64
    """
    x = xyz.to(torch.float64)
    srt = torch.sort(x, dim=0).values
    lo, hi = _sorted_quantile(srt, 0.001), _sorted_quantile(srt, 0.999)
    return (x - lo) / (hi - lo + 1e-6)


def minmax_normalize_colors(dc: torch.Tensor) -> torch.Tensor:
    """f̂ = (f − min) / (max − min + 1e-6) per channel over all Gaussians (omg4 §6a).

    dc: [N, 3] → [N, 3] float64
    """
    f = dc.to(torch.float64)
    lo, hi = f.min(0).values, f.max(0).values
    return (f - lo) / (hi - lo + 1e-6)


def merge_cells(xyz: torch.Tensor, t: torch.Tensor, time_range: tuple[float, float], grid_size: float,
                time_cell_fraction: float) -> torch.Tensor:
    """Dense id of each Gaussian's 4D cell (⌊x/g⌋, ⌊y/g⌋, ⌊z/g⌋, ⌊(t − t0)/(φ·D)⌋) (paper §4.3).

    xyz: [N, 3], t: [N] → [N] int64 in 0..(#cells − 1), ordered lexicographically by cell key
    """
    t0, t1 = time_range
    key = torch.cat([torch.floor(xyz.to(torch.float64) / grid_size),
                     torch.floor((t.to(torch.float64) - t0) / (time_cell_fraction * (t1 - t0)))[:, None]], 1)
    return torch.unique(key.to(torch.int64), dim=0, return_inverse=True)[1]


def _split_large_cells(cell: torch.Tensor, x: torch.Tensor, cap: int) -> torch.Tensor:
    """Cells with more than ``cap`` members split into ⌈m/cap⌉ near-equal slabs along x.

    cell: [N] dense cell ids, x: [N] first coordinate → [N] dense block ids
    """
    size = torch.bincount(cell)
    if int(size.max()) <= cap:
        return cell
    order = torch.sort(x.to(torch.float64), stable=True).indices
    order = order[torch.sort(cell[order], stable=True).indices]  # by cell, then x, then index
    c = cell[order]
    start = torch.cumsum(size, 0) - size
    rank = torch.arange(len(c)) - start[c]
    pieces = (size + cap - 1) // cap
    sub = rank * pieces[c] // size[c]
    change = torch.ones(len(c), dtype=torch.bool)
    change[1:] = (c[1:] != c[:-1]) | (sub[1:] != sub[:-1])
    block = torch.empty_like(cell)
    block[order] = torch.cumsum(change.to(torch.int64), 0) - 1
    return block


# ------------------------------------------------------------------------------ per chunk
def _bit_rows(ea: torch.Tensor, eb: torch.Tensor, rank: torch.Tensor, words: torch.Tensor,
              has_row: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Neighbour sets N(a) as bit rows: bit ``rank[b]`` of row a is set for every edge a → b.

    ea, eb: [E] positions, sorted by (a, b); rank: [n] rank within the block; words: [n] words per
    row of that block; has_row: [n] bool → (bits [total words] int64, row_off [n], nz_addr [Z]
    addresses of the nonzero words (row by row, ascending), nz_start [n], nz_count [n] per row)
    """
    width = words * has_row
    row_off = torch.cumsum(width, 0) - width
    addr = row_off[ea] + rank[eb] // _WORD_BITS  # ascending
    bits = torch.zeros(int(width.sum()), dtype=torch.int64)
    bits.index_add_(0, addr, torch.bitwise_left_shift(torch.ones_like(eb), rank[eb] % _WORD_BITS))
    new = torch.ones(len(addr), dtype=torch.bool)
    new[1:] = addr[1:] != addr[:-1]
    nz_count = torch.bincount(ea[new], minlength=len(rank))
    return bits, row_off, addr[new], torch.cumsum(nz_count, 0) - nz_count, nz_count


def _subset_of_source(ca: torch.Tensor, cb: torch.Tensor, bits: torch.Tensor, row_off: torch.Tensor,
                      nz_addr: torch.Tensor, nz_start: torch.Tensor, nz_count: torch.Tensor) -> torch.Tensor:
    """For candidate edges a → b: is N(b) ⊆ N(a)? ``N(b)_w & ~N(a)_w == 0`` for every word w.

    Only the nonzero words of row b are scanned, with a per-candidate pointer; a candidate leaves
    the scan at its first violating word or after its last word, so the loop runs at most
    ``max(nonzero words per row)`` times over a shrinking set (never over clusters).
    ca, cb: [K] positions with non-empty bit rows; other arguments from :func:`_bit_rows` → [K] bool
    """
    subset = torch.zeros(len(ca), dtype=torch.bool)
    idx, ptr = torch.arange(len(ca)), nz_start[cb]
    end, shift = ptr + nz_count[cb], row_off[ca] - row_off[cb]  # shift: same word in row a
    while len(idx):
        addr = nz_addr[ptr]
        ok = (bits[addr] & ~bits[addr + shift]) == 0
        ptr = ptr + 1
        done = ok & (ptr >= end)
        subset[idx[done]] = True
        go_on = ok & ~done
        idx, ptr, end, shift = idx[go_on], ptr[go_on], end[go_on], shift[go_on]
    return subset


def _cell_thresholds(sim: torch.Tensor, pblock: torch.Tensor, npairs: torch.Tensor, cfg: MergeConfig) -> torch.Tensor:
    """thr_b = max(τ_sim, Q_q(sims of block b)) (omg4 §6a), by a segmented sort.

    Only the pairs with sim > τ are sorted: with v_0 ≤ … ≤ v_{P−1} the sorted sims and c_b of them
    above τ, the quantile lerp(v_lo, v_hi) can exceed τ only if hi ≥ P − c_b; then v_hi is among the
    sorted ones and v_lo too, or v_lo = v_{P−c_b−1} = the largest sim ≤ τ. Same values as a full sort.
    sim, pblock: [P] (pblock sorted); npairs: [B] pairs per block → [B]
    """
    above = sim > cfg.tau_sim
    nb = len(npairs)
    count = torch.bincount(pblock[above], minlength=nb)
    pos = cfg.sim_quantile * (npairs - 1).to(torch.float64)
    lo = pos.floor().to(torch.int64)
    hi = torch.minimum(lo + 1, npairs - 1)
    base = npairs - count  # full-order index of the first pair above τ
    need = hi >= base
    thr = torch.full((nb,), cfg.tau_sim, dtype=sim.dtype)
    if not bool(need.any()):
        return thr
    sel = above & need[pblock]
    srt, order = torch.sort(sim[sel], stable=True)
    srt = srt[torch.sort(pblock[sel][order], stable=True).indices]
    low = ~above & need[pblock]
    below_max = torch.full((nb,), -torch.inf, dtype=sim.dtype)
    below_max.scatter_reduce_(0, pblock[low], sim[low], reduce="amax")
    b = torch.nonzero(need).squeeze(1)
    start = torch.cumsum(count[b], 0) - count[b]  # of each needed block in ``srt``

    def value(i: torch.Tensor) -> torch.Tensor:  # v_i of the needed blocks
        return torch.where(i >= base[b], srt[start + (i - base[b]).clamp(min=0)], below_max[b])

    frac = (pos - lo.to(torch.float64)).to(sim.dtype)[b]
    thr[b] = torch.lerp(value(lo[b]), value(hi[b]), frac).clamp(min=cfg.tau_sim)
    return thr


def _pair_similarity(x: torch.Tensor, f: torch.Tensor, first: torch.Tensor, second: torch.Tensor,
                     color_weight: float) -> torch.Tensor:
    """sim = −‖x̂_p − x̂_q‖² − λ‖f̂_p − f̂_q‖² for pairs (p, q) (paper §4.3 Eq. 3, with omg4 §6a signs).

    x, f: [n, 3]; first, second: [P] → [P]. Column by column (1-D gathers, in-place sums).
    """
    def sq_dist(v: torch.Tensor) -> torch.Tensor:
        total = torch.zeros(len(first), dtype=v.dtype)
        for col in v.T.contiguous():  # the 3 coordinates
            d = col[first] - col[second]
            total.add_(d.square_())
        return total

    return sq_dist(x).neg_().sub_(sq_dist(f).mul_(color_weight))


def _chunk_clusters(gidx: torch.Tensor, block: torch.Tensor, rank: torch.Tensor, block_size: torch.Tensor,
                    xn: torch.Tensor, fn: torch.Tensor, cfg: MergeConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Maximal star clusters of a chunk of whole cells, as (centre, member) Gaussian index pairs.

    gidx: [n] Gaussian indices ordered by (block, index); block: [n] chunk-local block ids (sorted);
    rank: [n] position within the block; block_size: [B] members per block (≥ 2);
    xn, fn: [N, 3] normalized positions and colours → (centre [K], member [K]) incl. (c, c)
    """
    n = len(gidx)
    m = block_size[block]
    count = m - 1 - rank  # pairs (p, q) with p < q in the block, p first
    first = torch.repeat_interleave(torch.arange(n), count)
    second = first + 1 + torch.arange(len(first)) - (torch.cumsum(count, 0) - count)[first]
    sim = _pair_similarity(xn[gidx], fn[gidx], first, second, cfg.color_weight)

    pblock = block[first]
    thr = _cell_thresholds(sim, pblock, block_size * (block_size - 1) // 2, cfg)
    edge = sim >= thr[pblock]
    ea, eb = first[edge], second[edge]  # a < b in the block ⇒ gidx[a] < gidx[b]
    del first, second, sim, pblock, edge

    # subset / duplicate removal: drop C_b when some edge a → b has N(b) ⊆ N(a)
    outdeg = torch.bincount(ea, minlength=n)
    words = (block_size[block] + _WORD_BITS - 1) // _WORD_BITS
    rows = _bit_rows(ea, eb, rank, words, outdeg > 0)
    cand = (outdeg[eb] >= 1) & (outdeg[eb] <= outdeg[ea] - 1)
    ca, cb = ea[cand], eb[cand]
    removed = torch.zeros(n, dtype=torch.bool)
    removed[cb[_subset_of_source(ca, cb, *rows)]] = True

    centre = torch.nonzero((outdeg > 0) & ~removed).squeeze(1)
    keep = ~removed[ea]
    c = torch.cat([centre, ea[keep]])
    member = torch.cat([centre, eb[keep]])
    return gidx[c], gidx[member]


# --------------------------------------------------------------------------------- public
def _validate(xyz: torch.Tensor, t: torch.Tensor, dc: torch.Tensor, time_range: tuple[float, float],
              grid_size: float, cfg: MergeConfig) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    n = xyz.shape[0]
    if xyz.shape != (n, 3) or t.numel() != n or dc.numel() != 3 * n:
        raise OMG4Error(f"merging needs xyz [N,3], t [N(,1)], dc [N(,1),3]; got {tuple(xyz.shape)}, "
                        f"{tuple(t.shape)}, {tuple(dc.shape)}")
    if not grid_size > 0 or not cfg.time_cell_fraction > 0 or not time_range[1] > time_range[0]:
        raise OMG4Error(f"merging needs positive cell sizes and t1 > t0; got grid {grid_size}, "
                        f"time cell fraction {cfg.time_cell_fraction}, time range {tuple(time_range)}")
    if cfg.max_cell_size < 2 or cfg.pair_chunk < 1:
        raise OMG4Error(f"merging needs max_cell_size ≥ 2 and pair_chunk ≥ 1; got {cfg.max_cell_size}, "
                        f"{cfg.pair_chunk}")
    xyz, t, dc = xyz.detach().cpu(), t.detach().cpu().reshape(n), dc.detach().cpu().reshape(n, 3)
    bad = ~(torch.isfinite(xyz).all(1) & torch.isfinite(t) & torch.isfinite(dc).all(1))
    if bool(bad.any()):
        raise OMG4Error(f"merging: {int(bad.sum())} Gaussians have non-finite position, time or colour")
    return xyz, t, dc


def _empty_clusters() -> StarClusters:
    e = torch.zeros(0, dtype=torch.int64)
    return StarClusters(e, e.clone(), e.clone())


def build_star_clusters(xyz: torch.Tensor, t: torch.Tensor, dc: torch.Tensor, time_range: tuple[float, float],
                        grid_size: float, cfg: MergeConfig) -> StarClusters:
    """Maximal star clusters C_i (paper §4.3 Eq. 4; omg4 §6a), before disjointness.

    xyz: [N, 3] normalized world; t: [N] or [N, 1] dataset time units; dc: [N, 3] or [N, 1, 3] SH DC;
    time_range: (t0, t1); grid_size: spatial cell g of this round. Results live on the CPU.
    """
    xyz, t, dc = _validate(xyz, t, dc, time_range, grid_size, cfg)
    if xyz.shape[0] < 2:
        return _empty_clusters()
    xn, fn = robust_normalize_positions(xyz), minmax_normalize_colors(dc)
    block = _split_large_cells(merge_cells(xyz, t, time_range, grid_size, cfg.time_cell_fraction), xyz[:, 0],
                               cfg.max_cell_size)
    size = torch.bincount(block)
    gidx = torch.nonzero(size[block] >= 2).squeeze(1)  # Gaussians sharing their cell with someone
    if len(gidx) == 0:
        return _empty_clusters()
    gidx = gidx[torch.sort(block[gidx], stable=True).indices]  # by (block, index)
    _, local_block = torch.unique_consecutive(block[gidx], return_inverse=True)
    bsize = torch.bincount(local_block)
    bstart = torch.cumsum(bsize, 0) - bsize
    rank = torch.arange(len(gidx)) - bstart[local_block]
    npairs = bsize * (bsize - 1) // 2
    chunk = (torch.cumsum(npairs, 0) - npairs) // cfg.pair_chunk
    bounds = torch.cumsum(torch.bincount(chunk), 0).tolist()  # block ranges of the chunks
    centres, members = [], []
    b0 = 0
    for b1 in bounds:
        if b1 == b0:
            continue
        p0, p1 = int(bstart[b0]), int(bstart[b1 - 1] + bsize[b1 - 1])
        c, mem = _chunk_clusters(gidx[p0:p1], local_block[p0:p1] - b0, rank[p0:p1], bsize[b0:b1], xn, fn, cfg)
        centres.append(c)
        members.append(mem)
        b0 = b1
    centre, member = torch.cat(centres), torch.cat(members)
    n = xyz.shape[0]
    pair = torch.sort(centre * n + member).values
    centre_ids, cluster_of = torch.unique_consecutive(pair // n, return_inverse=True)
    return StarClusters(centre_ids, pair % n, cluster_of)


def make_disjoint(clusters: StarClusters, num_gaussians: int) -> MergeGroups:
    """Disjoint merge groups from overlapping maximal clusters (omg4 §14.7).

    Rule: clusters are ranked by size (descending), ties by centre index (ascending). Every
    Gaussian goes to the highest-ranked cluster that contains it (equivalently: process the
    clusters in rank order and let each claim its still-unclaimed members). A cluster left with
    fewer than 2 members is dropped; its remaining member stays an unmerged singleton. Each
    group's representative is its smallest index, and groups are ordered by representative.
    """
    c = len(clusters.centre)
    empty = torch.zeros(0, dtype=torch.int64)
    if c == 0:
        return MergeGroups(empty, empty.clone(), empty.clone())
    size = torch.bincount(clusters.cluster_of, minlength=c)
    prio = torch.empty(c, dtype=torch.int64)
    prio[torch.sort(-size, stable=True).indices] = torch.arange(c)  # cluster ids ascend with the centre
    member_prio = prio[clusters.cluster_of]
    best = torch.full((num_gaussians,), c, dtype=torch.int64).scatter_reduce_(
        0, clusters.members, member_prio, reduce="amin")
    won = member_prio == best[clusters.members]
    valid = torch.bincount(clusters.cluster_of[won], minlength=c) >= 2
    sel = won & valid[clusters.cluster_of]
    member, owner = clusters.members[sel], clusters.cluster_of[sel]
    rep = torch.full((c,), num_gaussians, dtype=torch.int64).scatter_reduce_(0, owner, member, reduce="amin")
    key = torch.sort(rep[owner] * num_gaussians + member).values
    representative, group_of = torch.unique_consecutive(key // num_gaussians, return_inverse=True)
    return MergeGroups(key % num_gaussians, group_of, representative)


def build_merge_groups(xyz: torch.Tensor, t: torch.Tensor, dc: torch.Tensor, time_range: tuple[float, float],
                       grid_size: float, cfg: MergeConfig) -> MergeGroups:
    """Disjoint merge groups of one round (paper §4.3 clustering + omg4 §14.7 disjointness).

    xyz: [N, 3], t: [N] or [N, 1], dc: [N, 3] or [N, 1, 3]; see :func:`build_star_clusters` and
    :func:`make_disjoint`. Returned tensors are on ``xyz``'s device.
    """
    with torch.device("cpu"):  # the clustering runs on the CPU whatever the default device
        groups = make_disjoint(build_star_clusters(xyz, t, dc, time_range, grid_size, cfg), xyz.shape[0])
    dev = xyz.device
    return MergeGroups(groups.members.to(dev), groups.group_of.to(dev), groups.representative.to(dev))


__all__ = ["MergeConfig", "MergeGroups", "StarClusters", "build_merge_groups", "build_star_clusters",
           "make_disjoint", "merge_cells", "minmax_normalize_colors", "robust_normalize_positions"]
