"""A third backbone, declared in this file alone, trains, compresses, writes, decodes and renders.

"static": Gaussians that neither move nor fade (a static 3DGS scene carried in a 4D file: its time
centres are stored but the slice ignores them), 3D SH, MLP appearance without a time input, one size
preset, and a density control of its own that prunes transparent Gaussians every fifth step. Nothing
outside this file names it: if training, the OMG4 stages, the codec, the decoder or the renderer
branched on the known backbones, this test would fail.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import pytest
import torch

from omg4.gaussians.backbone import (APPEARANCE_FEATURES, BACKBONES, SH_REST, Attribute, Backbone, SizePreset,
                                     _svq_groups, register_backbone)
from omg4.gaussians.covariance import condition_and_cull
from omg4.gaussians.freetime import covariance_3d
from omg4.gaussians.initial import neighbour_log_scales, spatial_params
from omg4.optimize.parameters import keep_rows
from omg4.train.strategies.base import DensityStrategy

NEVER_FADES = 1e6  # temporal variance: p_t ≈ 1 over any clip


@dataclasses.dataclass
class PruneTransparent(DensityStrategy):
    """Every ``every`` steps, remove the Gaussians below ``min_opacity`` (never all of them): its settings are its
    own fields, as every strategy's."""

    every: int = 5
    min_opacity: float = 0.02
    calls: ClassVar[list[int]] = []

    def after_step(self, model, optimizer, stats, step, extent):
        if step % self.every:
            return
        PruneTransparent.calls.append(step)
        keep = torch.sigmoid(model.params["opacity"].detach()[:, 0]) >= self.min_opacity
        if bool(keep.any()) and not bool(keep.all()):
            keep_rows(model.params, optimizer, keep)
        stats.reset(model.num_gaussians)


def _motion(values, config):
    n = values["xyz"].shape[0]
    return (torch.zeros_like(values["xyz"]), covariance_3d(values["scaling"], values["rotation"]),
            torch.full((n,), NEVER_FADES, dtype=values["xyz"].dtype, device=values["xyz"].device))


def _geometry(values, config, timestamps):
    velocity, cov3, variance = _motion(values, config)
    return condition_and_cull(values["xyz"], values["t"], velocity, cov3, variance, timestamps.reshape(-1),
                              time_cull=config.time_cull)


def _initialize(xyz, rgb, config, generator):
    params = spatial_params(rgb, neighbour_log_scales(xyz.double().numpy()), config.num_coeffs)
    t_mid = 0.5 * (config.time_range[0] + config.time_range[1])
    params.update(xyz=xyz.clone(), t=torch.full((xyz.shape[0], 1), t_mid))
    return params


_ATTRIBUTES = (
    Attribute("xyz", (3,), "none", lr="position_lr_init", extent_lr=True, merge_logit="merge_xyz_logits"),
    Attribute("t", (1,), "none", lr="time_lr", extent_lr=True),
    Attribute("features_dc", (1, 3), "none", lr="feature_lr", merge_logit="merge_dc_logits", by_mlp=True),
    Attribute("features_rest", (SH_REST, 3), "none", lr="feature_rest_lr", merge_logit="merge_rest_logits",
              by_mlp=True),
    Attribute("opacity", (1,), "sigmoid", lr="opacity_lr", by_mlp=True),
    Attribute("scaling", (3,), "exp", lr="scaling_lr", svq="scale"),
    Attribute("rotation", (4,), "quaternion", lr="rotation_lr", svq="rotation"),
)
STATIC = Backbone(
    name="static",
    title="static 3D Gaussians",
    attributes=_ATTRIBUTES,
    svq_groups=_svq_groups((*_ATTRIBUTES, *APPEARANCE_FEATURES),
                           (("scale", 1, "svq3d"), ("rotation", 2, "svq3d"), ("app", 2, "svq3d"))),
    mlp_time_input=False,
    geometry=_geometry,
    motion=_motion,
    initialize=_initialize,
    size_presets={"M": SizePreset("M", 0.6, 0.3, {"scale": 32, "rotation": 64, "app": 64}, "static")},
    default_preset="M",
    training=PruneTransparent,
    paper_rows={"OMG4-M": ("M", ("sample", "prune", "merge", "appearance", "svq3d", "svq4d"))},
    sh_degree_t=0,
)


@pytest.fixture
def static_backbone(monkeypatch):
    monkeypatch.setattr(PruneTransparent, "calls", [])
    register_backbone(STATIC)
    yield STATIC
    BACKBONES.pop(STATIC.name, None)


def test_a_backbone_declared_here_trains_compresses_decodes_and_renders(tiny_scene, tmp_path, static_backbone):
    from omg4.compress.api import compress_to_file
    from omg4.compress.pipeline import CompressConfig
    from omg4.compress.schedule import StageLengths
    from omg4.evaluate import evaluate
    from omg4.gaussians.checkpoint import load_gaussians
    from omg4.models import load_model
    from omg4.models.compact import load_omg4
    from omg4.render.view import render_view
    from omg4.train import Trainer, make_config

    cfg = make_config("cpu-small", iterations=15, batch_size=1, backbone="static", num_random_points=500,
                      checkpoint_interval=0, backend="cpu")
    result = Trainer(tiny_scene, cfg, tmp_path / "run", progress=False, log=lambda *_: None).run()
    assert PruneTransparent.calls == [5, 10, 15]  # its own density control, not another backbone's
    baseline, _ = load_gaussians(result.model_path)
    assert baseline.config.backbone == "static" and set(baseline.params) == {a.name for a in _ATTRIBUTES}
    assert baseline.num_gaussians == result.model.num_gaussians

    out = tmp_path / "static.omg4"
    lengths = StageLengths(sample=3, prune=3, merge=3, appearance=6, svq3d=3, svq4d=3)
    report = compress_to_file(baseline, tiny_scene, CompressConfig(lengths=lengths, batch_size=1, backend="cpu"),
                              out, progress=False, log=lambda *_: None)
    assert report["config"]["preset"] == "M" and report["config"]["backbone"] == "static"
    assert report["stages"][0]["num_gaussians"] == round(0.6 * baseline.num_gaussians)

    decoded = load_omg4(out)
    assert decoded.config.backbone == "static"
    view = tiny_scene.test_views[0]
    with torch.no_grad():
        first = render_view(decoded, view.camera, tiny_scene.time_range[0], backend="cpu")[0].image
        last = render_view(decoded, view.camera, tiny_scene.time_range[1], backend="cpu")[0].image
    assert float(first.amax()) > 0.05  # something is drawn
    torch.testing.assert_close(first, last, atol=1e-5, rtol=0)  # and it does not change over time
    metrics = evaluate(load_model(out), tiny_scene.test_views[:1], lpips_nets=(), backend="cpu", fps_views=1,
                       progress=False)
    assert metrics["num_gaussians"] == decoded.num_gaussians and metrics["psnr"] > 5


def test_registering_checks_the_presets_against_the_attributes():
    bad = dataclasses.replace(STATIC, name="static-bad",
                              size_presets={"M": SizePreset("M", 0.5, 0.5, {"scale": 32}, "static-bad")})
    with pytest.raises(ValueError, match="exactly its SVQ attributes"):
        register_backbone(bad)
    with pytest.raises(ValueError, match="already called"):
        register_backbone(dataclasses.replace(STATIC, name="rt4dgs"))
    assert "static-bad" not in BACKBONES and BACKBONES["rt4dgs"].title == "Real-Time4DGS"
