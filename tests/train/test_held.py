"""Lasting Gaussians of the segment before held while a segment trains (omg4.train.held)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from omg4.data import load_scene
from omg4.data.segments import plan_segments
from omg4.errors import OMG4Error
from omg4.gaussians.checkpoint import load_gaussians
from omg4.gaussians.model import GaussianConfig, Gaussians4D
from omg4.models import load_model
from omg4.train import make_config
from omg4.train.held import ANCHOR, HeldGaussians4D, anchor_penalty, deviation, held_layer, held_rows
from omg4.train.init import initial_points
from omg4.train.segmented import segment_budget, segment_plan, train_segments, warm_start, write_plan
from omg4.train.trainer import Trainer

CFG = make_config("cpu-small", iterations=6, batch_size=1, checkpoint_interval=0, backend="cpu",
                  num_random_points=200)


@pytest.fixture(scope="module")
def capture(synthetic_scene):
    return synthetic_scene("held", num_cameras=4, num_frames=12, width=48, height=32, num_points=300)


def _gaussians(n: int, seed: int = 0) -> Gaussians4D:
    gen = torch.Generator().manual_seed(seed)
    return Gaussians4D.from_points(torch.rand(n, 3, generator=gen), torch.rand(n, 3, generator=gen),
                                   GaussianConfig(time_range=(0.0, 1.0), backbone="rt4dgs"), generator=gen)


def test_held_rows_are_those_lasting_through_the_range_and_staying_put():
    """Marginal exp(−½ (gap/σ_t)²) ≥ ½ at both ends of [1, 2] (|t − end| ≤ 1.177 σ_t) and velocity × the farther
    end's distance ≤ the largest scale (identity right quaternions: a static Gaussian, velocity 0)."""
    model = _gaussians(4)
    model.params["t"] = torch.tensor([[1.5], [1.5], [0.2], [1.5]])
    model.params["scaling_t"] = torch.log(torch.tensor([[1.0], [0.3], [1.0], [1.0]]))  # 0.5/0.3 = 1.67 σ: fades
    model.params["rotation_r"][3] = torch.tensor([math.cos(0.4), math.sin(0.4), 0.0, 0.0])  # a moving one
    model.params["scaling"][3] = math.log(1e-3)
    assert held_rows(model.params, model.config, (1.0, 2.0)).tolist() == [0]  # 2: 1.8 σ from the far end


def test_held_gaussians_render_after_the_models_own_and_train_with_them():
    own, held = _gaussians(5, 1), _gaussians(3, 2)
    for v in [*own.params.values(), *held.params.values()]:
        v.requires_grad_(True)
    model = HeldGaussians4D(own.params, own.config, held.params, held.params)
    assert model.num_gaussians == 5 and model.num_held == 3
    times, centres = torch.tensor([0.5], dtype=torch.float64), torch.tensor([[0.5, 0.5, -3.0]])
    sl = model.slice_views(times, centres)
    both = Gaussians4D({k: torch.cat([own.params[k].detach(), held.params[k].detach()]) for k in own.params},
                       own.config)
    reference = both.slice_views(times, centres)
    assert sl.index.tolist() == reference.index.tolist() and int(sl.index.max()) >= 5  # held rows follow own ones
    torch.testing.assert_close(sl.means, reference.means, rtol=0, atol=0)
    torch.testing.assert_close(sl.colors, reference.colors, rtol=0, atol=0)
    sl.opacities.sum().backward()
    assert own.params["opacity"].grad is not None and held.params["opacity"].grad is not None
    assert float(model.penalty().detach()) == 0.0  # at the reference


