"""FreeTimeGS end to end on a tiny scene: train (relocation, regularization) → compress → decode → render."""

import pytest
import torch

from omg4.compress.api import compress_to_file
from omg4.compress.pipeline import CompressConfig, CompressionPipeline
from omg4.compress.schedule import StageLengths
from omg4.gaussians.checkpoint import load_gaussians
from omg4.models.compact import load_omg4
from omg4.render.view import render_view
from omg4.train import Trainer, make_config

LENGTHS = StageLengths(sample=3, prune=3, merge=3, appearance=6, svq3d=3, svq4d=3)
BUDGET = 900


@pytest.fixture(scope="module")
def ftgs_run(tiny_scene, tmp_path_factory):
    cfg = make_config("cpu-small", iterations=40, batch_size=2, checkpoint_interval=0, densify_from=5,
                      densify_interval=10, densify_until=35, max_gaussians=BUDGET, backbone="freetimegs",
                      backend="cpu")
    out = tmp_path_factory.mktemp("ftgs")
    return Trainer(tiny_scene, cfg, out, progress=False, log=lambda *_: None).run(), out


def test_training_keeps_the_budget_and_writes_a_freetimegs_checkpoint(ftgs_run):
    result, _ = ftgs_run
    assert result.model.num_gaussians == BUDGET  # relocation never changes the count
    model, meta = load_gaussians(result.model_path)
    assert model.config.backbone == "freetimegs" and model.config.sh_degree_t == 0
    assert set(model.params) == {"xyz", "t", "duration", "velocity", "scaling", "rotation", "opacity", "features_dc",
                                 "features_rest"}
    assert model.params["velocity"].abs().max() > 0  # velocities were learned
    assert meta["iteration"] == 40


def test_resumed_training_continues_exactly(tiny_scene, tmp_path):
    cfg = make_config("cpu-small", iterations=24, batch_size=2, checkpoint_interval=12, densify_from=5,
                      densify_interval=10, densify_until=20, max_gaussians=600, backbone="freetimegs", backend="cpu")
    whole = Trainer(tiny_scene, cfg, tmp_path / "a", progress=False, log=lambda *_: None).run()
    Trainer(tiny_scene, cfg, tmp_path / "b", progress=False, log=lambda *_: None).run(stop_at=12)
    resumed = Trainer(tiny_scene, cfg, tmp_path / "b", resume=True, progress=False, log=lambda *_: None).run()
    for k, v in whole.model.params.items():
        torch.testing.assert_close(resumed.model.params[k], v, rtol=0, atol=0)


def test_compress_decode_render_round_trip(ftgs_run, tiny_scene, tmp_path):
    result, _ = ftgs_run
    cfg = CompressConfig(preset="L", lengths=LENGTHS, batch_size=1, backend="cpu")
    pipeline = CompressionPipeline(result.model, tiny_scene, cfg, progress=False, log=lambda *_: None)
    compressed = pipeline.run()
    assert set(compressed.quantizers) == {"scale", "rotation", "app", "duration", "velocity"}
    assert compressed.appearance.num_inputs == 3
    report = compress_to_file(result.model, tiny_scene, cfg, tmp_path / "m.omg4", progress=False, log=lambda *_: None)
    assert report["config"]["backbone"] == "freetimegs" and report["config"]["preset"] == "L"
    decoded = load_omg4(tmp_path / "m.omg4")
    assert decoded.config.backbone == "freetimegs" and decoded.num_gaussians == report["num_gaussians"]
    assert decoded.num_gaussians < BUDGET  # sampling, pruning and merging removed Gaussians
    view = tiny_scene.test_views[0]
    image = render_view(decoded, view.camera, view.timestamp, backend="cpu")[0].image
    assert torch.isfinite(image).all() and image.max() > 0.05


def test_real_time_4dgs_presets_are_refused_for_freetimegs(ftgs_run, tiny_scene):
    from omg4.errors import OMG4Error

    result, _ = ftgs_run
    with pytest.raises(OMG4Error, match="size preset 'M' for freetimegs"):
        CompressionPipeline(result.model, tiny_scene, CompressConfig(preset="M", lengths=LENGTHS, backend="cpu"),
                            progress=False, log=lambda *_: None)


def test_bench_rows_of_a_freetimegs_baseline(ftgs_run, tiny_scene, tmp_path):
    from omg4.app.bench import run_bench

    result, _ = ftgs_run
    results = run_bench(tiny_scene, result.model, result.model_path, tmp_path / "bench", schedule="tiny",
                        batch_size=1, rows=["AC only"], backend="cpu", log=lambda *_: None)
    assert list(results) == ["FreeTimeGS", "AC only"]
    assert results["AC only"]["num_gaussians"] == BUDGET  # attribute compression alone keeps every Gaussian
    assert results["AC only"]["storage_mb"] < results["FreeTimeGS"]["storage_mb"] / 2
