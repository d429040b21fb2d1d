"""The stillness penalty (omg4.train.stillness) against the motion computed here from the 4D covariance, its
gradient against finite differences, and a training step that applies it."""

from __future__ import annotations

import torch

from omg4.gaussians import GaussianConfig, Gaussians4D
from omg4.gaussians.rotation import build_rotation_4d
from omg4.train.stillness import stillness_penalty

TIME_RANGE = (0.0, 2.0)


def model(n: int = 12, seed: int = 0) -> Gaussians4D:
    g = torch.Generator().manual_seed(seed)
    config = GaussianConfig(time_range=TIME_RANGE, sh_degree=0, sh_degree_t=0)
    m = Gaussians4D.from_points(torch.rand(n, 3, generator=g), torch.rand(n, 3, generator=g), config, generator=g)
    m.params = {k: v.double() for k, v in m.params.items()}
    for name in ("rotation", "rotation_r"):
        m.params[name] = m.params[name] + 0.3 * torch.randn(m.params[name].shape, generator=g, dtype=torch.float64)
    m.params["scaling_t"] = torch.linspace(-3.0, 2.0, n, dtype=torch.float64).reshape(n, 1)  # brief to lasting
    return m


def reference_terms(p: dict, convention: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(velocity [N, 3], lasting weight [N], largest scale [N]) from the 4D covariance R diag(s²) Rᵀ built here."""
    rotation = build_rotation_4d(torch.nn.functional.normalize(p["rotation"], dim=-1),
                                 torch.nn.functional.normalize(p["rotation_r"], dim=-1), convention)
    scales = torch.cat([p["scaling"], p["scaling_t"]], dim=1).exp()
    cov = rotation @ torch.diag_embed(scales ** 2) @ rotation.transpose(1, 2)
    mu = p["t"].reshape(-1)
    farther = torch.maximum((mu - TIME_RANGE[0]).abs(), (mu - TIME_RANGE[1]).abs())
    return cov[:, :3, 3] / cov[:, 3, 3:], torch.exp(-0.5 * farther ** 2 / cov[:, 3, 3]), scales[:, :3].max(dim=1).values


def reference_penalty(p: dict, convention: str, weight=None, size=None) -> torch.Tensor:
    """w · (|v| D / s)² (``weight`` and ``size`` given: held at those values)."""
    velocity, w, s = reference_terms(p, convention)
    weight, size = (w if weight is None else weight), (s if size is None else size)
    return (weight * (velocity.norm(dim=1) * (TIME_RANGE[1] - TIME_RANGE[0]) / size) ** 2).mean()


def test_the_penalty_is_the_lasting_gaussians_displacement_in_their_size():
    m = model()
    value = stillness_penalty(m.params, m.config, TIME_RANGE)
    assert value > 0 and torch.allclose(value, reference_penalty(m.params, m.config.rotation_convention), rtol=1e-9)
    still = {k: v.clone() for k, v in m.params.items()}
    for name in ("rotation", "rotation_r"):
        still[name][:] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)  # no space-time mixing: no motion
    assert float(stillness_penalty(still, m.config, TIME_RANGE)) == 0.0
    brief = {k: v.clone() for k, v in m.params.items()}
    brief["t"][:] = -100.0  # shown long before the clip, not through it: it may move as it likes
    assert float(stillness_penalty(brief, m.config, TIME_RANGE)) < 1e-12 * float(value)


def test_its_gradient_matches_finite_differences_with_the_weight_and_size_held():
    m = model(n=5)
    convention = m.config.rotation_convention
    _, weight, size = reference_terms(m.params, convention)
    for name in ("rotation_r", "scaling_t"):
        value = m.params[name].clone().requires_grad_(True)
        stillness_penalty({**m.params, name: value}, m.config, TIME_RANGE).backward()
        numeric = torch.zeros_like(value)
        for index in range(value.numel()):
            step = torch.zeros(value.numel(), dtype=torch.float64)
            step[index] = 1e-6
            step = step.reshape(value.shape)
            up, down = ({**m.params, name: m.params[name] + d} for d in (step, -step))
            numeric.view(-1)[index] = (reference_penalty(up, convention, weight, size)
                                       - reference_penalty(down, convention, weight, size)) / 2e-6
        assert torch.allclose(value.grad, numeric, rtol=1e-5, atol=1e-9), name


def test_training_with_it_leaves_lasting_gaussians_moving_less(tmp_path):
    from omg4.data import load_scene
    from omg4.data.synthetic import SynthConfig, write_synthetic_scene
    from omg4.models import load_model
    from omg4.train import make_config
    from omg4.train.trainer import Trainer

    write_synthetic_scene(tmp_path / "scene", SynthConfig(num_cameras=3, num_frames=6, width=32, height=24,
                                                          num_points=200), progress=False)
    scene = load_scene(tmp_path / "scene", progress=False)
    moved = []
    for weight in (0.0, 1.0):
        cfg = make_config("cpu-small", iterations=30, batch_size=1, checkpoint_interval=0, backend="cpu",
                          num_random_points=200, still_weight=weight)
        out = tmp_path / f"run{weight}"
        Trainer(scene, cfg, out, log=lambda *_: None).run()
        trained = load_model(out / "model.safetensors")
        values = {k: v.detach().double() for k, v in trained.values.items()}
        moved.append(float(stillness_penalty(values, trained.config, scene.time_range)))
    assert moved[1] < 0.5 * moved[0], moved
