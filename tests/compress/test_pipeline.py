"""The OMG4 pipeline end to end on a tiny scene: stages, the .omg4 file, the decoder."""

import copy
import subprocess
import sys

import pytest
import torch

from omg4.compress.api import compress_to_file
from omg4.compress.pipeline import CompressConfig
from omg4.compress.schedule import StageLengths
from omg4.data.scene import Camera
from omg4.gaussians import Gaussians4D
from omg4.gaussians.checkpoint import load_gaussians
from omg4.models.compact import load_omg4
from omg4.render.view import render_view
from omg4.train import Trainer, make_config

LENGTHS = StageLengths(sample=3, prune=3, merge=3, appearance=6, svq3d=3, svq4d=3)


@pytest.fixture(scope="module")
def baseline(tiny_scene, tmp_path_factory):
    cfg = make_config("cpu-small", iterations=30, batch_size=2, checkpoint_interval=0, densify_until=0,
                      backend="cpu")
    return Trainer(tiny_scene, cfg, tmp_path_factory.mktemp("run"), progress=False, log=lambda *_: None).run()


@pytest.fixture(scope="module")
def scores_file(baseline, tiny_scene, tmp_path_factory):
    """SD scores of the baseline, computed once for the module's compression runs."""
    from omg4.compress.score import compute_sd_scores

    path = tmp_path_factory.mktemp("scores") / "scores.npz"
    compute_sd_scores(baseline.model, tiny_scene.train_views, backend="cpu", progress=False).save(path)
    return path


def _config(**kw):
    return CompressConfig(lengths=LENGTHS, batch_size=1, backend="cpu", **kw)


def test_stop_after_prune_writes_checkpoint_with_expected_count(baseline, tiny_scene, tmp_path):
    out = tmp_path / "pruned.safetensors"
    report = compress_to_file(baseline.model, tiny_scene, _config(), out, stop_after="prune", progress=False,
                              log=lambda *_: None)
    n = baseline.model.num_gaussians
    sampled = int(round(0.2 * n))
    stages = {r["stage"]: r["num_gaussians"] for r in report["stages"]}
    assert stages["sample"] == sampled
    assert stages["prune"] < sampled
    model, meta = load_gaussians(out)
    assert model.num_gaussians == stages["prune"] and meta["stopped_after"] == "prune"
    # the scores were saved beside the output and are reused by a later run
    scores = tmp_path / "pruned.safetensors.scores.npz"
    assert scores.exists()
    again = compress_to_file(baseline.model, tiny_scene, _config(), tmp_path / "again.safetensors",
                             stop_after="sample", scores_path=scores, progress=False, log=lambda *_: None)
    assert again["stages"][0]["num_gaussians"] == sampled


def _rounded_copy(model):
    """The pipeline's model with every stored float rounded to fp16, as the file stores it."""
    m = copy.deepcopy(model)
    for k in ("xyz", "t"):
        m.params[k] = m.params[k].detach().half().float()
    with torch.no_grad():
        for q in m.quantizers.values():
            for cb in q.codebooks:
                cb.copy_(cb.half().float())
        for p in m.appearance.parameters():
            p.copy_(p.half().float())
    return m


def keep_pipeline_model(monkeypatch) -> dict:
    """Make every pipeline run leave its final in-memory model in the returned dict (key "model")."""
    from omg4.compress import pipeline as pl

    kept = {}
    original_run = pl.CompressionPipeline.run

    def run_and_keep(self, stop_after=None):
        kept["model"] = original_run(self, stop_after)
        return kept["model"]

    monkeypatch.setattr(pl.CompressionPipeline, "run", run_and_keep)
    return kept


