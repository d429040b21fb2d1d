"""A resumed run trains with the settings it recorded; the default preset follows the device; Ctrl-C keeps every
finished step; the history holds the training curve; compression reads the baseline's length from its file."""

from __future__ import annotations

import json
import os
import signal

import pytest
import torch

from omg4.app.cli import main
from omg4.errors import OMG4Error
from omg4.train import Trainer, TrainConfig, make_config
from omg4.train.config import default_preset
from omg4.train.resume import recorded_config, resumed_config
from omg4.train.run_state import latest_iteration

SMALL = ["--preset", "cpu-small", "--iterations", "12", "--checkpoint-interval", "6", "--backend", "cpu"]


def record(run) -> dict:
    return json.loads((run / "config.json").read_text())["train_config"]


def test_resume_without_flags_keeps_the_recorded_settings(tiny_scene_dir, tmp_path, capsys):
    """An interrupted 12-iteration cpu-small run resumed by a bare --resume ends at 12 with its own settings; resumed
    again it is finished and says so, changing nothing."""
    run = tmp_path / "run"
    cfg = make_config("cpu-small", iterations=12, checkpoint_interval=6, backend="cpu")
    from omg4.data import load_scene

    Trainer(load_scene(tiny_scene_dir, progress=False), cfg, run, progress=False, log=lambda *_: None).run(stop_at=6)
    before = record(run)
    assert main(["train", str(tiny_scene_dir), "--out", str(run), "--resume"]) == 0
    assert "resuming" in capsys.readouterr().out
    assert latest_iteration(run) == 12 and record(run) == before
    model_bytes = (run / "model.safetensors").read_bytes()
    assert main(["train", str(tiny_scene_dir), "--out", str(run), "--resume"]) == 0
    out = capsys.readouterr().out
    assert "is finished (12 of 12 iterations" in out and "nothing to resume" in out
    assert (run / "model.safetensors").read_bytes() == model_bytes and record(run) == before


