"""The command line refuses bad input before any work, in one line, and never destroys its inputs."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from omg4.app.cli import main
from omg4.testing import forge


@pytest.fixture(scope="module")
def model_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("model") / "m.omg4"
    forge.valid_file(path, 300, codebook_scale=0.1)
    return path


def _digest(path: Path) -> str:
    if path.is_dir():
        return hashlib.sha256(b"".join(_digest(p).encode() + p.name.encode() for p in sorted(path.rglob("*"))
                                       if p.is_file())).hexdigest()
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _failed(argv: list[str], capsys, *, contains: str) -> None:
    """Run ``omg4 argv``, which may print progress first: exit 2 and a last stderr line naming ``contains``."""
    capsys.readouterr()
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err and contains in err.splitlines()[-1], err


def _refused(argv: list[str], capsys, *, contains: str) -> str:
    """Run ``omg4 argv``: exit 2 and one line on stderr naming ``contains``."""
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert contains in err, err
    return err


# ----------------------------------------------------------------- inputs stay intact
def test_every_command_refuses_an_output_that_is_one_of_its_inputs(tiny_scene_dir, model_file, tmp_path, capsys):
    scene = str(tiny_scene_dir)
    checkpoint = tmp_path / "baseline.safetensors"
    checkpoint.write_bytes(b"not really a checkpoint, never read")
    poses = tiny_scene_dir / "poses_bounds.npy"
    cases = [
        ["compress", scene, "--model", str(checkpoint), "--out", str(checkpoint)],
        ["compress", scene, "--model", str(checkpoint), "--out", str(tmp_path / "x.omg4"), "--json", str(poses),
         "--force"],
        ["eval", scene, "--model", str(model_file), "--json", str(model_file)],
        ["render", "--model", str(model_file), "--data", scene, "--out", str(poses)],
        ["render", "--model", str(model_file), "--data", scene, "--out", str(poses), "--force"],
        ["info", scene, "--json", str(tiny_scene_dir / "points3d.ply")],
        ["info", str(model_file), "--json", str(model_file)],
        ["train", scene, "--out", scene],
        ["bench", scene, "--model", str(checkpoint), "--out", str(checkpoint)],
        ["import-rt4dgs", str(checkpoint), "--out", str(checkpoint), "--time-range", "0", "1"],
    ]
    before = {p: _digest(p) for p in (tiny_scene_dir, model_file, checkpoint)}
    for argv in cases:
        _refused(argv, capsys, contains="overwrite")
    assert {p: _digest(p) for p in before} == before


def test_existing_files_inside_a_dataset_folder_need_force(tiny_scene_dir, model_file, capsys):
    notes = tiny_scene_dir / "notes.json"
    notes.write_text("{}")
    try:
        _refused(["eval", str(tiny_scene_dir), "--model", str(model_file), "--json", str(notes)], capsys,
                 contains="--force")
        assert notes.read_text() == "{}"
    finally:
        notes.unlink()


def test_dataset_rule_refuses_files_a_reader_takes_even_new_ones_and_force_allows_the_rest(tmp_path):
    from omg4.app.outputs import check_outputs
    from omg4.errors import OMG4Error

    data = tmp_path / "data"
    (data / "train").mkdir(parents=True)
    (data / "frame.png").write_text("old")
    (data / "m.omg4.scores.npz").write_text("old")
    for new in ("cam99.mp4", "poses_bounds.npy", "transforms_val.json", "train/r_999.png"):
        with pytest.raises(OMG4Error, match="file of the dataset"):
            check_outputs({"--out": data / new}, inputs=[data], datasets=[data], force=True)
    for existing in ("frame.png", "m.omg4.scores.npz"):
        with pytest.raises(OMG4Error, match="--force"):
            check_outputs({"--out": data / existing}, inputs=[data], datasets=[data])
        check_outputs({"--out": data / existing}, inputs=[data], datasets=[data], force=True)
    check_outputs({"--out": data / "preview.png"}, inputs=[data], datasets=[data])  # new, read by no reader
    with pytest.raises(OMG4Error, match="cannot check"):
        check_outputs({"--json": tmp_path / ("x" * 300 + ".json")})


def test_info_json_beside_a_model_may_be_rewritten(model_file, tmp_path, capsys):
    out = model_file.parent / "summary.json"
    for _ in range(2):
        assert main(["info", str(model_file), "--json", str(out)]) == 0
    assert json.loads(out.read_text())["kind"] == "omg4"


def test_two_outputs_of_one_command_may_not_be_the_same_file(tiny_scene_dir, tmp_path, capsys):
    out = tmp_path / "m.omg4"
    _refused(["compress", str(tiny_scene_dir), "--model", str(tmp_path / "b.safetensors"), "--out", str(out),
              "--json", str(out)], capsys, contains="same file")


def test_train_into_an_existing_run_folder_needs_resume_or_force(tiny_scene_dir, tmp_path, capsys):
    from omg4.train.run_state import clear_run

    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    files = [run / "model.safetensors", run / "checkpoints" / "model_0000100.safetensors",
             run / "checkpoints" / "state_0000100.pt", run / "notes.txt"]
    for f in files:
        f.write_text("x")
    _refused(["train", str(tiny_scene_dir), "--out", str(run)], capsys, contains="--resume")
    assert all(f.read_text() == "x" for f in files)
    clear_run(run)  # what --force does before training afresh
    assert [f.exists() for f in files] == [False, False, False, True]


def test_train_force_starts_afresh_in_an_existing_run_folder(tiny_scene_dir, tmp_path, capsys):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    stale = run / "checkpoints" / "model_0000500.safetensors"
    stale.write_text("from an earlier run")
    (run / "checkpoints" / "state_0000500.pt").write_text("from an earlier run")
    argv = ["train", str(tiny_scene_dir), "--out", str(run), "--iterations", "2", "--init", "random",
            "--num-random-points", "200", "--test-interval", "0"]
    assert main(argv + ["--force"]) == 0
    assert not stale.exists() and (run / "model.safetensors").exists()
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["model_0000002.safetensors",
                                                                     "state_0000002.pt"]
    capsys.readouterr()
    assert main(argv + ["--resume"]) == 0  # resuming the finished run is allowed (and trains no further)


# ------------------------------------------------------------- checked before work
@pytest.mark.parametrize("argv, contains", [
    (["train", "DATA", "--out", "OUT", "--iterations", "-5"], "--iterations"),
    (["train", "DATA", "--out", "OUT", "--batch-size", "0"], "--batch-size"),
    (["train", "DATA", "--out", "OUT", "--downscale", "nan"], "--downscale"),
    (["render", "--model", "M", "--data", "DATA", "--out", "x.png", "--time", "nan"], "--time"),
    (["render", "--model", "M", "--data", "DATA", "--out", "x.mp4", "--fps", "0"], "--fps"),
    (["render", "--model", "M", "--data", "DATA", "--out", "x.mp4", "--num-frames", "0"], "--num-frames"),
    (["compress", "DATA", "--model", "M", "--out", "x.omg4", "--tau-gs", "1.5"], "--tau-gs"),
    (["compress", "DATA", "--model", "M", "--out", "x.omg4", "--grid-bits", "17,9,10"], "--grid-bits"),
    (["compress", "DATA", "--model", "M", "--out", "x.omg4", "--grid-bits", "12,7,7", "--codec", "paper"],
     "compact codec only"),
    (["bench", "DATA", "--model", "M", "--grid-bits", "15,9"], "--grid-bits"),
    (["compress", "DATA", "--model", "M", "--out", "x.safetensors", "--stop-after", "merge", "--grid-bits", "12,7,7"],
     "--stop-after writes a checkpoint"),
    (["bench", "DATA", "--model", "M", "--grid-bits", "15,9,10", "12,7,7", "--codec", "ans"], "compact codec only"),
    (["eval", "DATA", "--model", "M", "--max-views", "0"], "--max-views"),
    (["import-rt4dgs", "C", "--out", "x", "--time-range", "0", "inf"], "--time-range"),
    (["import-rt4dgs", "C", "--out", "x", "--time-range", "1", "0"], "T0 < T1"),
    (["train", "DATA", "--out", "OUT", "--seed", "99999999999999999999"], "--seed: must be at most"),
    (["compress", "DATA", "--model", "M", "--out", "x.omg4", "--seed", "-1"], "--seed: must be at least 0"),
    (["synth", "OUT", "--seed", str(2**63)], "--seed: must be at most 9223372036854775807"),
    (["demo", "--seed", "x"], "--seed: expected an integer"),
    (["compress", "DATA", "--model", "M", "--out", "x.omg4", "--batch-size", "257"], "--batch-size: must be at most 256"),
    (["bench", "DATA", "--model", "M", "--batch-size", "100000"], "--batch-size: must be at most 256"),
])
def test_bad_numbers_are_one_line_errors(argv, contains, capsys):
    with pytest.raises(SystemExit) as info:
        code = main(argv)
        raise SystemExit(code)
    err = capsys.readouterr().err
    assert info.value.code == 2 and err.count("\n") == 1 and contains in err, err


def test_outputs_are_checked_before_the_inputs_are_even_read(tmp_path, capsys):
    a_file = tmp_path / "file"
    a_file.write_text("x")
    missing = str(tmp_path / "no_such_data")
    # an output under a file, in a folder nothing can write to, or naming a folder: refused first
    _refused(["eval", missing, "--model", "M", "--json", str(a_file / "x.json")], capsys, contains="not a folder")
    _refused(["compress", missing, "--model", "M", "--out", "/proc/omg4-test/x.omg4"], capsys, contains="cannot write")
    (tmp_path / "frame.png").mkdir()
    _refused(["render", "--model", "M", "--data", missing, "--out", str(tmp_path / "frame.png")], capsys,
             contains="is a folder")
    _refused(["train", missing, "--out", str(a_file)], capsys, contains="not a folder")


def test_time_outside_the_model_range_is_refused(tiny_scene_dir, model_file, tmp_path, capsys):
    out = tmp_path / "x.png"
    _refused(["render", "--model", str(model_file), "--data", str(tiny_scene_dir), "--out", str(out),
              "--time", "7"], capsys, contains="time range")
    assert not out.exists()


@pytest.mark.parametrize("width, height", [(0, 10), (-5, 10), (200000, 200000), (10.5, 10)])
def test_camera_sizes_outside_sane_bounds_are_refused(model_file, tmp_path, capsys, width, height):
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps({"K": np.eye(3).tolist(), "viewmat": np.eye(4).tolist(), "width": width,
                               "height": height}))
    _refused(["render", "--model", str(model_file), "--camera", str(cam), "--out", str(tmp_path / "x.png")], capsys,
             contains="camera")


def test_ply_declaring_more_vertices_than_its_bytes_is_refused(tmp_path):
    from omg4.data.points import read_ply
    from omg4.errors import DataError

    for fmt in ("binary_little_endian", "ascii"):
        path = tmp_path / f"{fmt}.ply"
        path.write_bytes(f"ply\nformat {fmt} 1.0\nelement vertex 100000000000\nproperty float x\nproperty float y\n"
                         "property float z\nend_header\n".encode() + b"\0" * 120)
        with pytest.raises(DataError, match="declares 100000000000 vertices"):
            read_ply(path)


# ------------------------------------------------------------- interrupted writes
def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_temporaries_of_interrupted_writes_are_removed_by_the_next_write(tmp_path):
    from omg4.atomic import write_text_atomic

    dead = tmp_path / f".summary.{_dead_pid()}-abcd1234.tmp.json"
    old_style = tmp_path / ".summary.k2j4h5g6.tmp.json"
    alive = tmp_path / f".summary.{os.getppid()}-abcd1234.tmp.json"  # a running process: maybe still writing
    other = tmp_path / f".summary.v2.{_dead_pid()}-abcd1234.tmp.json"  # another target's
    for p in (dead, old_style, alive, other):
        p.write_text("partial")
    write_text_atomic(tmp_path / "summary.json", "{}")
    assert (tmp_path / "summary.json").read_text() == "{}"
    assert [p.exists() for p in (dead, old_style, alive, other)] == [False, False, True, True]


def test_synth_removes_the_folders_an_interrupted_synth_left(tmp_path):
    from omg4.data.synthetic import SynthConfig, write_synthetic_scene

    stale = tmp_path / f".scene.tmp-{_dead_pid()}-0123456789ab"
    stale.mkdir()
    (stale / "cam00.mp4").write_bytes(b"partial")
    write_synthetic_scene(tmp_path / "scene", SynthConfig(num_cameras=2, num_frames=1, width=16, height=16,
                                                          num_points=10), progress=False)
    assert not stale.exists() and (tmp_path / "scene" / "poses_bounds.npy").exists()


# ------------------------------------------------------------- nothing lost when a run fails or misnames
def test_train_force_keeps_the_old_run_when_the_initialization_fails(tiny_scene_dir, tmp_path, capsys, monkeypatch):
    from omg4.errors import OMG4Error

    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    files = [run / "model.safetensors", run / "checkpoints" / "model_0000100.safetensors",
             run / "checkpoints" / "state_0000100.pt"]
    for f in files:
        f.write_text("the earlier run")

    def failing_init(scene, mode, cfg):
        raise OMG4Error("initialization failed")

    monkeypatch.setattr("omg4.train.init.initial_points", failing_init)
    _failed(["train", str(tiny_scene_dir), "--out", str(run), "--force"], capsys, contains="initialization failed")
    assert all(f.read_text() == "the earlier run" for f in files)


def test_kernels_are_the_commands_choice_for_its_run_only(tiny_scene_dir, tmp_path, monkeypatch):
    """``--kernels`` is the run's config's ``kernels`` (recorded) and holds while the command runs, where every
    operation asks the one place that decides, and not after it (nor does parsing ``--device`` choose); the command's
    own failure leaves the choice as it was."""
    from omg4.errors import OMG4Error
    from omg4.kernels import kernel_mode, runs_cpu_kernels

    seen = []

    def recording_step(self, step):
        seen.append((kernel_mode(), runs_cpu_kernels(torch.zeros(2))))
        raise OMG4Error("stop here")

    monkeypatch.setattr("omg4.train.trainer.Trainer._train_step", recording_step)
    base = ["train", str(tiny_scene_dir), "--iterations", "2"]
    assert main([*base, "--out", str(tmp_path / "a"), "--kernels", "reference"]) == 2
    assert kernel_mode() == "fused" and runs_cpu_kernels(torch.zeros(2))
    assert main([*base, "--out", str(tmp_path / "b")]) == 2
    assert main([*base, "--out", str(tmp_path / "c"), "--set", "kernels=reference"]) == 2
    assert seen == [("reference", False), ("fused", True), ("reference", False)]
    recorded = [json.loads((tmp_path / run / "config.json").read_text())["train_config"]["kernels"] for run in "abc"]
    assert recorded == ["reference", None, "reference"]


def test_a_configs_kernels_hold_in_its_trainer_and_pipeline_only(tiny_scene, tmp_path, monkeypatch):
    """The choice is the config's: the trainer's and the pipeline's steps run with it (from the library too, no
    command around them), and it is gone after them; an unknown one is a one-line error."""
    from omg4.compress.pipeline import CompressConfig, CompressionPipeline
    from omg4.errors import OMG4Error
    from omg4.kernels import kernel_mode
    from omg4.train import Trainer, make_config

    seen = []
    monkeypatch.setattr("omg4.train.trainer.Trainer._train_step", lambda self, step: seen.append(kernel_mode()))
    monkeypatch.setattr(CompressionPipeline, "_finetune_step", lambda self, step: seen.append(kernel_mode()))
    cfg = make_config("cpu-small", iterations=1, checkpoint_interval=0, backend="cpu", kernels="reference")
    trainer = Trainer(tiny_scene, cfg, tmp_path / "run", progress=False, log=lambda *_: None)
    trainer.train_step(1)
    pipeline = CompressionPipeline(trainer.model, tiny_scene, CompressConfig(schedule="tiny", kernels="reference"),
                                   progress=False)
    pipeline.finetune_step(1)
    assert seen == ["reference", "reference"] and kernel_mode() == "fused"
    with pytest.raises(OMG4Error, match="unknown kernels 'fast'") as caught:
        make_config("cpu-small", kernels="fast")
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize("name", ["model.safetensors", "config.json", "checkpoints/summary.json"])
def test_train_json_may_not_overwrite_what_the_run_folder_holds(tiny_scene_dir, tmp_path, capsys, name):
    run = tmp_path / "run"
    _refused(["train", str(tiny_scene_dir), "--out", str(run), "--json", str(run / name)], capsys,
             contains=f"would overwrite {name.split('/')[0]}, which --out")
    assert not run.exists()


def test_train_json_beside_the_run_files_is_allowed():
    from omg4.app.outputs import check_outputs
    from omg4.train.run_state import RUN_FILES

    from omg4.errors import OMG4Error

    run = Path("run")
    check_outputs({"--out": run, "--json": run / "summary.json"}, folders=["--out"], reserved={"--out": RUN_FILES})
    with pytest.raises(OMG4Error, match="would overwrite config.json"):  # the contrast: a file the run writes
        check_outputs({"--out": run, "--json": run / "config.json"}, folders=["--out"], reserved={"--out": RUN_FILES})


def test_demo_refuses_a_folder_holding_anything_but_an_earlier_demo(tmp_path, capsys):
    from omg4.app.demo import check_demo_folder

    mine = tmp_path / "mine"
    (mine / "scene").mkdir(parents=True)
    (mine / "scene" / "mydata.txt").write_text("keep me")
    _refused(["demo", "--quick", "--out", str(mine)], capsys, contains="is no scene it synthesized")
    (mine / "notes.txt").write_text("keep me too")
    _refused(["demo", "--quick", "--out", str(mine)], capsys, contains="holds 'notes.txt', which the demo does not")
    assert (mine / "scene" / "mydata.txt").read_text() == "keep me"
    stray = tmp_path / "stray"  # a training run that no demo wrote: no synthesized scene beside it
    (stray / "baseline").mkdir(parents=True)
    (stray / "baseline" / "model.safetensors").write_text("my model")
    _refused(["demo", "--quick", "--out", str(stray)], capsys, contains="is not a folder an earlier demo wrote")
    assert (stray / "baseline" / "model.safetensors").read_text() == "my model"
    earlier = tmp_path / "earlier"  # what a demo leaves, plus an interrupted write's hidden temporary
    (earlier / "scene").mkdir(parents=True)
    (earlier / "scene" / "synth.json").write_text('{"generator": "omg4 synth"}')
    for name in ("results.json", "scene_M.omg4", ".scene_M.omg4.tmp-1-abc"):
        (earlier / name).write_text("x")
    (earlier / "baseline" / "checkpoints").mkdir(parents=True)
    check_demo_folder(earlier)
    check_demo_folder(tmp_path / "new")
    (earlier / "baseline" / "notes.txt").write_text("mine")
    _refused(["demo", "--quick", "--out", str(earlier)], capsys, contains="which the demo's training does not write")


def test_no_output_replaces_a_file_of_a_dataset_the_command_does_not_read(tiny_scene_dir, model_file, tmp_path,
                                                                           capsys):
    before = _digest(tiny_scene_dir)
    _refused(["export", str(model_file), "--out", str(tiny_scene_dir / "points3d.ply")], capsys,
             contains="would overwrite or add a file of the dataset")
    _refused(["info", str(model_file), "--json", str(tiny_scene_dir / "poses_bounds.npy")], capsys,
             contains="file of the dataset")
    blender = tmp_path / "blender"
    (blender / "train").mkdir(parents=True)
    (blender / "transforms_train.json").write_text("{}")
    _refused(["export", str(model_file), "--out", str(blender / "train" / "r_000.png"), "--format", "ply"], capsys,
             contains="file of the dataset")
    panoptic = tmp_path / "panoptic"  # images two levels down: ims/<camera>/<frame>.jpg, seg/<camera>/<frame>.png
    (panoptic / "seg" / "1").mkdir(parents=True)
    (panoptic / "train_meta.json").write_text("{}")
    _refused(["export", str(model_file), "--out", str(panoptic / "seg" / "1" / "000000.png"), "--format", "ply"],
             capsys, contains="file of the dataset")
    assert _digest(tiny_scene_dir) == before


def test_outputs_beside_a_dataset_that_no_reader_takes_are_allowed(tmp_path):
    from omg4.app.outputs import check_outputs

    project = tmp_path / "project"  # an N3DV folder: its reader takes top-level files only
    (project / "renders").mkdir(parents=True)
    (project / "poses_bounds.npy").write_bytes(b"")
    for out in (project / "renders" / "frame.png", project / "renders" / "orbit.mp4", project / "eval.json",
                tmp_path / "frame.png"):
        check_outputs({"--out": out})
    from omg4.errors import OMG4Error

    with pytest.raises(OMG4Error, match="file of the dataset"):  # the contrast: a new top-level camera video
        check_outputs({"--out": project / "orbit.mp4"})


def test_a_failed_compression_leaves_the_earlier_scores_file(tiny_scene_dir, tmp_path, capsys, monkeypatch):
    from omg4.compress.pipeline import CompressionPipeline
    from omg4.errors import OMG4Error

    baseline = tmp_path / "run"
    assert main(["train", str(tiny_scene_dir), "--out", str(baseline), "--iterations", "2", "--init", "random",
                 "--num-random-points", "200", "--test-interval", "0"]) == 0
    out = tmp_path / "m.omg4"
    scores = tmp_path / "m.omg4.scores.npz"
    scores.write_bytes(b"an earlier run's scores")
    computed = []

    def failing_run(self, stop_after=None):
        computed.append(self.ensure_scores())
        raise OMG4Error("a stage failed")

    monkeypatch.setattr(CompressionPipeline, "run", failing_run)
    argv = ["compress", str(tiny_scene_dir), "--model", str(baseline / "model.safetensors"), "--out", str(out),
            "--schedule", "tiny"]
    _failed(argv, capsys, contains="a stage failed")
    assert computed and scores.read_bytes() == b"an earlier run's scores" and not out.exists()
    scores.unlink()  # with no earlier scores the fresh ones are kept for a re-run
    _failed(argv, capsys, contains="a stage failed")
    assert np.array_equal(np.load(scores)["static"], computed[-1].static.double().numpy()) and not out.exists()


def test_eval_skips_lpips_on_images_smaller_than_its_network_takes(tiny_scene_dir, model_file, tmp_path, capsys):
    out = tmp_path / "eval.json"  # downscale 2: 32x24 test images, below AlexNet's 31 and above VGG's 16
    assert main(["eval", str(tiny_scene_dir), "--model", str(model_file), "--downscale", "2", "--lpips", "alex,vgg",
                 "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["lpips_alex"] is None and 0.0 <= result["lpips_vgg"] <= 1.0
    assert all("lpips_alex" not in row and "lpips_vgg" in row for row in result["per_view"])


def test_unreadable_inputs_and_impossible_outputs_are_one_line_errors(tiny_scene_dir, model_file, tmp_path, capsys):
    from omg4.codec.container import has_magic
    from omg4.errors import OMG4Error

    _refused(["render", "--model", str(model_file), "--camera", str(tmp_path), "--out", str(tmp_path / "x.png")],
             capsys, contains="cannot read the camera file")
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    _refused(["synth", str(blocker / "scene")], capsys, contains="is not a folder")
    _refused(["synth", str(tmp_path / ("x" * 300))], capsys, contains="cannot check")
    if Path("/proc/self/mem").exists():
        with pytest.raises(OMG4Error, match="cannot read /proc/self/mem"):
            has_magic("/proc/self/mem")


def test_info_decides_a_file_kind_by_its_content_as_render_does(model_file, tmp_path, capsys):
    import shutil

    from omg4.gaussians import GaussianConfig, Gaussians4D
    from omg4.gaussians.checkpoint import save_gaussians

    checkpoint = tmp_path / "named_like_a_file.omg4"
    save_gaussians(checkpoint, Gaussians4D.from_points(torch.rand(30, 3), torch.rand(30, 3),
                                                       GaussianConfig(time_range=(0.0, 1.0))))
    container = tmp_path / "named_like_a_checkpoint.safetensors"
    shutil.copy(model_file, container)
    for path, kind in ((checkpoint, "rt4dgs-checkpoint"), (container, "omg4")):
        out = tmp_path / f"{path.stem}.json"
        assert main(["info", str(path), "--json", str(out)]) == 0
        assert json.loads(out.read_text())["kind"] == kind
    damaged = tmp_path / "damaged.omg4"
    damaged.write_bytes(b"garbage" * 10)
    _refused(["info", str(damaged)], capsys, contains="damaged.omg4")


def test_bench_refuses_a_control_that_is_no_baseline_of_the_same_backbone(tiny_scene_dir, model_file, tmp_path,
                                                                          capsys):
    from omg4.gaussians import GaussianConfig, Gaussians4D
    from omg4.gaussians.checkpoint import save_gaussians

    def checkpoint(name: str, backbone: str) -> Path:
        path = tmp_path / name
        save_gaussians(path, Gaussians4D.from_points(torch.rand(30, 3), torch.rand(30, 3),
                                                     GaussianConfig(time_range=(0.0, 1.0), backbone=backbone,
                                                                    sh_degree_t=0 if backbone == "freetimegs" else 2)))
        return path

    baseline = checkpoint("baseline.safetensors", "rt4dgs")
    other = checkpoint("freetime.safetensors", "freetimegs")
    bench = ["bench", str(tiny_scene_dir), "--model", str(baseline), "--out", str(tmp_path / "bench")]
    _refused(bench + ["--control", str(model_file)], capsys, contains="--control: ")
    _refused(bench + ["--control", str(tmp_path / "missing.safetensors")], capsys, contains="--control: ")
    _refused(bench + ["--control", str(other)], capsys, contains="the control trains the same backbone longer")
    assert not (tmp_path / "bench").exists()


def test_a_removed_setting_is_read_off_and_refused_on(tiny_scene_dir, tmp_path, capsys):
    """A config file (or a run's record) may hold a setting that was removed: at its "off" value it is read without
    it; any other value asks for a run this version cannot make, so it is one line saying why."""
    from omg4.train import TrainConfig

    config = tmp_path / "old.json"
    config.write_text(json.dumps({"train_config": {"iterations": 2, "still_weight": 0.01}}))
    _refused(["train", str(tiny_scene_dir), "--out", str(tmp_path / "run"), "--config", str(config)], capsys,
             contains="the setting 'still_weight' (0.01) was removed: the penalty on lasting Gaussians' motion did "
                      "not pay")
    assert not (tmp_path / "run").exists()
    record = {**TrainConfig().to_dict(), "still_weight": 0.0}
    assert TrainConfig.from_dict(record) == TrainConfig()
    with pytest.raises(Exception, match="'still_weight' \\(0.5\\) was removed"):
        TrainConfig.from_dict({**record, "still_weight": 0.5})