@pytest.mark.parametrize("codec", ["paper", "ans"])
def test_decoded_file_renders_like_the_fp16_rounded_model(baseline, tiny_scene, tmp_path, codec, monkeypatch, scores_file):
    kept = keep_pipeline_model(monkeypatch)
    out = tmp_path / f"m_{codec}.omg4"
    report = compress_to_file(baseline.model, tiny_scene, _config(), out, codec=codec, progress=False,
                              log=lambda *_: None, scores_path=scores_file)
    assert [r["stage"] for r in report["stages"]] == ["sample", "prune", "merge1", "merge2", "appearance", "svq3d",
                                                       "svq4d"]
    assert report["file_bytes"] == out.stat().st_size
    decoded = load_omg4(out)
    reference = _rounded_copy(kept["model"])
    assert decoded.num_gaussians == reference.num_gaussians
    for view in tiny_scene.test_views[::2]:
        with torch.no_grad():
            a, _ = render_view(decoded, view.camera, view.timestamp, backend="cpu")
            b, _ = render_view(reference, view.camera, view.timestamp, backend="cpu")
        assert torch.allclose(a.image, b.image, atol=1e-4, rtol=0), float((a.image - b.image).abs().max())


def _mlp_on_every_gaussian(values, mlp, config, degrees, tau):
    """The former order: the appearance MLPs on all N Gaussians, then the baseline's slice."""
    t0, t1 = config.time_range
    with torch.no_grad():
        dc, rest, logit = mlp.predict(values["xyz"], (tau - t0) / (t1 - t0), values["f_static"], values["f_view"])
    params = {k: values[k].detach() for k in ("xyz", "t", "scaling", "scaling_t", "rotation", "rotation_r")}
    params.update(opacity=logit[:, None], features_dc=dc, features_rest=rest)
    return Gaussians4D(params, config, *degrees)


def test_culling_before_the_mlp_renders_the_same_frame(baseline, tiny_scene, tmp_path, monkeypatch, scores_file):
    """Mid-pipeline and decoded models: cull (and visibility windows) first, MLP after = MLP on all, cull after."""
    kept = keep_pipeline_model(monkeypatch)
    out = tmp_path / "m.omg4"
    compress_to_file(baseline.model, tiny_scene, _config(), out, progress=False, log=lambda *_: None,
                     scores_path=scores_file)
    mid, decoded = kept["model"], load_omg4(out)
    views = tiny_scene.test_views
    checked = 0
    for model, values in ((mid, mid.merged_values()[0]), (decoded, decoded.values)):
        degrees = (model.active_sh_degree, model.active_sh_degree_t)
        for view in views:
            with torch.no_grad():
                culled, sl = render_view(model, view.camera, view.timestamp, backend="cpu")
                reference = _mlp_on_every_gaussian(values, model.appearance, model.config, degrees, view.timestamp)
                full, ref_sl = render_view(reference, view.camera, view.timestamp, backend="cpu")
            assert sl.index.tolist() == ref_sl.index.tolist()
            assert float(full.image.max()) > 0.05
            torch.testing.assert_close(culled.image, full.image, rtol=1e-5, atol=1e-5)
            checked += 1
    assert checked == 2 * len(views)


