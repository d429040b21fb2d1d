"""Training on a chosen device: explicit CPU equals the default bit for bit, no tensor leaks to the
default device, older configs load, and (on CUDA machines) a CUDA run tracks the CPU run."""

import pytest
import torch

from omg4.train import Trainer, TrainConfig, make_config

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


def small_config(**kw):
    """8 steps with densification (steps 3 and 6), an opacity reset (6) and checkpoints every 4 steps."""
    base = dict(iterations=8, batch_size=2, densify_from=2, densify_interval=3, densify_until=8,
                opacity_reset_interval=6, sh_increase_interval=2, position_lr_max_steps=8, checkpoint_interval=4,
                backend="cpu", densify_grad_threshold=1e-6, max_gaussians=400)
    return make_config("cpu-small", **{**base, **kw})


def quiet(**kw):
    return dict(progress=False, log=lambda *_: None, **kw)


def test_config_without_device_loads_as_cpu():
    old = small_config().to_dict()
    del old["device"]  # a run folder written before the field existed
    assert TrainConfig.from_dict(old).device == "cpu"


def test_explicit_cpu_under_a_meta_default_device_matches_the_default_run(tiny_scene, tmp_path):
    """With torch's default device set to "meta", any tensor created without an explicit device
    lands on meta and cannot take part in the computation: the run (densification, opacity
    reset, a checkpoint and a resume included) must still reproduce the default run exactly."""
    reference = Trainer(tiny_scene, small_config(), tmp_path / "default", **quiet())
    default = reference.run()
    cfg = small_config(device="cpu")
    with torch.device("meta"):
        Trainer(tiny_scene, cfg, tmp_path / "cpu", **quiet()).run(stop_at=4)
        resumed = Trainer(tiny_scene, cfg, tmp_path / "cpu", **quiet(resume=True))
        assert resumed.start == 4
        result = resumed.run()
    assert result.model.num_gaussians == default.model.num_gaussians
    for name, value in default.model.params.items():
        got = result.model.params[name]
        assert got.device.type == "cpu" and torch.equal(value.detach(), got.detach()), name
    for key in ("grad_sum", "visible_views", "max_radii"):
        assert torch.equal(getattr(resumed.stats, key), getattr(reference.stats, key)), key


@needs_cuda
@pytest.mark.gpu
def test_cuda_training_tracks_the_cpu_run(tiny_scene, tmp_path):
    """Each step from the same state on both devices (the CPU run's parameters and Adam state copied to CUDA first,
    no densification): the losses differ only by the two rasterizers' disagreement, which
    ``test_rasterizer_gsplat`` bounds at 1e-4 of the image; 1e-3 leaves ten times that for the D-SSIM's quotients
    over flat windows. The same model then evaluates alike on both devices: an image 1e-4 off moves a PSNR near
    25 dB by under 0.02 dB (ΔPSNR ≈ 4.34 · 2 · 1e-4 / RMSE), so 0.05. Checkpoints hold CPU tensors and resume on
    CUDA."""
    steps = 6
    cpu = Trainer(tiny_scene, small_config(densify_until=0, iterations=steps), tmp_path / "cpu", **quiet())
    gpu = Trainer(tiny_scene, small_config(densify_until=0, iterations=steps, device="cuda", backend="auto"),
                  tmp_path / "gpu", **quiet())
    assert gpu.model.params["xyz"].is_cuda and gpu.background.is_cuda and gpu.stats.grad_sum.is_cuda

    def same_state():
        with torch.no_grad():
            for name, value in cpu.model.params.items():
                gpu.model.params[name].copy_(value)
        gpu.optimizer.load_state_dict(cpu.optimizer.state_dict())  # moves Adam's moments to the parameters' device

    for s in range(1, steps + 1):
        same_state()
        loss_cpu, _ = cpu.train_step(s)
        loss_gpu, _ = gpu.train_step(s)
        assert loss_gpu == pytest.approx(loss_cpu, rel=1e-3), s
    assert all(v.is_cuda for p in gpu.optimizer.state.values() for k, v in p.items() if k != "step")
    from omg4.train.trainer import evaluate_psnr

    same_state()
    p_cpu = evaluate_psnr(cpu.model, tiny_scene.test_views, cpu.background, "cpu")
    p_gpu = evaluate_psnr(gpu.model, tiny_scene.test_views, gpu.background, "auto", "cuda")
    assert p_gpu == pytest.approx(p_cpu, abs=0.05)
    gpu.save_checkpoint(steps)
    state = torch.load(tmp_path / "gpu" / "checkpoints" / f"state_{steps:07d}.pt", weights_only=True)
    assert all(v.device.type == "cpu" for v in state["stats"].values())
    again = Trainer(tiny_scene, gpu.cfg, tmp_path / "gpu", **quiet(resume=True))
    assert again.start == steps and again.model.params["xyz"].is_cuda
    assert all(v.is_cuda for p in again.optimizer.state.values() for k, v in p.items() if k != "step")