def test_the_pull_and_the_snap_measure_changes_of_geometry_in_each_gaussians_own_units():
    """Centre in units of the largest scale, time centre in the temporal standard deviation (√Σtt: exp(scaling_t)
    with identity rotations), other geometry as it is, appearance (opacity, SH) not at all; the final model keeps
    its own rows, the held rows that moved beyond SNAP, then the others with their geometry set back to the reference
    exactly and their appearance as trained."""
    reference = _gaussians(4, 5)
    reference.params["scaling"][:] = torch.log(torch.tensor([0.1, 0.2, 0.5]))
    reference.params["scaling_t"][:] = math.log(2.0)
    moved = {k: v.clone() for k, v in reference.params.items()}
    moved["xyz"][0, 1] += 0.04  # 0.08 of its largest scale 0.5: kept
    moved["xyz"][1, 2] -= 0.06  # 0.12: released
    moved["t"][2] += 0.3  # 0.15 σ_t: released
    moved["rotation"][3, 0] += 0.09  # kept
    moved["features_dc"][0] += 5.0  # appearance: free
    moved["opacity"][3] -= 3.0
    dev = deviation(moved, reference.params, reference.config)
    torch.testing.assert_close(dev, torch.tensor([0.08, 0.12, 0.15, 0.09]), rtol=1e-5, atol=1e-6)
    expected = ANCHOR * (0.08 ** 2 + 0.12 ** 2 + 0.15 ** 2 + 0.09 ** 2)
    assert float(anchor_penalty(moved, reference.params, reference.config)) == pytest.approx(expected, rel=1e-4)
    own = _gaussians(2, 6)
    model = HeldGaussians4D(own.params, own.config, moved, reference.params)
    final, held = model.whole()
    assert held == 2 and final.num_gaussians == 6
    torch.testing.assert_close(final.params["xyz"][2:4], moved["xyz"][[1, 2]], rtol=0, atol=0)  # moved: own
    for k, v in reference.params.items():  # stayed: geometry as the reference, appearance as trained
        expected_rows = (moved if k in ("opacity", "features_dc", "features_rest") else reference.params)[k][[0, 3]]
        torch.testing.assert_close(final.params[k][4:], expected_rows, rtol=0, atol=0)


def test_the_held_budget_leaves_the_own_gaussians_what_the_held_do_not_take():
    assert segment_budget(CFG.with_strategy(max_gaussians=0), 150, held=40).strategy.max_gaussians == 110
    assert segment_budget(CFG.with_strategy(max_gaussians=100), 150, held=40).strategy.max_gaussians == 60
    assert segment_budget(CFG.with_strategy(max_gaussians=0), 150, held=150).strategy.max_gaussians == 1  # never 0


def test_a_warm_start_leaves_out_the_held_gaussians_and_the_points_they_cover(capture):
    scene = load_scene(capture, frames=range(4, 10), progress=False)
    before = _gaussians(6, 3)
    before.params["t"] = torch.full((6, 1), float(np.mean(scene.time_range)))
    before.params["scaling_t"][:3] = math.log(5.0)  # rows 0-2 last, 3-5 fade within the range
    before.params["scaling_t"][3:] = math.log(0.01)
    before.params["scaling"][:3] = math.log(1e4)  # the held ones cover every point
    teacher = load_model_from(before)
    rows, held = held_layer(teacher, scene.time_range)
    assert rows.tolist() == [0, 1, 2] and held["xyz"].shape[0] == 3
    points = initial_points(scene, "random", CFG)
    start = warm_start(teacher, scene, CFG.with_strategy(max_gaussians=0), points, rows)
    assert start.num_gaussians == 3  # the three fading ones (opaque enough at the centre); no point uncovered
    torch.testing.assert_close(start.params["t"], before.params["t"][3:], rtol=0, atol=0)
    before.params["scaling"][:3] = math.log(1e-4)  # and now none
    teacher = load_model_from(before)
    rows, _ = held_layer(teacher, scene.time_range)
    start = warm_start(teacher, scene, CFG.with_strategy(max_gaussians=0), points, rows)
    assert start.num_gaussians == 3 + len(points.xyz)


def load_model_from(model: Gaussians4D):
    from omg4.models.windowed import WindowedModel

    return WindowedModel(model.params, model.config, 3, 1)


