"""Fine-tuning views drawn by each span's fall below the baseline (omg4.compress.time_balance)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from omg4.compress import time_balance
from omg4.compress.pipeline import CompressConfig, CompressionPipeline
from omg4.compress.schedule import StageLengths
from omg4.compress.time_balance import DeficitSampler
from omg4.errors import OMG4Error
from omg4.train import make_config
from omg4.train.trainer import initial_model

FRAMES, CAMERAS = 20, 3


def views():
    """Every camera at every frame, shuffled (the sampler must not rely on the order)."""
    out = [SimpleNamespace(timestamp=f / 30, camera=SimpleNamespace(name=f"cam{c:02d}"), frame=f)
           for f in range(FRAMES) for c in range(CAMERAS)]
    order = np.random.default_rng(0).permutation(len(out))
    return [out[i] for i in order]


def test_each_view_falls_in_its_tenth_of_the_clip_and_every_tenth_has_its_probes():
    vs = views()
    sampler = DeficitSampler(vs, lambda batch: [0.0] * len(batch))
    assert sampler.bucket_of_view.tolist() == [v.frame // 2 for v in vs]  # 20 frames, 10 spans of 2 frames
    per_bucket = {}
    for b, i in sampler.probes:
        assert vs[i].frame // 2 == b
        per_bucket.setdefault(b, []).append(i)
    assert sorted(per_bucket) == list(range(10))
    assert all(len(set(p)) == time_balance.PROBES_PER_BUCKET for p in per_bucket.values())


def test_a_span_that_fell_further_is_drawn_more_often_by_the_stated_rule():
    vs = views()
    quality = {"now": lambda v: 30.0}
    sampler = DeficitSampler(vs, lambda batch: [quality["now"](v) for v in batch])
    sampler.start()
    # span 0 now 1 dB below its baseline, span 9 0.1 dB, the rest unchanged: mean fall 0.11 dB
    quality["now"] = lambda v: 30.0 - {0: 1.0, 9: 0.1}.get(v.frame // 2, 0.0)
    falls = sampler.update()
    np.testing.assert_allclose(falls, [1.0] + [0.0] * 8 + [0.1], atol=1e-12)
    mean = 1.1 / 10
    expected = [min(4.0, 2 ** ((1.0 - mean) / 0.25))] + [2 ** (-mean / 0.25)] * 8 + [2 ** ((0.1 - mean) / 0.25)]
    np.testing.assert_allclose(sampler.weights, expected, rtol=1e-12)
    assert sampler.weights[0] == 4.0  # clipped at MAX_RATIO
    draws = sampler.draw(40_000, torch.Generator().manual_seed(1))
    share = np.bincount(sampler.bucket_of_view[draws].numpy(), minlength=10) / len(draws)
    np.testing.assert_allclose(share, np.array(expected) / sum(expected), atol=0.01)


def test_a_tenth_without_frames_is_logged_as_a_dash_not_nan():
    vs = [SimpleNamespace(timestamp=f / 8, camera=SimpleNamespace(name="cam00"), frame=f) for f in range(8)]
    quality = {"now": lambda v: 30.0}
    sampler = DeficitSampler(vs, lambda batch: [quality["now"](v) for v in batch])
    sampler.start()
    quality["now"] = lambda v: 30.0 - (1.0 if v.frame == 0 else 0.0)
    line = sampler.describe(sampler.update())
    assert "nan" not in line
    falls, weights = (part.split()[-10:] for part in line.split(";"))
    # 8 frames in 10 tenths: frame f in tenth 10 f // 8, so tenths 4 and 9 hold none
    assert [i for i, f in enumerate(falls) if f == "-"] == [4, 9] == [i for i, w in enumerate(weights) if w == "-"]
    assert falls[0] == "+1.00" and weights[0] == "4.00" and falls[1] == "+0.00"


def test_no_fall_anywhere_draws_uniformly():
    sampler = DeficitSampler(views(), lambda batch: [25.0] * len(batch))
    sampler.start()
    sampler.update()
    np.testing.assert_array_equal(sampler.weights, np.ones(10))


def test_a_span_better_than_the_rest_is_drawn_less_but_never_below_the_floor():
    vs = views()
    quality = {"now": lambda v: 30.0}
    sampler = DeficitSampler(vs, lambda batch: [quality["now"](v) for v in batch])
    sampler.start()
    quality["now"] = lambda v: 30.0 + (3.0 if v.frame < 2 else 0.0)  # span 0 gained 3 dB
    sampler.update()
    assert sampler.weights[0] == pytest.approx(1 / time_balance.MAX_RATIO)
    assert sampler.weights[1] == pytest.approx(2 ** (0.3 / 0.25))


def test_the_pipeline_measures_the_baseline_first_and_draws_every_batch_from_the_sampler(tiny_scene, monkeypatch):
    cfg = make_config("cpu-small", num_random_points=300, max_gaussians=300, backend="cpu")
    model = initial_model(tiny_scene, cfg)
    calls = {"start": [], "draw": 0, "update": 0}
    start, draw = DeficitSampler.start, DeficitSampler.draw

    def recording_start(self):
        calls["start"].append(pipeline.model.num_gaussians)
        start(self)

    def recording_draw(self, count, generator):
        calls["draw"] += 1
        return draw(self, count, generator)

    monkeypatch.setattr(DeficitSampler, "start", recording_start)
    monkeypatch.setattr(DeficitSampler, "draw", recording_draw)
    lengths = StageLengths(sample=3, prune=4, merge=0, appearance=0, svq3d=0, svq4d=0)
    compress_cfg = CompressConfig(preset="M", stages=("sample", "prune"), lengths=lengths, batch_size=1,
                                  backend="cpu", time_sampling="deficit")
    pipeline = CompressionPipeline(model, tiny_scene, compress_cfg, progress=False, log=lambda *_: None)
    pipeline.run()
    assert calls["start"] == [300]  # the baseline, before sampling
    assert calls["draw"] == 7  # every fine-tuning step
    assert pipeline.time_balance.reference is not None and np.isfinite(pipeline.time_balance.reference).any()


def test_the_deficit_draw_is_the_default_the_paper_draw_a_switch_and_an_unknown_one_is_refused(tiny_scene):
    assert CompressConfig().choice("time_sampling") == "deficit"
    model = initial_model(tiny_scene, make_config("cpu-small", num_random_points=50, max_gaussians=50, backend="cpu"))
    default = CompressionPipeline(model, tiny_scene, CompressConfig(backend="cpu"), progress=False)
    assert isinstance(default.time_balance, DeficitSampler)
    paper = CompressConfig(backend="cpu", time_sampling="uniform")
    assert CompressionPipeline(model, tiny_scene, paper, progress=False).time_balance is None
    with pytest.raises(OMG4Error, match="unknown time sampling 'errors'"):
        CompressionPipeline(model, tiny_scene, CompressConfig(backend="cpu", time_sampling="errors"), progress=False)

