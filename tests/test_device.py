"""Device settings: ``resolve_device``, backend/device checks and the CLI's one-line ``--device`` errors."""

import sys

import pytest
import torch

from omg4.app.cli import main
from omg4.device import resolve_device
from omg4.errors import OMG4Error
from omg4.render.api import resolve_backend


@pytest.fixture
def no_cuda(monkeypatch):
    """Pretend this machine has no CUDA (so the tests mean the same on a GPU machine)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


def test_resolve_device_names(no_cuda):
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(torch.device("cpu")) == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cpu")
    for bad, message in (("tpu", "unknown device 'tpu'"), ("cuda:x", "unknown device"),
                         ("meta", "not supported"), ("cuda", "CUDA is not available"),
                         ("cuda:0", "CUDA is not available")):
        with pytest.raises(OMG4Error, match=message):
            resolve_device(bad)


def test_resolve_device_checks_the_cuda_index(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert resolve_device("auto") == torch.device("cuda")
    assert resolve_device("cuda:0") == torch.device("cuda:0")
    with pytest.raises(OMG4Error, match="has 1 CUDA device"):
        resolve_device("cuda:3")


def test_backend_must_suit_the_device(monkeypatch):
    cuda = torch.device("cuda")  # a device description; no CUDA needed
    with pytest.raises(OMG4Error, match="cpu rasterizer backend cannot render tensors on cuda"):
        resolve_backend("cpu", cuda)
    monkeypatch.setitem(sys.modules, "gsplat", None)  # gsplat does not import
    with pytest.raises(OMG4Error, match="needs gsplat"):
        resolve_backend("auto", cuda)
    assert resolve_backend("auto", torch.device("cpu")) == "cpu"


def test_trainer_and_pipeline_reject_a_missing_device_at_once(tiny_scene, tmp_path, no_cuda):
    from omg4.compress.pipeline import CompressConfig, CompressionPipeline
    from omg4.train import Trainer, make_config
    from omg4.train.trainer import initial_model

    cfg = make_config("cpu-small", max_gaussians=50, device="cuda")
    with pytest.raises(OMG4Error, match="CUDA is not available"):
        Trainer(tiny_scene, cfg, tmp_path / "run", log=lambda *_: None)
    assert not (tmp_path / "run").exists()
    with pytest.raises(OMG4Error, match="CUDA is not available"):
        CompressionPipeline(initial_model(tiny_scene, cfg), tiny_scene, CompressConfig(device="cuda"),
                            log=lambda *_: None)


# every command with --device, with its other required arguments (the device is checked before they are read)
COMMANDS = {
    "train": ["train", "nowhere", "--out", "run"],
    "compress": ["compress", "nowhere", "--model", "m.safetensors", "--out", "m.omg4"],
    "eval": ["eval", "nowhere", "--model", "m.omg4"],
    "render": ["render", "--model", "m.omg4", "--camera", "cam.json", "--out", "x.png"],
    "bench": ["bench", "nowhere", "--model", "m.safetensors"],
    "demo": ["demo", "--quick"],
}


@pytest.mark.parametrize("command", list(COMMANDS))
def test_cli_device_errors_are_one_line_exit_2(command, tmp_path, monkeypatch, capsys, no_cuda):
    monkeypatch.chdir(tmp_path)
    argv = COMMANDS[command]
    cases = [("cuda", "CUDA is not available on this machine (torch.cuda.is_available() is False)"),
             ("gpu0", "unknown device 'gpu0'")]
    for device, message in cases:
        assert main([*argv, "--device", device]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and message in err and f"omg4 {command}: error:" in err, err
    if command != "demo":  # demo has no --backend
        assert main([*argv, "--device", "cpu", "--backend", "gsplat"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "--backend gsplat renders on CUDA" in err, err
    assert list(tmp_path.iterdir()) == []  # nothing was written


def test_cli_help_lists_the_device_option(capsys):
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    assert "--device DEVICE" in capsys.readouterr().out


def test_to_device_on_the_cpu_keeps_the_values():
    from omg4.device import to_device

    x = torch.arange(6.0).reshape(2, 3)
    moved = to_device(x, "cpu")
    assert moved.device.type == "cpu" and torch.equal(moved, x)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.gpu
def test_a_steps_cameras_times_and_images_reach_the_gpu_without_a_host_synchronization(tiny_scene):
    """In CUDA's sync debug mode "error" any copy that makes the host wait for the GPU raises; the values that
    arrive equal the CPU ones."""
    from omg4.device import to_device
    from omg4.render.view import view_image
    from omg4.render.view import camera_tensors

    view = tiny_scene.train_views[0]
    expected = [*camera_tensors(view.camera), view_image(view), torch.tensor([view.timestamp], dtype=torch.float64)]
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        got = [*camera_tensors(view.camera, "cuda"), view_image(view, "cuda"),
               to_device(torch.tensor([view.timestamp], dtype=torch.float64), "cuda")]
        doubled = [g * 2 for g in got]  # kernels queued behind the copies
    finally:
        torch.cuda.set_sync_debug_mode("default")
    for g, d, e in zip(got, doubled, expected):
        assert g.is_cuda and torch.equal(g.cpu(), e) and torch.equal(d.cpu(), 2 * e)