def test_the_trainer_holds_its_held_gaussians_through_density_events_and_resumes_exactly(capture, tmp_path):
    """Densification every 2 steps (statistics of own rows only: held rows' view-space gradients are left out);
    the final file holds the own Gaussians, the held ones that changed, then the others as they were; a run stopped
    and resumed ends as the uninterrupted one, bit for bit."""
    scene = load_scene(capture, frames=range(0, 6), progress=False)
    cfg = make_config("cpu-small", iterations=6, batch_size=2, checkpoint_interval=0, backend="cpu",
                      num_random_points=100, densify_from=1, densify_interval=2, densify_grad_threshold=0.0)
    held = {k: v.detach().clone() for k, v in _gaussians(20, 4).params.items()}
    held["t"][:] = float(np.mean(scene.time_range))
    points = initial_points(scene, "random", cfg)
    trainer = Trainer(scene, cfg, tmp_path / "run", points=points, held=held, progress=False)
    start = trainer.model.num_gaussians
    result = trainer.run()
    assert trainer.model.num_gaussians > start  # the density events ran
    saved, metadata = load_gaussians(result.model_path)
    exact = metadata["held"]
    assert 0 < exact <= 20 and saved.num_gaussians == trainer.model.num_gaussians + 20
    kept = {tuple(row) for row in held["xyz"].tolist()}
    assert sum(tuple(row) in kept for row in saved.params["xyz"][-exact:].tolist()) == exact  # exact copies
    Trainer(scene, cfg, tmp_path / "split", points=points, held=held, progress=False).run(stop_at=3)
    with pytest.raises(OMG4Error, match=r"trains 20 Gaussians held from the segment before: resume it with "
                                        r"--hold-lasting"):
        Trainer(scene, cfg, tmp_path / "split", resume=True, progress=False)
    resumed = Trainer(scene, cfg, tmp_path / "split", resume=True, held=held, progress=False).run()
    again, again_meta = load_gaussians(resumed.model_path)
    assert again_meta["held"] == exact
    for k, v in saved.params.items():
        torch.testing.assert_close(again.params[k], v, rtol=0, atol=0)


def test_held_segments_keep_the_segment_befores_lasting_gaussians_exactly(capture, tmp_path):
    plan = segment_plan(plan_segments(12, 6, 2), fps=30.0, first_frame=0, segment_frames=6, overlap=2)
    run = tmp_path / "run"
    write_plan(run, plan)
    train_segments(run, plan, CFG, lambda a, b: load_scene(capture, frames=range(a, b), progress=False),
                   lambda scene: initial_points(scene, "random", CFG), hold=True, log=lambda *_: None)
    first = load_gaussians(run / "segment_000" / "model.safetensors")[0].num_gaussians
    for before, seg in zip(plan["segments"], plan["segments"][1:]):
        _, held = held_layer(load_model(run / before["folder"] / "model.safetensors"), seg["time_range"])
        count = held["xyz"].shape[0]
        assert count > 0  # the setting gives the check something to hold
        model, metadata = load_gaussians(run / seg["folder"] / "model.safetensors")
        exact = metadata["held"]
        assert json.loads((run / seg["folder"] / "config.json").read_text())["held_training"] == count
        assert 0 < exact <= count and model.num_gaussians <= first  # own within what the held leave
        rows = {tuple(r) for r in held["xyz"].tolist()}
        assert all(tuple(r) in rows for r in model.params["xyz"][-exact:].tolist())
    (run / "segment_002" / "model.safetensors").unlink()  # continued without holding: refused in one line
    with pytest.raises(OMG4Error, match="^segment 1 was trained with --hold-lasting: continue the run with it"):
        train_segments(run, plan, CFG, lambda a, b: load_scene(capture, frames=range(a, b), progress=False),
                       lambda scene: initial_points(scene, "random", CFG), log=lambda *_: None)


def test_a_forged_held_count_is_refused_with_one_line():
    from omg4.compress.api import held_count
    from omg4.errors import CorruptFileError

    model = _gaussians(4)
    assert held_count("m.safetensors", {}, model) == 0 and held_count("m.safetensors", {"held": 4}, model) == 4
    for forged in (-1, 5, "2", True, 1.5):
        with pytest.raises(CorruptFileError, match=r"^m.safetensors: the held count .* is not an integer from 0 to "
                                                   r"the model's 4 Gaussians$"):
            held_count("m.safetensors", {"held": forged}, model)


def test_holding_needs_segments_taught_by_the_one_before(capture, tmp_path):
    plan = segment_plan(plan_segments(12, 6, 2), fps=30.0, first_frame=0, segment_frames=6, overlap=2)
    for options in ({"teach": False}, {"parallel": "segments"}):
        with pytest.raises(OMG4Error, match="needs segments taught by it"):
            train_segments(tmp_path, plan, CFG, None, None, hold=True, log=lambda *_: None, **options)
