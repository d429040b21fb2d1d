"""What every command does with the model it is given: a file that is not one names what it lacks, a training run's
folder stands for its model, a failed web export leaves nothing behind, a missing optional package names its pip
command, outputs get the usual permissions, and the library speaks through logging only."""

from __future__ import annotations

import logging
import os
import stat
import sys
from pathlib import Path

import pytest

from omg4.app.cli import install_hint, main
from omg4.testing import forge


@pytest.fixture(scope="module")
def trained_run(tiny_scene_dir, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("trained") / "run"
    assert main(["train", str(tiny_scene_dir), "--out", str(run), "--preset", "cpu-small", "--iterations", "6",
                 "--backend", "cpu"]) == 0
    return run


def _one_line_error(argv, capsys) -> str:
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


def test_random_bytes_named_as_a_model_name_the_magic_bytes_in_every_command(tiny_scene_dir, tmp_path, capsys):
    bogus = tmp_path / "random.omg4"
    bogus.write_bytes(os.urandom(4000))
    data = str(tiny_scene_dir)
    commands = [
        ["info", str(bogus)],
        ["render", "--model", str(bogus), "--data", data, "--time", "0.1", "--out", str(tmp_path / "x.png")],
        ["eval", data, "--model", str(bogus)],
        ["export", str(bogus), "--out", str(tmp_path / "x.ply")],
        ["export", str(bogus), "--format", "web", "--out", str(tmp_path / "web")],
        ["compress", data, "--model", str(bogus), "--out", str(tmp_path / "y.omg4")],
        ["bench", data, "--model", str(bogus), "--out", str(tmp_path / "bench")],
    ]
    for argv in commands:
        err = _one_line_error(argv, capsys)
        assert "random.omg4" in err and "magic bytes" in err, (argv[0], err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["random.omg4"]  # nothing written


def test_compress_says_an_omg4_file_is_already_compressed(tiny_scene_dir, tmp_path, capsys):
    model = tmp_path / "m.omg4"
    forge.valid_file(model, 300)
    err = _one_line_error(["compress", str(tiny_scene_dir), "--model", str(model), "--out", str(tmp_path / "y.omg4")],
                          capsys)
    assert "is a compressed .omg4 file" in err and "model.safetensors or its run folder" in err


def test_a_training_run_folder_stands_for_its_model(tiny_scene_dir, trained_run, tmp_path, capsys):
    data = str(tiny_scene_dir)
    assert main(["render", "--model", str(trained_run), "--data", data, "--time", "0.1", "--out",
                 str(tmp_path / "run.png")]) == 0
    assert main(["render", "--model", str(trained_run / "model.safetensors"), "--data", data, "--time", "0.1",
                 "--out", str(tmp_path / "file.png")]) == 0
    assert (tmp_path / "run.png").read_bytes() == (tmp_path / "file.png").read_bytes()
    assert main(["eval", data, "--model", str(trained_run), "--json", str(tmp_path / "e.json")]) == 0
    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    (unfinished / "config.json").write_text("{}")
    err = _one_line_error(["render", "--model", str(unfinished), "--data", data, "--out", str(tmp_path / "u.png")],
                          capsys)
    assert "training run without its final model yet" in err and "--resume" in err


def test_a_failed_web_export_names_the_file_and_leaves_nothing(tmp_path, capsys):
    model = tmp_path / "m.omg4"
    forge.valid_file(model, 300)
    truncated = tmp_path / "truncated.omg4"
    truncated.write_bytes(model.read_bytes()[:3000])
    err = _one_line_error(["export", str(truncated), "--format", "web", "--out", str(tmp_path / "web")], capsys)
    assert "truncated.omg4" in err and "truncated" in err.split(":", 2)[-1]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.omg4", "truncated.omg4"]  # no folder, no temporary
    # over an earlier export, a failed one leaves the earlier export as it was
    assert main(["export", str(model), "--format", "web", "--out", str(tmp_path / "web")]) == 0
    before = sorted((p.relative_to(tmp_path), p.read_bytes()) for p in (tmp_path / "web").rglob("*") if p.is_file())
    _one_line_error(["export", str(truncated), "--format", "web", "--out", str(tmp_path / "web")], capsys)
    after = sorted((p.relative_to(tmp_path), p.read_bytes()) for p in (tmp_path / "web").rglob("*") if p.is_file())
    assert after == before and sorted(p.name for p in tmp_path.iterdir()) == ["m.omg4", "truncated.omg4", "web"]


def test_a_missing_optional_package_names_its_pip_command(tmp_path, capsys, monkeypatch):
    assert install_hint("viser") == "pip install 'viser>=1.0' (the package's 'viewer' extra)"
    assert install_hint("gsplat") == "pip install 'gsplat==1.5.3' (the package's 'gpu' extra)"
    assert install_hint("numpy") is None and install_hint("pytorch_msssim") is None  # required, or tests only
    model = tmp_path / "m.omg4"
    forge.valid_file(model, 300)
    for name in [m for m in sys.modules if m == "viser" or m.startswith(("viser.", "omg4.app.viewer", "omg4.app.commands.view"))]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "viser", None)  # not installed
    err = _one_line_error(["view", str(model)], capsys)
    assert "viser" in err and "pip install 'viser>=1.0'" in err


def test_outputs_get_the_usual_permissions(trained_run):
    mask = os.umask(0)
    os.umask(mask)
    for path in (trained_run / "model.safetensors", trained_run / "config.json",
                 next((trained_run / "checkpoints").glob("model_*.safetensors"))):
        assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~mask, path


def test_the_library_is_quiet_unless_asked(tiny_scene, tmp_path, capsys, caplog):
    import omg4

    config = omg4.train_config("cpu-small", iterations=25, backend="cpu", checkpoint_interval=0)
    omg4.train_baseline(tiny_scene, config, tmp_path / "quiet")
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == ""
    with caplog.at_level(logging.INFO, logger="omg4"):
        omg4.train_baseline(tiny_scene, config, tmp_path / "told")
    assert any("remaining" in r.getMessage() and r.name.startswith("omg4.") for r in caplog.records)
    assert capsys.readouterr().out == ""  # logging, not print


def test_the_tiny_schedule_says_it_is_a_smoke_test(tiny_scene, caplog):
    from omg4.compress.pipeline import CompressConfig, CompressionPipeline
    from omg4.train import make_config
    from omg4.train.trainer import initial_model

    model = initial_model(tiny_scene, make_config("cpu-small", max_gaussians=200))
    with caplog.at_level(logging.WARNING, logger="omg4"):
        CompressionPipeline(model, tiny_scene, CompressConfig(schedule="short", backend="cpu"), progress=False)
        assert not caplog.records
        CompressionPipeline(model, tiny_scene, CompressConfig(schedule="tiny", backend="cpu"), progress=False)
    assert len(caplog.records) == 1 and "smoke test" in caplog.records[0].getMessage()


def test_info_says_how_training_would_initialize(tiny_scene_dir, tmp_path, capsys):
    import shutil

    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene_dir, scene)
    assert main(["info", str(scene)]) == 0
    assert "init points  600 (points3d.ply)" in capsys.readouterr().out
    (scene / "points3d.ply").unlink()
    assert main(["info", str(scene)]) == 0
    assert "--init auto makes them by plane-sweep stereo of the first frame" in capsys.readouterr().out