def test_a_flag_contradicting_the_record_is_refused_and_set_overrides_it(tiny_scene_dir, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", str(tiny_scene_dir), "--out", str(run), *SMALL]) == 0
    before = record(run)
    assert json.loads((run / "config.json").read_text())["preset"] == "cpu-small"
    assert main(["train", str(tiny_scene_dir), "--out", str(run), "--resume", "--preset", "cpu-small"]) == 0
    for extra, named in ((["--iterations", "30"], "iterations 30 contradicts the run's recorded iterations 12"),
                         (["--preset", "official"], "--preset official contradicts the run's recorded preset cpu-small"),
                         (["--set", "batch_size=3", "--lambda-dssim", "0.5"], "lambda_dssim 0.5 contradicts")):
        capsys.readouterr()
        assert main(["train", str(tiny_scene_dir), "--out", str(run), "--resume", *extra]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and named in err and "--set" in err, err
        assert record(run) == before
    # agreeing flags and where it computes are fine; --set changes a setting on purpose, and the record says so
    assert main(["train", str(tiny_scene_dir), "--out", str(run), "--resume", "--iterations", "12",
                 "--checkpoint-interval", "3", "--set", "iterations=16"]) == 0
    assert "changed by --set: iterations=16" in capsys.readouterr().out
    assert latest_iteration(run) == 16 and record(run) == {**before, "iterations": 16, "checkpoint_interval": 3}


def test_resumed_config_compares_only_what_was_given():
    recorded = make_config("cpu-small", iterations=600)
    assert resumed_config(recorded, asked={}) == recorded
    assert resumed_config(recorded, asked={"iterations": 600, "device": "cpu"}) == recorded
    assert resumed_config(recorded, asked={"test_interval": 50}).test_interval == 50  # reporting may change
    # the preset named again: its name against the recorded one (its fields scale with the iterations)
    assert resumed_config(recorded, asked={}, preset="cpu-small", recorded_preset="cpu-small") == recorded
    assert resumed_config(recorded, asked={}, preset="official") == recorded  # a record that names none
    with pytest.raises(OMG4Error, match="--preset official contradicts the run's recorded preset cpu-small"):
        resumed_config(recorded, asked={}, preset="official", recorded_preset="cpu-small")
    with pytest.raises(OMG4Error, match="seed 1 contradicts"):
        resumed_config(recorded, asked={"seed": 1})
    assert resumed_config(recorded, asked={"seed": 1}, overrides={"seed": 1}).seed == 1


def test_recorded_config_of_a_folder_without_a_record_is_none(tmp_path):
    assert recorded_config(tmp_path) is None
    (tmp_path / "config.json").write_text("{not json")
    with pytest.raises(OMG4Error, match="not a readable training record"):
        recorded_config(tmp_path)


def test_the_default_preset_follows_the_device(tiny_scene_dir, tmp_path, capsys):
    assert default_preset("cpu") == "cpu-small" and default_preset("cuda:1") == "official"
    run = tmp_path / "run"
    assert main(["train", str(tiny_scene_dir), "--out", str(run), "--iterations", "4", "--backend", "cpu"]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith("preset cpu-small (the default on cpu") and "4 iterations of 2 views" in first
    assert record(run)["strategy"]["max_gaussians"] == 60_000 and record(run)["batch_size"] == 2  # cpu-small's, not official's
    assert TrainConfig().strategy.max_gaussians == 0 and TrainConfig().batch_size == 4


def test_ctrl_c_writes_a_checkpoint_and_resume_loses_no_step(tiny_scene, tmp_path):
    """SIGINT during step 5 of 10: the step finishes, a checkpoint of it is written and KeyboardInterrupt raised; the
    resumed run ends with the parameters of an uninterrupted one, bit for bit."""
    cfg = make_config("cpu-small", iterations=10, checkpoint_interval=0, densify_from=2, densify_interval=3,
                      densify_until=9, densify_grad_threshold=1e-6, backend="cpu", max_gaussians=400)
    quiet = dict(progress=False, log=lambda *_: None)
    whole = Trainer(tiny_scene, cfg, tmp_path / "whole", **quiet).run()
    trainer = Trainer(tiny_scene, cfg, tmp_path / "cut", **quiet)
    step = trainer.train_step

    def interrupted_step(i):
        if i == 5:
            os.kill(os.getpid(), signal.SIGINT)
        return step(i)

    trainer.train_step = interrupted_step
    with pytest.raises(KeyboardInterrupt):
        trainer.run()
    assert latest_iteration(tmp_path / "cut") == 5 and not (tmp_path / "cut" / "model.safetensors").exists()
    resumed = Trainer(tiny_scene, cfg, tmp_path / "cut", resume=True, **quiet)
    assert resumed.start == 5
    result = resumed.run()
    for name, value in whole.model.params.items():
        assert torch.equal(value.detach(), result.model.params[name].detach()), name


def test_the_history_holds_the_training_curve(tiny_scene, tmp_path):
    cfg = make_config("cpu-small", iterations=20, checkpoint_interval=0, backend="cpu")
    history = Trainer(tiny_scene, cfg, tmp_path / "run", progress=False, log=lambda *_: None).run().history
    assert [h["iteration"] for h in history] == list(range(1, 21))  # 20 < 100 points: every step
    assert all(h["loss"] > 0 and h["train_psnr"] > 0 and h["num_gaussians"] > 0 for h in history)
    assert "test_psnr" not in history[0]  # no test views rendered unless test_interval asks


def test_compress_reads_how_long_the_baseline_trained(tiny_scene_dir, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", str(tiny_scene_dir), "--out", str(run), *SMALL]) == 0
    out = tmp_path / "m.omg4"
    assert main(["compress", str(tiny_scene_dir), "--model", str(run), "--out", str(out), "--schedule", "tiny",
                 "--backend", "cpu"]) == 0
    settings = json.loads(out.with_name("m.omg4.config.json").read_text())["compress_config"]
    assert settings["baseline_iterations"] == 12
    assert main(["compress", str(tiny_scene_dir), "--model", str(run / "model.safetensors"), "--out", str(out),
                 "--schedule", "tiny", "--backend", "cpu", "--baseline-iterations", "500", "--force"]) == 0
    assert json.loads(out.with_name("m.omg4.config.json").read_text())["compress_config"]["baseline_iterations"] == 500