def test_decoder_imports_no_training_or_compression_code():
    code = ("import sys, omg4.models.compact, omg4.evaluate; "
            "bad = [m for m in sys.modules if m.startswith(('omg4.train', 'omg4.compress'))]; "
            "print(bad); sys.exit(1 if bad else 0)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def test_corrupt_file_gives_one_line_error(tmp_path, baseline, tiny_scene, scores_file):
    from omg4.app.cli import main

    out = tmp_path / "m.omg4"
    compress_to_file(baseline.model, tiny_scene, _config(), out, progress=False, log=lambda *_: None,
                     scores_path=scores_file)
    data = out.read_bytes()
    bad = tmp_path / "bad.omg4"
    bad.write_bytes(data[: len(data) // 2])
    cam = tmp_path / "cam.json"
    cam.write_text(__import__("json").dumps(Camera.to_json(tiny_scene.test_views[0].camera)))
    for argv in (["info", str(bad)], ["render", "--model", str(bad), "--camera", str(cam), "--out",
                                      str(tmp_path / "x.png")]):
        res = subprocess.run([sys.executable, "-m", "omg4", *argv], capture_output=True, text=True)
        assert res.returncode == 2
        lines = [l for l in res.stderr.splitlines() if l.strip()]
        assert len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    assert not (tmp_path / "x.png").exists()
    flipped = bytearray(data)
    flipped[len(data) // 3] ^= 0x10
    bad.write_bytes(bytes(flipped))
    assert main(["info", str(bad)]) == 2


def test_info_breakdown_adds_up_to_file_size(tmp_path, baseline, tiny_scene, scores_file):
    from omg4.app.commands.info import summarize

    out = tmp_path / "m.omg4"
    compress_to_file(baseline.model, tiny_scene, _config(), out, progress=False, log=lambda *_: None,
                     scores_path=scores_file)
    summary, text = summarize(out)
    assert sum(summary["groups"].values()) == out.stat().st_size == summary["total_bytes"]
    # the default (compact) coder: a tiny model's rotations are cheaper as unit quaternions than as codebooks
    assert {"positions", "time centres", "MLPs", "header", "scale indices", "rotation quaternions",
            "rotation_r quaternions"} <= set(summary["groups"])
    assert summary["bits_per_gaussian"] == pytest.approx(8 * out.stat().st_size / summary["num_gaussians"])
    from omg4.codec.payload import decode_payload, encode_payload

    encode_payload(decode_payload(out), tmp_path / "ans.omg4", codec="ans")
    groups = summarize(tmp_path / "ans.omg4")[0]["groups"]
    assert sum(groups.values()) == (tmp_path / "ans.omg4").stat().st_size
    assert {"rotation indices", "rotation_r codebooks"} <= set(groups)


def test_explicit_cpu_under_a_meta_default_device_writes_the_same_file(baseline, tiny_scene, tmp_path):
    """With torch's default device set to "meta", a tensor created without an explicit device cannot
    take part in the computation: SD scores, every stage and the file must match the default run."""
    from omg4.compress.merging import MergeConfig

    merge = MergeConfig(grid_size=1.0, time_cell_fraction=1.0, tau_sim=-1.0)  # coarse cells: groups form
    default = tmp_path / "default.omg4"
    compress_to_file(baseline.model, tiny_scene, _config(merge=merge), default, progress=False, log=lambda *_: None)
    explicit = tmp_path / "explicit.omg4"
    with torch.device("meta"):
        report = compress_to_file(baseline.model, tiny_scene, _config(merge=merge, device="cpu"), explicit,
                                  progress=False, log=lambda *_: None)
    counts = {r["stage"]: r["num_gaussians"] for r in report["stages"]}
    assert counts["appearance"] < counts["merge1"] and report["config"]["device"] == "cpu"
    assert explicit.read_bytes() == default.read_bytes()
    scores = [tmp_path / f"{name}.omg4.scores.npz" for name in ("default", "explicit")]
    assert scores[0].read_bytes() == scores[1].read_bytes()
    assert all(v.device.type == "cpu" for v in baseline.model.params.values())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.gpu
def test_cuda_compression_tracks_the_cpu_run(baseline, tiny_scene, tmp_path, scores_file):
    """The same scores on both devices give the same sampled and pruned sets; the CUDA-written file decodes on the CPU
    and on CUDA and renders close to the CPU-written one.

    The bounds: the SD scores sum gradients that ``test_rasterizer_gsplat`` holds to 1e-3 of their norm on the two
    rasterizers, so 1e-2 of their sum (ten times, for the views' sum); two compressions part as float32 rounding
    grows over their steps, so the CUDA file's PSNR is held to the spread of two CPU seeds (at least the 0.05 dB an
    image 1e-4 off moves it: ΔPSNR ≈ 4.34 · 2 · 1e-4 / RMSE); one file rendered on either device differs only by
    the rasterizers, so 0.05 dB."""
    from omg4.compress.score import SDScores, compute_sd_scores
    from omg4.evaluate import evaluate
    from omg4.models import load_model

    cpu_scores = SDScores.load(scores_file, baseline.model.num_gaussians)
    gpu_scores = compute_sd_scores(baseline.model.to("cuda"), tiny_scene.train_views, device="cuda", progress=False)
    assert gpu_scores.static.device.type == "cpu"
    rel = (gpu_scores.static - cpu_scores.static).abs().sum() / cpu_scores.static.abs().sum()
    assert float(rel) < 1e-2
    reports, results = {}, {}
    for device, backend, seed in (("cpu", "cpu", 0), ("cuda", "auto", 0), ("cpu_seed1", "cpu", 1)):
        out = tmp_path / f"{device}.omg4"
        cfg = CompressConfig(lengths=LENGTHS, batch_size=1, backend=backend, device=device.split("_")[0], seed=seed)
        reports[device] = compress_to_file(baseline.model, tiny_scene, cfg, out, scores_path=scores_file,
                                           progress=False, log=lambda *_: None)
        results[device] = evaluate(load_model(out), tiny_scene.test_views, lpips_nets=(), progress=False)
    counts = {d: {r["stage"]: r["num_gaussians"] for r in rep["stages"]} for d, rep in reports.items()}
    assert counts["cuda"]["sample"] == counts["cpu"]["sample"] and counts["cuda"]["prune"] == counts["cpu"]["prune"]
    seeds_spread = abs(results["cpu_seed1"]["psnr"] - results["cpu"]["psnr"])
    assert results["cuda"]["psnr"] == pytest.approx(results["cpu"]["psnr"], abs=max(seeds_spread, 0.05))
    on_gpu = evaluate(load_model(tmp_path / "cuda.omg4", "cuda"), tiny_scene.test_views, lpips_nets=(),
                      backend="auto", progress=False, device="cuda")
    assert on_gpu["psnr"] == pytest.approx(results["cuda"]["psnr"], abs=0.05)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.gpu
def test_cli_render_and_eval_on_cuda_match_cpu(baseline, tiny_scene, tiny_scene_dir, tmp_path):
    import json

    import numpy as np

    from omg4.app.cli import main

    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps(Camera.to_json(tiny_scene.test_views[0].camera)))
    images, metrics = {}, {}
    for device in ("cpu", "cuda"):
        out, js = tmp_path / f"{device}.npy", tmp_path / f"{device}.json"
        assert main(["render", "--model", str(baseline.model_path), "--camera", str(cam), "--out", str(out),
                     "--device", device]) == 0
        assert main(["eval", str(tiny_scene_dir), "--model", str(baseline.model_path), "--lpips", "alex",
                     "--json", str(js), "--device", device]) == 0
        images[device], metrics[device] = np.load(out), json.loads(js.read_text())
    assert np.abs(images["cuda"] - images["cpu"]).max() < 2e-3
    assert metrics["cuda"]["psnr"] == pytest.approx(metrics["cpu"]["psnr"], abs=0.05)
    assert metrics["cuda"]["fps"] > 0


def test_eval_reports_the_mean_visible_fraction(baseline, tiny_scene):
    from omg4.evaluate import evaluate
    from omg4.render.view import camera_tensors

    model = baseline.model
    result = evaluate(model, tiny_scene.test_views, lpips_nets=(), backend="cpu", fps_views=2, progress=False)
    expected = []
    for v in tiny_scene.test_views:
        with torch.no_grad():
            culled = model.slice_at(v.timestamp, camera_tensors(v.camera)[2]).index.numel()
        expected.append(culled / model.num_gaussians)
    assert result["visible_fraction"] == pytest.approx(sum(expected) / len(expected), rel=1e-12)
    assert [r["visible_fraction"] for r in result["per_view"]] == pytest.approx(expected, rel=1e-12)
    assert 0 < result["visible_fraction"] <= 1


def test_rate_weight_fits_entropy_constrained_codebooks(baseline, tiny_scene, tmp_path, monkeypatch, scores_file):
    """--rate-weight reaches every SVQ fit: with small codebooks (so k-means has points to share them) the indices
    of a β > 0 run use fewer codewords at a lower empirical entropy, and the file says how it was made."""
    import dataclasses

    import numpy as np

    from omg4.codec.payload import decode_payload
    from omg4.gaussians.backbone import RT4DGS

    for name, p in list(RT4DGS.size_presets.items()):
        monkeypatch.setitem(RT4DGS.size_presets, name,
                            dataclasses.replace(p, codebook_sizes={k: 16 for k in p.codebook_sizes}))

    def entropy(ix):
        p = np.bincount(ix) / len(ix)
        p = p[p > 0]
        return float(-(p * np.log2(p)).sum())

    runs = {}
    for beta in (0.0, 30.0):
        out = tmp_path / f"beta{beta:g}.omg4"
        report = compress_to_file(baseline.model, tiny_scene, _config(rate_weight=beta), out, codec="ans",
                                  progress=False, log=lambda *_: None, scores_path=scores_file)
        assert report["config"]["rate_weight"] == beta
        runs[beta] = decode_payload(out)
    plain, constrained = runs[0.0], runs[30.0]
    assert "rate_weight" not in plain.meta and constrained.meta["rate_weight"] == 30.0
    for attr in ("scale", "app", "scale_t"):
        for cb_plain, cb_rate, ix_plain, ix_rate in zip(plain.attributes[attr].codebooks,
                                                        constrained.attributes[attr].codebooks,
                                                        plain.attributes[attr].indices,
                                                        constrained.attributes[attr].indices):
            assert len(cb_plain) == 16 and len(cb_rate) < 16
            assert entropy(ix_rate) < entropy(ix_plain) - 0.3, attr


def test_invalid_rate_weight_is_refused_before_any_work(baseline, tiny_scene):
    from omg4.compress.pipeline import CompressionPipeline
    from omg4.errors import OMG4Error

    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(OMG4Error, match="rate weight"):
            CompressionPipeline(baseline.model, tiny_scene, _config(rate_weight=bad), progress=False)


def test_the_stage_log_reports_quality_in_each_fifth_of_the_clip(tiny_scene):
    """Before and after a stage, the PSNR of two training views per fifth of the clip (in time order): the values
    the evaluation of those views gives."""
    import numpy as np

    from omg4.compress.pipeline import TIME_BUCKETS, CompressConfig, CompressionPipeline
    from omg4.evaluate import evaluate
    from omg4.train import make_config
    from omg4.train.trainer import initial_model

    model = initial_model(tiny_scene, make_config("cpu-small", max_gaussians=300))
    pipe = CompressionPipeline(model, tiny_scene, CompressConfig(schedule="tiny", backend="cpu", stages=("prune",)),
                               progress=False, log=lambda *_: None)
    views = sorted(tiny_scene.train_views, key=lambda v: (v.timestamp, v.camera.name))
    edges = np.linspace(0, len(views), TIME_BUCKETS + 1).astype(int)
    picked = [[views[i] for i in np.linspace(a, b - 1, 2).round().astype(int)] for a, b in zip(edges[:-1], edges[1:])]
    expected = [np.mean([r["psnr"] for r in evaluate(pipe.model, group, lpips_nets=(), time_frames=False,
                                                      progress=False, backend="cpu")["per_view"]]) for group in picked]
    pipe.apply_event("prune", 0, 0)
    record = pipe.records[-1]
    assert record.psnr_by_time_before == pytest.approx(expected, abs=1e-9)
    assert len(record.psnr_by_time_after) == TIME_BUCKETS and record.num_gaussians < 300
    assert record.psnr_by_time_after != record.psnr_by_time_before  # pruning changed the images
