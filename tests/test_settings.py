"""Every config field reachable from the command line: --config files, --set, per-field flags, the run's record."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from omg4.app.cli import main
from omg4.compress.pipeline import CompressConfig
from omg4.errors import OMG4Error
from omg4.settings import apply_settings, check_settings, parse_assignments, read_config_file, settings_of
from omg4.train.config import TrainConfig


@pytest.mark.parametrize("command,config", [("train", TrainConfig), ("compress", CompressConfig)])
def test_every_field_has_a_flag_the_command_parses(command, config):
    from omg4.app.cli import _build_parser

    parser = _build_parser(command)[0]
    shortcut_flags = {"background": "--white-background", "strategy.max_gaussians": "--max-gaussians",
                      "strategy.densify_until": "--densify-until", "strategy.densify_interval": "--densify-interval"}
    flags = {s for a in parser._subparsers._group_actions[0].choices[command]._actions for s in a.option_strings}
    for name in settings_of(config):
        flag = shortcut_flags.get(name, "--" + name.replace(".", "-").replace("_", "-"))
        assert flag in flags, (command, name)


def test_settings_are_checked_by_type_and_name():
    assert check_settings(TrainConfig, {"iterations": 3.0, "lambda_dssim": 1, "background": [1, 1, 1]}) == {
        "iterations": 3, "lambda_dssim": 1.0, "background": (1.0, 1.0, 1.0)}
    with pytest.raises(OMG4Error, match="did you mean strategy.densify_interval"):
        check_settings(TrainConfig, {"densify_intervall": 3})
    with pytest.raises(OMG4Error, match="'iterations' expects an integer"):
        check_settings(TrainConfig, {"iterations": 2.5})
    with pytest.raises(OMG4Error, match="expects true or false"):
        check_settings(CompressConfig, {"official_score_quirk": "yes"})
    with pytest.raises(OMG4Error, match="expects 3 values"):
        check_settings(TrainConfig, {"background": [1, 1]})
    with pytest.raises(OMG4Error, match="did you mean merge.grid_size"):
        check_settings(CompressConfig, {"merge.grid_sise": 0.2})
    assert check_settings(CompressConfig, {"tau_gs": None, "merge.grid_size": 1}) == {"tau_gs": None,
                                                                                       "merge.grid_size": 1.0}


def test_nested_settings_apply_and_unset_nested_configs_start_from_their_defaults():
    cfg = apply_settings(CompressConfig(), {"merge.grid_size": 0.3, "lengths.appearance": 7, "num_merge": 3})
    assert cfg.merge.grid_size == 0.3 and cfg.merge.grid_growth == 1.2 and cfg.num_merge == 3
    assert cfg.lengths.appearance == 7 and cfg.lengths.sample == 1000
    assert CompressConfig().merge.grid_size == 0.1  # the default is not shared


def test_files_in_toml_and_json_and_assignments(tmp_path):
    toml = tmp_path / "c.toml"
    toml.write_text('preset = "S"\nnum_merge = 3\n[merge]\ngrid_size = 0.25\n')
    assert read_config_file(toml, "compress_config") == {"preset": "S", "num_merge": 3, "merge.grid_size": 0.25}
    record = tmp_path / "record.json"
    record.write_text(json.dumps({"scene": "x", "train_config": {"iterations": 5}, "codec": "ans"}))
    assert read_config_file(record, "train_config") == {"iterations": 5}
    assert read_config_file(record, "train_config", extra=("codec",)) == {"iterations": 5, "codec": "ans"}
    bad = tmp_path / "bad.toml"
    bad.write_text("preset = \n")
    with pytest.raises(OMG4Error, match="not valid TOML"):
        read_config_file(bad, "compress_config")
    assert parse_assignments(["a=1", "b=[1, 2]", "c=freetimegs", "d=true"]) == {"a": 1, "b": [1, 2], "c": "freetimegs",
                                                                               "d": True}
    with pytest.raises(OMG4Error, match="KEY=VALUE"):
        parse_assignments(["iterations"])


def _train(tiny_scene_dir, out, *extra):
    return main(["train", str(tiny_scene_dir), "--out", str(out), "--preset", "cpu-small", "--test-interval", "0",
                 "--checkpoint-interval", "0", *extra])


def test_train_precedence_file_then_set_then_flags_and_the_record_reproduces_the_run(tiny_scene_dir, tmp_path,
                                                                                     capsys):
    cfg_file = tmp_path / "train.toml"
    cfg_file.write_text("iterations = 6\nbatch_size = 2\nlambda_dssim = 0.5\nsh_increase_interval = 2\n"
                        "num_random_points = 400\nbackend = \"cpu\"\n")
    run = tmp_path / "run"
    assert _train(tiny_scene_dir, run, "--config", str(cfg_file), "--set", "batch_size=1", "--set",
                  "lambda_dssim=0.3", "--lambda-dssim", "0.25", "--iterations", "4") == 0
    recorded = json.loads((run / "config.json").read_text())["train_config"]
    # the flags win over --set, which wins over the file; the file's other values hold
    assert (recorded["iterations"], recorded["batch_size"], recorded["lambda_dssim"], recorded["sh_increase_interval"],
            recorded["num_random_points"], recorded["backend"]) == (4, 1, 0.25, 2, 400, "cpu")
    again = tmp_path / "again"
    assert _train(tiny_scene_dir, again, "--config", str(run / "config.json")) == 0
    assert json.loads((again / "config.json").read_text())["train_config"] == recorded
    from omg4.gaussians.checkpoint import load_gaussians

    a, _ = load_gaussians(run / "model.safetensors")
    b, _ = load_gaussians(again / "model.safetensors")
    assert all(torch.equal(a.params[k], b.params[k]) for k in a.params)


def test_a_bad_setting_is_one_line(tiny_scene_dir, tmp_path, capsys):
    assert _train(tiny_scene_dir, tmp_path / "r", "--set", "densify_untill=3") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "did you mean strategy.densify_until" in err
    assert _train(tiny_scene_dir, tmp_path / "r", "--config", str(tmp_path / "missing.toml")) == 2
    assert "cannot read the config file" in capsys.readouterr().err


def test_compress_records_its_settings_and_the_record_reproduces_them(tiny_scene_dir, tmp_path, capsys):
    run = tmp_path / "run"
    assert _train(tiny_scene_dir, run, "--iterations", "6", "--backend", "cpu") == 0
    common = [str(tiny_scene_dir), "--model", str(run / "model.safetensors"), "--backend", "cpu"]
    out = tmp_path / "m.omg4"
    assert main(["compress", *common, "--out", str(out), "--schedule", "tiny", "--batch-size", "1",
                 "--set", "merge.grid_size=0.3", "--lengths-appearance", "5", "--codec", "ans", "--num-merge", "1"]) == 0
    record = json.loads(out.with_name("m.omg4.config.json").read_text())
    cfg = record["compress_config"]
    assert record["codec"] == "ans" and cfg["merge"]["grid_size"] == 0.3 and cfg["num_merge"] == 1
    # one stage length changes only that stage of the named schedule
    assert cfg["lengths"] == {"sample": 4, "prune": 4, "merge": 4, "appearance": 5, "svq3d": 4, "svq4d": 4}
    again = tmp_path / "again.omg4"
    assert main(["compress", *common, "--out", str(again), "--config", str(out.with_name("m.omg4.config.json"))]) == 0
    assert json.loads(again.with_name("again.omg4.config.json").read_text()) == record
    assert again.read_bytes() == out.read_bytes()
    # the file records the capture's cameras, test cameras first, for viewers without the dataset
    from omg4.codec.payload import decode_payload
    from omg4.codec.rig import rig_cameras
    from omg4.data import load_scene

    scene = load_scene(tiny_scene_dir, decode=False, progress=False)
    meta = decode_payload(out).meta
    from omg4.data.scene import Camera

    rig = [Camera.from_json(c) for c in rig_cameras(meta)]
    assert [c.name for c in rig] == [c.name for c in scene.cameras()] and meta["rig"]["test"] == len(scene.test_cameras())
    for recorded, camera in zip(rig, scene.cameras()):
        np.testing.assert_allclose(recorded.viewmat, camera.viewmat, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(recorded.K, camera.K, rtol=1e-6)
