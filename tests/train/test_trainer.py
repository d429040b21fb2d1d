"""Baseline training: the loss falls, resuming equals an uninterrupted run, checkpoints round-trip."""

import json

import pytest
import torch

from omg4.gaussians.checkpoint import load_gaussians
from omg4.train import Trainer, make_config
from omg4.train.trainer import active_sh_degrees


def small_config(**kw):
    base = dict(iterations=12, batch_size=2, densify_from=2, densify_interval=3, densify_until=10,
                opacity_reset_interval=9, sh_increase_interval=2, checkpoint_interval=0, backend="cpu",
                densify_grad_threshold=1e-6)
    base.update(kw)
    return make_config("cpu-small", **base)


def test_sh_degree_schedule_is_spatial_then_temporal():
    assert [active_sh_degrees(s, 1000, 3, 2) for s in (0, 999, 1000, 3000, 4000, 5000, 9000)] == [
        (0, 0), (0, 0), (1, 0), (3, 0), (3, 1), (3, 2), (3, 2)]


def test_training_lowers_loss(tiny_scene, tmp_path):
    cfg = small_config(iterations=40, densify_until=0, opacity_reset_interval=1000)
    trainer = Trainer(tiny_scene, cfg, tmp_path / "run", progress=False, log=lambda *_: None)
    losses = [trainer.train_step(s)[0] for s in range(1, 41)]
    assert sum(losses[-5:]) / 5 < 0.85 * sum(losses[:5]) / 5


def test_densification_counts_are_consistent(tiny_scene, tmp_path):
    from omg4.train.strategies import densification as densify

    cfg = small_config(iterations=10)
    trainer = Trainer(tiny_scene, cfg, tmp_path / "run", progress=False, log=lambda *_: None)
    for s in range(1, 3):  # accumulate gradient statistics without a densification event
        trainer.cfg = small_config(densify_from=100)
        trainer.train_step(s)
    n0 = trainer.model.num_gaussians
    grads = trainer.stats.mean_grad()
    assert (grads > 0).any()
    counts = densify.densify_and_prune(
        trainer.model, trainer.optimizer, trainer.stats, grad_threshold=1e-12, percent_dense=0.01,
        extent=trainer.extent, prune_opacity=0.0, max_screen_size=None, prune_world_size=0.1, max_gaussians=0,
        generator=torch.Generator().manual_seed(0))
    visible = int((grads >= 1e-12).sum())
    assert counts["cloned"] + counts["split"] == visible
    # a clone adds one Gaussian; a split replaces its parent by two children
    assert trainer.model.num_gaussians == n0 + counts["cloned"] + counts["split"] - counts["pruned"] + counts["split"]
    assert counts["pruned"] == counts["split"]  # only the split parents go (no opacity pruning here)
    # optimizer moments follow the new rows
    for g in trainer.optimizer.param_groups:
        p = g["params"][0]
        assert p is trainer.model.params[g["name"]]
        if p in trainer.optimizer.state:
            assert trainer.optimizer.state[p]["exp_avg"].shape == p.shape


def test_resume_equals_uninterrupted_run(tiny_scene, tmp_path):
    cfg = small_config()
    full = Trainer(tiny_scene, cfg, tmp_path / "full", progress=False, log=lambda *_: None).run()
    Trainer(tiny_scene, cfg, tmp_path / "split", progress=False, log=lambda *_: None).run(stop_at=5)
    resumed = Trainer(tiny_scene, cfg, tmp_path / "split", resume=True, progress=False, log=lambda *_: None)
    assert resumed.start == 5
    result = resumed.run()
    assert result.model.num_gaussians == full.model.num_gaussians
    for name, value in full.model.params.items():
        assert torch.equal(value.detach(), result.model.params[name].detach()), name


def test_final_model_file_round_trips(tiny_scene, tmp_path):
    cfg = small_config(iterations=4)
    result = Trainer(tiny_scene, cfg, tmp_path / "run", progress=False, log=lambda *_: None).run()
    model, meta = load_gaussians(result.model_path)
    assert meta["iteration"] == 4 and meta["time_range"] == list(tiny_scene.time_range)
    for name, value in result.model.params.items():
        assert torch.equal(value.detach(), model.params[name])
    assert json.loads((tmp_path / "run" / "config.json").read_text())["train_config"]["iterations"] == 4


def test_cli_train_writes_a_model_and_resumes_without_reinitializing(tiny_scene_dir, tmp_path, monkeypatch, capsys):
    import json

    import omg4.train.init as init
    from omg4.app.cli import main
    from omg4.gaussians.checkpoint import load_gaussians

    run = tmp_path / "run"
    common = [str(tiny_scene_dir), "--out", str(run), "--preset", "cpu-small", "--batch-size", "1",
              "--checkpoint-interval", "2", "--test-interval", "0", "--backend", "cpu"]
    assert main(["train", *common, "--iterations", "4"]) == 0
    model, _ = load_gaussians(run / "model.safetensors")
    assert model.num_gaussians > 0

    def no_init(*args, **kwargs):
        raise AssertionError("a resumed run must not compute initial points")

    monkeypatch.setattr(init, "initial_points", no_init)
    assert main(["train", *common, "--set", "iterations=6", "--resume", "--json", str(tmp_path / "s.json")]) == 0
    summary = json.loads((tmp_path / "s.json").read_text())
    assert summary["iterations"] == 6
    w, h = summary["image_size"]
    assert summary["gaussians_per_pixel"] == pytest.approx(summary["num_gaussians"] / (w * h))
    assert summary["gaussians_per_pixel"] > 0
    assert "resuming from iteration 4" in capsys.readouterr().out


def test_a_checkpoint_without_its_model_file_is_not_complete(tiny_scene, tmp_path):
    from omg4.train.run_state import checkpoint_paths, latest_iteration

    cfg = small_config(iterations=6, checkpoint_interval=2)
    Trainer(tiny_scene, cfg, tmp_path / "run", progress=False, log=lambda *_: None).run()
    assert latest_iteration(tmp_path / "run") == 6
    checkpoint_paths(tmp_path / "run", 6)[0].unlink()  # the state file alone
    assert latest_iteration(tmp_path / "run") == 4


def test_one_initial_point_is_enough_and_none_is_an_error(tiny_scene):
    import numpy as np

    from omg4.data.scene import PointCloud
    from omg4.errors import OMG4Error
    from omg4.train.trainer import initial_model

    cfg = small_config()
    one = PointCloud(xyz=np.zeros((1, 3), np.float32), rgb=np.full((1, 3), 0.5, np.float32))
    assert initial_model(tiny_scene, cfg, one).num_gaussians == 1
    with pytest.raises(OMG4Error, match="empty"):
        initial_model(tiny_scene, cfg, PointCloud(xyz=np.zeros((0, 3), np.float32), rgb=np.zeros((0, 3), np.float32)))
