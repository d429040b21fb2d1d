"""Rendering a long capture: a sequence of segments (an ``.omg4`` sequence file or a segmented training run), each
decoded when first shown.

:class:`SequenceModel` renders a sequence: at a time inside two segments it is both, blended
(:func:`omg4.data.segments.blend_weights`); at most two decoded segments are held, and the next one is decoded
ahead of playback. The file layout is :mod:`omg4.codec.sequence`'s.
"""

from __future__ import annotations

import dataclasses
import os
import threading
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable

from omg4.codec.sequence import SegmentDecoder
from omg4.data.segments import blend_weights
from omg4.errors import OMG4Error
from omg4.models.compact import CompactModel


class SequenceModel:
    """A render-only model of a sequence of segments: each segment a model loaded on demand by ``load(k)``.

    ``parts_at(t)`` gives the models to render at ``t`` with their blend weights (one, or two across a
    boundary); :func:`omg4.render.view.render_view` renders and blends them. At most ``keep`` decoded segments
    are held (two across a boundary plus the one decoded ahead).
    """

    def __init__(self, ranges: list[tuple[float, float]], load: Callable[[int], object], *, meta: dict | None = None,
                 num_gaussians: list[int] | None = None, storage_bytes: int | None = None, keep: int = 3):
        self.ranges = [tuple(r) for r in ranges]
        self._load = load
        self._cache: OrderedDict[int, object] = OrderedDict()
        self._ahead: dict[int, Future] = {}
        self._lock = threading.Lock()
        self._executor = ThreadPoolExecutor(max_workers=1)
        self.keep = keep
        self.storage_bytes = storage_bytes
        self.segment_gaussians = list(num_gaussians or [None] * len(ranges))
        first = self.segment(0)
        self.meta = {**getattr(first, "meta", {}), **(meta or {})}  # the scene's normalization, the frame rate
        self.config = dataclasses.replace(first.config, time_range=(self.ranges[0][0], self.ranges[-1][1]))
        self.active_sh_degree, self.active_sh_degree_t = first.active_sh_degree, first.active_sh_degree_t

    @property
    def num_segments(self) -> int:
        return len(self.ranges)

    @property
    def num_gaussians(self) -> int:
        """Gaussians of every segment (what the sequence stores; a frame shows one or two segments')."""
        return sum(n for n in self.segment_gaussians if n is not None)

    def segment(self, k: int):
        """Segment ``k``'s model (decoded once, kept while among the last :attr:`keep` used)."""
        with self._lock:
            if k in self._cache:
                self._cache.move_to_end(k)
                return self._cache[k]
            ahead = self._ahead.pop(k, None)
        model = ahead.result() if ahead is not None else self._load(k)
        with self._lock:
            self._cache[k] = model
            self._cache.move_to_end(k)
            while len(self._cache) > self.keep:
                self._cache.popitem(last=False)
        self.segment_gaussians[k] = model.num_gaussians
        return model

    def parts_at(self, time: float) -> list[tuple[object, float]]:
        """(segment model, weight) pairs to render and blend at ``time``; starts decoding the next segment."""
        weights = blend_weights(float(time), self.ranges)
        parts = [(self.segment(k), w) for k, w in weights]
        self._decode_ahead(weights[-1][0] + 1)
        return parts

    def segment_at(self, time: float):
        """The model of the segment weighing most at ``time`` (what one time slice of the sequence exports)."""
        return self.segment(max(blend_weights(float(time), self.ranges), key=lambda kw: kw[1])[0])

    @property
    def values(self) -> dict:
        """The first segment's per-Gaussian values (for the bounds a viewer frames its first camera by)."""
        return self.segment(0).values

    def _decode_ahead(self, k: int) -> None:
        with self._lock:
            if k >= len(self.ranges) or k in self._cache or k in self._ahead:
                return
            self._ahead = {k: self._executor.submit(self._load, k)}  # forget older look-aheads

    def to(self, device) -> "SequenceModel":
        raise OMG4Error("a sequence model is loaded on its device by load_model(path, device)")


def load_sequence(path: str | os.PathLike, device="cpu") -> SequenceModel:
    """A :class:`SequenceModel` of a sequence file on ``device``: its index now, each segment when first shown (a
    predicted one after the segments it is predicted from, :class:`~omg4.codec.sequence.SegmentDecoder`)."""
    decoder = SegmentDecoder(path)
    index = decoder.index

    def load(k: int):
        return CompactModel(decoder.payload(k), device)

    return SequenceModel([e.time_range for e in index.segments], load, meta={**index.meta, "fps": index.fps},
                         storage_bytes=index.total_bytes)


__all__ = ["SequenceModel", "load_sequence"]
