"""What each OMG4 stage and each merge round is given in a pipeline run (paper §4, §5.1; appendix presets).

The stage functions are wrapped so that every call is recorded and then passed through unchanged: the
test states, from the paper's settings written out here, which ratio, quantile, grid, codebook size,
seed and iteration count each call must receive — not only the Gaussian counts that come out.
"""

from __future__ import annotations

import math

import pytest
import torch

from omg4.compress import appearance_stage, merging
from omg4.compress import pipeline as pl
from omg4.compress.pipeline import CompressConfig, CompressionPipeline
from omg4.compress.schedule import StageLengths
from omg4.compress.score import UNRANKED, SDScores
from omg4.compress.svq import SubVectorQuantizer
from omg4.train import make_config
from omg4.train.trainer import initial_model

LENGTHS = StageLengths(sample=3, prune=4, merge=5, appearance=6, svq3d=7, svq4d=2)

#: the paper's appendix: (τ_GS, p) and the codebook sizes of each preset (T's τ_GS inferred from Table 1)
PAPER_PRESETS = {
    "rt4dgs": {
        "L": (0.4, 0.8, {"scale": 512, "rotation": 8192, "app": 1024, "scale_t": 512, "rotation_r": 8192}),
        "M": (0.2, 0.8, {"scale": 512, "rotation": 8192, "app": 1024, "scale_t": 512, "rotation_r": 8192}),
        "S": (0.3, 0.9, {"scale": 256, "rotation": 8192, "app": 1024, "scale_t": 512, "rotation_r": 8192}),
        "T": (0.25, 0.9, {"scale": 256, "rotation": 8192, "app": 1024, "scale_t": 512, "rotation_r": 8192}),
    },
    "freetimegs": {
        "L": (0.7, 0.6, {"scale": 512, "rotation": 8192, "app": 1024, "duration": 1024, "velocity": 1024}),
        "S": (0.3, 0.4, {"scale": 512, "rotation": 8192, "app": 1024, "duration": 1024, "velocity": 1024}),
    },
}
#: sub-vector lengths (OMG's): scale 1, rotation 2, appearance 2, time scale 1, right quaternion 2; FreeTimeGS's
#: duration and velocity 1; and the per-Gaussian widths they split
SUB_LENGTHS = {"scale": (1, 3), "rotation": (2, 4), "app": (2, 6), "scale_t": (1, 1), "rotation_r": (2, 4),
               "duration": (1, 1), "velocity": (1, 3)}
STAGE_3D = ("scale", "rotation", "app")


def baseline(scene, backbone="rt4dgs", n=400):
    cfg = make_config("cpu-small", num_random_points=n, max_gaussians=n, backbone=backbone, backend="cpu")
    return initial_model(scene, cfg)


