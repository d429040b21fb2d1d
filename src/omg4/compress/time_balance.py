"""Fine-tuning that keeps every span of the clip near its baseline (beyond the paper).

The paper fine-tunes on training views drawn uniformly (§5.1). Its stages do not cost every time alike: the
clip's ends lose most (docs/results.md, "Every frame"), and a uniform draw spends as many steps on the spans that
lost nothing. With ``time_sampling="deficit"`` the compression measures, on a few fixed training views of each of
:data:`BUCKETS` equal spans of the clip, how far each span's PSNR has fallen below the baseline's (measured once,
before the first stage), after every stage and every :data:`REFRESH` steps, and draws the views of a span
``2^(excess / TEMPERATURE_DB)`` times as often as uniform, ``excess`` its fall minus the mean fall over the spans
(clipped to a ratio of :data:`MAX_RATIO` either way). It is the default, with lifetime-weighted scores
(:func:`omg4.compress.score.lifetime_weights`); ``"uniform"`` is the paper's draw.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from omg4 import distributed
from omg4.data.scene import View

TIME_SAMPLINGS = ("uniform", "deficit")
"""How fine-tuning draws its views: ``uniform`` (the paper) or ``deficit`` (:class:`DeficitSampler`)."""

BUCKETS = 10
"""Equal spans of the clip (by frame) the deficit is measured and the draw weighted on."""

PROBES_PER_BUCKET = 4
"""Fixed training views per span the deficit is measured on."""

REFRESH = 100
"""Fine-tuning steps between two measurements (a stage's end measures too)."""

TEMPERATURE_DB = 0.25
"""A span this many dB further below its baseline than the mean span is drawn twice as often."""

MAX_RATIO = 4.0
"""No span is drawn more than this many times as often as uniform, nor less than its inverse."""


class DeficitSampler:
    """Draws fine-tuning views weighted by how far each span of the clip fell below its baseline.

    ``views``: the training views; ``views_psnr(views) -> [float]``: the PSNRs of the current model's renders of
    view (called under ``torch.no_grad``). In a distributed job each rank renders its share of the probe views
    and the sums are combined, so every rank holds the same weights and draws the same batch.
    """

    def __init__(self, views: list[View], views_psnr: Callable[[list[View]], list[float]], buckets: int = BUCKETS,
                 probes_per_bucket: int = PROBES_PER_BUCKET):
        times = sorted({v.timestamp for v in views})
        frame = {t: i for i, t in enumerate(times)}
        self.bucket_of_view = torch.tensor([frame[v.timestamp] * buckets // len(times) for v in views], device="cpu")
        self.buckets = buckets
        self.views, self.views_psnr = views, views_psnr
        self.probes = self._probes(probes_per_bucket)
        self.reference: np.ndarray | None = None
        self.weights = np.ones(buckets)  # per bucket, relative to uniform
        self.view_weights = torch.ones(len(views), dtype=torch.float64, device="cpu")  # each view's bucket weight

    def _probes(self, per_bucket: int) -> list[tuple[int, int]]:
        """(bucket, view index) pairs: ``per_bucket`` views of each bucket evenly spread in (time, camera) order."""
        order = sorted(range(len(self.views)), key=lambda i: (self.views[i].timestamp, self.views[i].camera.name))
        picks = []
        for b in range(self.buckets):
            members = [i for i in order if int(self.bucket_of_view[i]) == b]
            if members:
                at = np.linspace(0, len(members) - 1, min(per_bucket, len(members))).round().astype(int)
                picks += [(b, members[k]) for k in at]
        return picks

    def measure(self) -> np.ndarray:
        """Mean PSNR of each bucket's probe views now [buckets] (NaN for a bucket with no views)."""
        sums = torch.zeros(2, self.buckets, dtype=torch.float64, device="cpu")  # whatever the default device
        mine = distributed.world().shard(self.probes)
        with torch.no_grad():  # the probe views rendered together (one pass per image size)
            for (b, _), value in zip(mine, self.views_psnr([self.views[i] for _, i in mine])):
                sums[0, b] += value
                sums[1, b] += 1
        distributed.all_reduce_([sums], "sum", "measuring quality over the clip")
        with np.errstate(invalid="ignore"):
            return (sums[0] / sums[1]).numpy()

    def start(self) -> None:
        """Measure the baseline every later measurement is compared with."""
        self.reference = self.measure()

    def update(self) -> np.ndarray:
        """Re-weight the buckets from the current model's fall below the reference; returns the falls (dB)."""
        with np.errstate(invalid="ignore"):  # a model that renders its views exactly: inf - inf, no fall to weigh
            deficit = self.reference - self.measure()
        valid = np.isfinite(deficit)
        excess = np.where(valid, deficit - deficit[valid].mean(), 0.0) if valid.any() else np.zeros_like(deficit)
        self.weights = np.clip(np.exp2(excess / TEMPERATURE_DB), 1 / MAX_RATIO, MAX_RATIO)
        self.view_weights = torch.from_numpy(self.weights).index_select(0, self.bucket_of_view)
        return deficit

    def describe(self, deficit: np.ndarray) -> str:
        """One log line: each tenth's fall below the baseline (dB) and its draw weight; ``-`` for a tenth that holds
        no frame (a clip of fewer than :data:`BUCKETS` frames)."""
        empty = ~np.isfinite(deficit)
        falls = " ".join("-" if e else f"{d:+.2f}" for d, e in zip(deficit, empty))
        weights = " ".join("-" if e else f"{w:.2f}" for w, e in zip(self.weights, empty))
        return f"fall below the baseline by tenth of the clip (dB) {falls}; draw weights {weights}"

    def draw(self, count: int, generator: torch.Generator) -> torch.Tensor:
        """``count`` view indices (with replacement), each view drawn with its bucket's weight."""
        return torch.multinomial(self.view_weights, count, replacement=True, generator=generator)


__all__ = ["BUCKETS", "MAX_RATIO", "PROBES_PER_BUCKET", "REFRESH", "TEMPERATURE_DB", "TIME_SAMPLINGS",
           "DeficitSampler"]
