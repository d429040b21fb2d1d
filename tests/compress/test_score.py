"""The SD score against a direct computation with the independent dense rasterizer."""

import sys
from pathlib import Path

import pytest
import torch

from omg4.compress.score import UNRANKED, SDScores, compute_sd_scores, frame_ranks
from omg4.gaussians import GaussianConfig, Gaussians4D
from omg4.render.view import camera_tensors
from omg4.render.view import view_image
from omg4.optimize.loss import photometric_loss

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "render"))
from dense_reference import dense_rasterize  # noqa: E402


@pytest.fixture(scope="module")
def small_model(tiny_scene):
    pts = tiny_scene.initial_points
    g = torch.Generator().manual_seed(1)
    pick = torch.randperm(len(pts.xyz), generator=g)[:50]
    model = Gaussians4D.from_points(torch.as_tensor(pts.xyz[pick.numpy()], dtype=torch.float32),
                                    torch.as_tensor(pts.rgb[pick.numpy()], dtype=torch.float32),
                                    GaussianConfig(time_range=tuple(tiny_scene.time_range)), generator=g)
    with torch.no_grad():
        model.params["scaling"] += 1.0  # footprints of a few pixels at 64×48
        model.params["opacity"].fill_(1.0)
        model.params["t"].uniform_(*tiny_scene.time_range, generator=g)  # every Gaussian visible at some time
    return model


def direct_scores(model, views, quirk=False, per_frame=None):
    """Per view: dense render, loss, backward; S += ‖∂L/∂u‖, T += ∂L/∂t (running sum with the quirk); with a dict
    ``per_frame``, the static score of each timestamp's views summed there too."""
    n = model.num_gaussians
    S = torch.zeros(n, dtype=torch.float64)
    T = torch.zeros(n, dtype=torch.float64)
    t_param = model.params["t"].detach().clone().requires_grad_(True)
    params = {**{k: v.detach() for k, v in model.params.items()}, "t": t_param}
    m = Gaussians4D(params, model.config, model.active_sh_degree, model.active_sh_degree_t)
    for v in views:
        viewmat, K, center = camera_tensors(v.camera)
        sl = m.slice_at(v.timestamp, center)
        res = dense_rasterize(sl.means, sl.covars, sl.colors, sl.opacities, viewmat, K, v.camera.width,
                              v.camera.height)
        photometric_loss(res.image, view_image(v)).backward()
        S.index_add_(0, sl.index, res.means2d.grad.double().norm(dim=-1))
        if per_frame is not None:
            per_frame.setdefault(v.timestamp, torch.zeros(n, dtype=torch.float64)).index_add_(
                0, sl.index, res.means2d.grad.double().norm(dim=-1))
        T += t_param.grad.double().squeeze(1)
        if not quirk:
            t_param.grad = None
    return S, T


@pytest.mark.parametrize("quirk", [False, True])
def test_sd_score_matches_direct_dense_computation(small_model, tiny_scene, quirk):
    views = tiny_scene.train_views[:6]
    scores = compute_sd_scores(small_model, views, backend="cpu", official_quirk=quirk, progress=False)
    S, T = direct_scores(small_model, views, quirk=quirk)
    assert (S > 0).sum() >= 10 and (T != 0).sum() >= 10  # the scene exercises the scores
    assert torch.allclose(scores.static, S, rtol=1e-3, atol=1e-7)
    assert torch.allclose(scores.dynamic, T, rtol=1e-3, atol=1e-7)


def test_frame_ranks_come_from_each_frames_own_static_score(small_model, tiny_scene, monkeypatch):
    """The score pass sums the static score per timestamp as the dense reference does view by view, and ranks the
    Gaussians by those sums (:func:`frame_ranks`, tested on its own against places counted by hand)."""
    import omg4.compress.score as score_module

    views = tiny_scene.train_views[::4][:8]  # several cameras and timestamps
    seen = {}

    def keeping_the_sums(sums):
        seen["sums"] = sums
        return frame_ranks(sums)

    monkeypatch.setattr(score_module, "frame_ranks", keeping_the_sums)
    scores = compute_sd_scores(small_model, views, backend="cpu", progress=False, batch_size=3)
    reference = {}
    direct_scores(small_model, views, per_frame=reference)
    sums = seen["sums"]
    assert sums.shape == (len(reference), small_model.num_gaussians)
    expected = torch.stack([reference[t] for t in sorted(reference)]).float()
    assert (expected > 0).sum() >= 20
    assert torch.allclose(sums, expected, rtol=1e-3, atol=1e-7)
    assert torch.equal(scores.frame_rank, frame_ranks(sums))


def test_quirk_differs_from_clean_dynamic_score(small_model, tiny_scene):
    views = tiny_scene.train_views[:6]
    clean = compute_sd_scores(small_model, views, backend="cpu", progress=False)
    quirk = compute_sd_scores(small_model, views, backend="cpu", official_quirk=True, progress=False)
    assert torch.allclose(clean.static, quirk.static, rtol=1e-5, atol=0)  # the quirk only reweights views
    assert not torch.allclose(clean.dynamic, quirk.dynamic)


def test_scores_round_trip_and_reject_wrong_model(tmp_path):
    s = SDScores(torch.rand(7, dtype=torch.float64), torch.randn(7, dtype=torch.float64))
    s.save(tmp_path / "s.npz")
    back = SDScores.load(tmp_path / "s.npz", 7)
    assert torch.equal(back.static, s.static) and torch.equal(back.dynamic, s.dynamic)
    from omg4.errors import CorruptFileError

    with pytest.raises(CorruptFileError):
        SDScores.load(tmp_path / "s.npz", 8)
    assert back.frame_rank is None  # a file without frame ranks (as older versions wrote) reads without them
    ranked = SDScores(s.static, s.dynamic, torch.tensor([0, 3, 1, UNRANKED, 2, 5, 4]))
    ranked.save(tmp_path / "r.npz")
    assert torch.equal(SDScores.load(tmp_path / "r.npz", 7).frame_rank, ranked.frame_rank)
    assert torch.equal(ranked.select(torch.tensor([1, 3])).frame_rank, torch.tensor([3, UNRANKED]))
    import numpy as np

    np.savez(tmp_path / "forged.npz", static=s.static.numpy(), dynamic=s.dynamic.numpy(), frame_rank=-np.ones(7, int))
    with pytest.raises(CorruptFileError, match="frame ranks"):
        SDScores.load(tmp_path / "forged.npz", 7)