def scores(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    return SDScores(torch.rand(n, generator=g, dtype=torch.float64),
                    torch.randn(n, generator=g, dtype=torch.float64),
                    torch.full((n,), UNRANKED))  # no frame's own largest: the frame floor adds nothing to Eq. 2


class Recorder:
    """Wraps the stage functions the pipeline calls; each call appends (name, arguments) and passes through."""

    def __init__(self, monkeypatch):
        self.calls: list[tuple[str, dict]] = []
        self.events: list[tuple[str, int, int]] = []
        sampling, pruning = pl.sampling_mask, pl.pruning_mask
        groups, mlp_opt, fit = merging.build_merge_groups, appearance_stage.make_mlp_optimizer, SubVectorQuantizer.fit
        mlp_class, apply_event = pl.AppearanceMLP, pl.CompressionPipeline.apply_event

        def sampling_mask(s, ratio):
            self.calls.append(("sample", {"n": s.static.shape[0], "ratio": ratio}))
            return sampling(s, ratio)

        def pruning_mask(s, p, frame_floor=0.0):
            self.calls.append(("prune", {"n": s.static.shape[0], "p": p, "static": s.static.clone(),
                                         "frame_floor": frame_floor}))
            return pruning(s, p, frame_floor)

        def build_merge_groups(xyz, t, dc, time_range, grid, mc):
            self.calls.append(("merge", {"n": xyz.shape[0], "grid": grid, "time_range": time_range, "config": mc,
                                         "xyz": xyz.clone(), "dc": dc.clone()}))
            return groups(xyz, t, dc, time_range, grid, mc)

        def make_mlp_optimizer(mlp, **kw):
            self.calls.append(("mlp optimizer", kw))
            return mlp_opt(mlp, **kw)

        def appearance_mlp(**kw):
            self.calls.append(("mlp", kw))
            return mlp_class(**kw)

        def quantizer_fit(values, sub_len, codebook_size, seed=0, **kw):
            self.calls.append(("svq", {"width": values.shape[1], "sub_len": sub_len, "k": codebook_size,
                                       "seed": seed, **kw}))
            return fit(values, sub_len, codebook_size, seed=seed, **kw)

        def record_event(pipeline, name, round_index, iteration):
            self.events.append((name, round_index, iteration))
            return apply_event(pipeline, name, round_index, iteration)

        monkeypatch.setattr(pl, "sampling_mask", sampling_mask)
        monkeypatch.setattr(pl, "pruning_mask", pruning_mask)
        monkeypatch.setattr(merging, "build_merge_groups", build_merge_groups)
        monkeypatch.setattr(appearance_stage, "make_mlp_optimizer", make_mlp_optimizer)
        monkeypatch.setattr(pl, "AppearanceMLP", appearance_mlp)
        monkeypatch.setattr(SubVectorQuantizer, "fit", staticmethod(quantizer_fit))
        monkeypatch.setattr(pl.CompressionPipeline, "apply_event", record_event)

    def of(self, name: str) -> list[dict]:
        return [kw for n, kw in self.calls if n == name]


def test_a_three_round_run_gives_each_stage_and_round_its_settings(tiny_scene, monkeypatch):
    rec = Recorder(monkeypatch)
    model = baseline(tiny_scene)
    n0 = model.num_gaussians
    merge_cfg = merging.MergeConfig(grid_size=0.3, grid_growth=1.5)
    cfg = CompressConfig(preset="M", lengths=LENGTHS, num_merge=3, batch_size=1, backend="cpu", seed=17,
                         merge=merge_cfg, score_weighting="paper")
    pipeline = CompressionPipeline(model, tiny_scene, cfg, scores=scores(n0), progress=False, log=lambda *_: None)
    positions = []
    original_lr = pl.set_position_lr
    monkeypatch.setattr(pl, "set_position_lr", lambda opt, step, **kw: positions.append((step, kw))
                        or original_lr(opt, step, **kw))
    pipeline.run()
    # events at the schedule's iterations: sample 0, prune 3, merge rounds 7, 12, 17, appearance 22, svq3d 28,
    # svq4d 35; 37 iterations in all
    assert rec.events == [("sample", 0, 0), ("prune", 0, 3), ("merge", 0, 7), ("merge", 1, 12), ("merge", 2, 17),
                          ("appearance", 0, 22), ("svq3d", 0, 28), ("svq4d", 0, 35)]
    assert pipeline.total_iterations == 37
    # sampling: the preset's τ_GS over every Gaussian; pruning: its quantile over the sampled set's stored scores
    (sample,), (prune,) = rec.of("sample"), rec.of("prune")
    assert sample == {"n": n0, "ratio": 0.2}
    sampled = round(0.2 * n0)
    assert prune["n"] == sampled and prune["p"] == 0.8
    order = torch.sort(-(_minmax(scores(n0).static) * _minmax(scores(n0).dynamic)), stable=True).indices[:sampled]
    assert torch.equal(prune["static"], scores(n0).static[order.sort().values])
    # merging: one call per round on the current Gaussians, grid × growth^round, the model's time range
    rounds = rec.of("merge")
    assert [r["grid"] for r in rounds] == pytest.approx([0.3, 0.45, 0.675])
    assert all(r["config"] is merge_cfg and r["time_range"] == tuple(tiny_scene.time_range) for r in rounds)
    after = {r.stage: r.num_gaussians for r in pipeline.records}
    # a round's groups are baked when the next event starts, so round r + 1 sees what round r left
    assert [r["n"] for r in rounds] == [after["prune"], after["merge2"], after["merge3"]]
    assert after["merge1"] == after["prune"]
    # the appearance MLPs: the backbone's inputs (position + time), the schedule over the iterations that remain
    assert rec.of("mlp") == [{"num_inputs": 4}]
    assert rec.of("mlp optimizer") == [{"total_iterations": 37 - 22}]
    # SVQ: each attribute in its stage with the preset's codebook size, its sub-vector length and the run's seed
    svq = rec.of("svq")
    expected = [("scale", 512), ("rotation", 8192), ("app", 1024), ("scale_t", 512), ("rotation_r", 8192)]
    assert [(c["sub_len"], c["k"], c["width"], c["seed"], c["rate_weight"]) for c in svq] == [
        (SUB_LENGTHS[a][0], k, SUB_LENGTHS[a][1], 17, 0.0) for a, k in expected]
    # the position learning rate continues the baseline's decay over the fine-tuning iterations
    assert [s for s, _ in positions] == [30_000 + i for i in range(1, 38)]
    assert all(kw["max_steps"] == 30_000 + 37 and kw["extent"] == pytest.approx(tiny_scene.extent) for _, kw in
               positions)


def test_lifetime_weighting_ranks_sampling_and_pruning_by_weighted_scores(tiny_scene, monkeypatch):
    from omg4.compress.score import lifetime_weights

    rec = Recorder(monkeypatch)
    model = baseline(tiny_scene)
    n0 = model.num_gaussians
    times = sorted({v.timestamp for v in tiny_scene.train_views})
    weights = lifetime_weights(model, times)
    assert (weights > 1).any()  # some Gaussians outlive the tiny clip or are cut by its ends
    captured = []
    sampling = pl.sampling_mask
    monkeypatch.setattr(pl, "sampling_mask", lambda s, ratio: captured.append(s) or sampling(s, ratio))
    assert CompressConfig().choice("score_weighting") == "lifetime"  # the default, beyond the paper
    cfg = CompressConfig(preset="M", stages=("sample", "prune"), lengths=LENGTHS, batch_size=1, backend="cpu")
    CompressionPipeline(model, tiny_scene, cfg, scores=scores(n0), progress=False, log=lambda *_: None).run()
    torch.testing.assert_close(captured[0].static, scores(n0).static * weights)
    torch.testing.assert_close(captured[0].dynamic, scores(n0).dynamic * weights)
    (prune,) = rec.of("prune")  # the sampled Gaussians' weights, from the Gaussians the scores were computed on
    weighted = scores(n0).weighted(weights)
    kept = torch.sort(-(_minmax(weighted.static) * _minmax(weighted.dynamic)), stable=True).indices[:round(0.2 * n0)]
    torch.testing.assert_close(prune["static"], weighted.static[kept.sort().values])


def _minmax(x):
    return (x - x.min()) / (x.max() - x.min() + 1e-8)


@pytest.mark.parametrize("backbone,preset", [(b, p) for b in PAPER_PRESETS for p in PAPER_PRESETS[b]])
def test_every_preset_reaches_the_stages_with_the_papers_settings(tiny_scene, monkeypatch, backbone, preset):
    rec = Recorder(monkeypatch)
    model = baseline(tiny_scene, backbone, n=200)
    cfg = CompressConfig(preset=preset, lengths=LENGTHS, batch_size=1, backend="cpu", seed=5)
    pipeline = CompressionPipeline(model, tiny_scene, cfg, scores=scores(200), progress=False, log=lambda *_: None)
    for event in pipeline.events:
        pipeline.apply_event(event.name, event.round, event.iteration)
    tau, p, codebooks = PAPER_PRESETS[backbone][preset]
    assert rec.of("sample") == [{"n": 200, "ratio": tau}]
    assert [(c["n"], c["p"], c["frame_floor"]) for c in rec.of("prune")] == [(round(tau * 200), p, 0.02)]
    attributes = [*STAGE_3D, *(("scale_t", "rotation_r") if backbone == "rt4dgs" else ("duration", "velocity"))]
    assert [(c["sub_len"], c["k"], c["width"]) for c in rec.of("svq")] == [
        (SUB_LENGTHS[a][0], codebooks[a], SUB_LENGTHS[a][1]) for a in attributes]
    assert rec.of("mlp") == [{"num_inputs": 4 if backbone == "rt4dgs" else 3}]


def test_explicit_settings_override_the_preset_and_the_backbone_picks_the_default(tiny_scene, monkeypatch):
    rec = Recorder(monkeypatch)
    for backbone, preset, tau, p in (("rt4dgs", None, 0.2, 0.8), ("freetimegs", None, 0.7, 0.6)):
        cfg = CompressConfig(preset=preset, lengths=LENGTHS, batch_size=1, backend="cpu")
        size = cfg.size(backbone)
        assert (size.name, size.tau_gs, size.prune_quantile) == ({"rt4dgs": "M", "freetimegs": "L"}[backbone], tau, p)
    model = baseline(tiny_scene, n=200)
    cfg = CompressConfig(preset="S", tau_gs=0.55, prune_quantile=0.35, lengths=LENGTHS, batch_size=1, backend="cpu")
    pipeline = CompressionPipeline(model, tiny_scene, cfg, scores=scores(200), progress=False, log=lambda *_: None)
    pipeline.stage_sample()
    pipeline.stage_prune()
    assert rec.of("sample") == [{"n": 200, "ratio": 0.55}]
    assert [(c["n"], c["p"]) for c in rec.of("prune")] == [(110, 0.35)]
    assert pipeline.size.codebook("scale") == (1, 256)  # codebooks stay the preset's


def test_sampling_and_pruning_at_once_prune_within_the_sampled_set(tiny_scene, monkeypatch):
    rec = Recorder(monkeypatch)
    model = baseline(tiny_scene, n=300)
    s = scores(300, seed=3)
    cfg = CompressConfig(preset="M", stages=("sample+prune",), lengths=LENGTHS, batch_size=1, backend="cpu")
    pipeline = CompressionPipeline(model, tiny_scene, cfg, scores=s, progress=False, log=lambda *_: None)
    pipeline.stage_sample_prune()
    (sample,), (prune,) = rec.of("sample"), rec.of("prune")
    assert sample["n"] == 300 and prune["n"] == 60 and prune["p"] == 0.8
    sd = _minmax(s.static) * _minmax(s.dynamic)
    sampled = torch.sort(-sd, stable=True).indices[:60].sort().values
    static, dynamic = s.static[sampled], s.dynamic[sampled]
    keep = (static >= _quantile(static, 0.8)) | (dynamic >= _quantile(dynamic, 0.8))
    assert pipeline.model.num_gaussians == int(keep.sum())
    torch.testing.assert_close(pipeline.model.params["xyz"].detach(), model.params["xyz"].detach()[sampled[keep]])


def _quantile(x, q):
    """Linear interpolation between the order statistics at q·(n − 1)."""
    v = x.double().sort().values
    pos = q * (len(v) - 1)
    lo = math.floor(pos)
    hi = min(lo + 1, len(v) - 1)
    return float(v[lo] + (pos - lo) * (v[hi] - v[lo]))


def test_stopping_after_a_stage_fine_tunes_until_the_next_event(tiny_scene, monkeypatch):
    """--stop-after prune: the pruned model is fine-tuned for the prune stage's iterations (up to where merging
    would start), and no later event runs."""
    rec = Recorder(monkeypatch)
    steps = []
    original = pl.CompressionPipeline.finetune_step
    monkeypatch.setattr(pl.CompressionPipeline, "finetune_step", lambda self, step: steps.append(step) or
                        original(self, step))
    cfg = CompressConfig(preset="M", lengths=LENGTHS, batch_size=1, backend="cpu")
    pipeline = CompressionPipeline(baseline(tiny_scene, n=200), tiny_scene, cfg, scores=scores(200), progress=False,
                                   log=lambda *_: None)
    pipeline.run(stop_after="prune")
    assert [e[0] for e in rec.events] == ["sample", "prune"]
    assert steps == list(range(1, LENGTHS.sample + LENGTHS.prune + 1))


def test_stopping_after_the_last_event_runs_the_whole_schedule(tiny_scene, monkeypatch):
    """--stop-after the pipeline's last stage (sampling and pruning alone): every iteration runs, as without it."""
    rec = Recorder(monkeypatch)
    steps = []
    original = pl.CompressionPipeline.finetune_step
    monkeypatch.setattr(pl.CompressionPipeline, "finetune_step", lambda self, step: steps.append(step) or
                        original(self, step))
    cfg = CompressConfig(preset="M", lengths=LENGTHS, batch_size=1, backend="cpu", stages=("sample", "prune"))
    pipeline = CompressionPipeline(baseline(tiny_scene, n=200), tiny_scene, cfg, scores=scores(200), progress=False,
                                   log=lambda *_: None)
    pipeline.run(stop_after="prune")
    assert [e[0] for e in rec.events] == ["sample", "prune"]
    assert steps == list(range(1, pipeline.total_iterations + 1)) and pipeline.total_iterations > 0
