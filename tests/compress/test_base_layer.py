"""A predicted segment that carries the segment before's lasting Gaussians (``carry="auto"``): where the video does
not change it costs a few bytes per carried Gaussian, and a change in one region is paid only there — with videos
rendered from a known model, so what changed is known exactly."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from omg4.codec.container import read_versioned
from omg4.codec.payload import decode_payload
from omg4.codec.references import reference_sections
from omg4.compress.api import compress_to_file, refuse_held
from omg4.compress.pipeline import CompressConfig
from omg4.compress.schedule import StageLengths
from omg4.compress.stream import SegmentBefore
from omg4.data import load_scene
from omg4.errors import OMG4Error
from omg4.gaussians import GaussianConfig, Gaussians4D
from omg4.render.view import render_view

LENGTHS = StageLengths(sample=2, prune=2, merge=2, appearance=4, svq3d=2, svq4d=2)
BLOB = torch.tensor([0.15, 0.1, 0.0])
"""Where the second video adds content."""


def lasting_model(xyz: torch.Tensor, rgb: torch.Tensor, time_range) -> Gaussians4D:
    """Gaussians at ``xyz`` that last the whole capture (time centre in its middle, a 20 s time scale), opaque."""
    config = GaussianConfig(time_range=time_range, sh_degree=0, sh_degree_t=0)
    model = Gaussians4D.from_points(xyz, rgb, config, generator=torch.Generator().manual_seed(0))
    model.params["t"][:] = sum(time_range) / 2
    model.params["scaling_t"][:] = float(np.log(20.0))
    model.params["opacity"][:] = 2.0
    return model


def video_of(scene, model):
    """``scene`` whose every view shows ``model``'s render: a video of exactly that content."""

    def loader(view):
        return lambda: render_view(model, view.camera, view.timestamp, backend="cpu")[0].image.clamp(0, 1).numpy()

    return dataclasses.replace(scene, train_views=[dataclasses.replace(v, loader=loader(v)) for v in scene.train_views],
                               test_views=[dataclasses.replace(v, loader=loader(v)) for v in scene.test_views])


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """Cameras and times of a 10-frame synthetic capture, a static model of its points, and that model with a
    blob of new Gaussians at :data:`BLOB`; the key segment (frames 0-5) compressed from the static model's video."""
    from omg4.data.synthetic import SynthConfig, write_synthetic_scene

    root = tmp_path_factory.mktemp("base_layer")
    write_synthetic_scene(root / "scene", SynthConfig(num_cameras=4, num_frames=10, width=48, height=32,
                                                      num_points=400), progress=False)

    def scene(a, b):
        return load_scene(root / "scene", frames=range(a, b), progress=False)

    whole = load_scene(root / "scene", progress=False, decode=False)
    g = torch.Generator().manual_seed(1)
    points = whole.initial_points
    static = lasting_model(torch.as_tensor(points.xyz[:300]), torch.as_tensor(points.rgb[:300]), whole.time_range)
    blob_xyz = BLOB + 0.03 * torch.randn(40, 3, generator=g)
    changed = lasting_model(torch.cat([torch.as_tensor(points.xyz[:300]), blob_xyz]),
                            torch.cat([torch.as_tensor(points.rgb[:300]), torch.tensor([[1.0, 0.1, 0.1]]).repeat(40, 1)]),
                            whole.time_range)
    changed.params["scaling"][300:] = float(np.log(0.02))
    cfg = CompressConfig(lengths=LENGTHS, batch_size=1, backend="cpu", carry="auto", predicted_mlp="keep", tau_gs=1.0,
                         prune_quantile=0.0)  # every Gaussian kept: what changes is only the carry
    key = root / "key.omg4"
    compress_to_file(static, video_of(scene(0, 6), static), cfg, key, progress=False, log=lambda *_: None)
    return scene, static, changed, cfg, key


def predicted(capture, model, out):
    """Frames 4-9 of ``model``'s video compressed as a segment predicted from the key segment: its file's header,
    its bytes by section, its decoded payload and the key's."""
    scene, _, _, cfg, key = capture
    reference = reference_sections(decode_payload(key))
    report = compress_to_file(model, video_of(scene(4, 10), model), cfg, out, progress=False, log=lambda *_: None,
                              before=SegmentBefore(reference))
    _, header, _ = read_versioned(out)
    return header, report["sections"], decode_payload(out, reference), decode_payload(key)


def test_a_segment_whose_video_does_not_change_costs_a_few_bytes_per_carried_gaussian(capture, tmp_path):
    _, static, _, _, key = capture
    out = tmp_path / "same.omg4"
    header, sections, _, before = predicted(capture, static, out)
    decision = header["meta"]["carry"]
    assert decision == {"setting": "auto", "carried": "lasting", "gaussians": before.num_gaussians,
                        "covered_share": 1.0}
    carried = header["carried"]
    assert carried == before.num_gaussians > 200  # every Gaussian of the key segment lasts: all carried
    assert header["num_gaussians"] == 1  # of its own only the one a file holds at least
    per_carried = (out.stat().st_size - sections["header"]) / carried  # the header (~1 KB of JSON) is per segment
    assert per_carried < 1.0, per_carried  # measured: 0.53 bytes, of which the carry mask 0.02
    assert sections["carry"] <= carried / 8  # the mask: at most a bit per carried Gaussian
    assert key.stat().st_size / before.num_gaussians > 50 * per_carried  # what a Gaussian costs coded as its own


def test_a_change_in_one_region_is_paid_only_there(capture, tmp_path):
    _, _, changed, _, _ = capture
    header, _, payload, before = predicted(capture, changed, tmp_path / "changed.omg4")
    carried = header["carried"]
    assert header["meta"]["carry"]["carried"] == "lasting" and carried == before.num_gaussians
    own = np.asarray(payload.xyz[carried:], np.float32)
    assert len(own) == header["num_gaussians"] >= 5
    distance = np.linalg.norm(own - BLOB.numpy(), axis=1)
    assert (distance < 0.15).mean() >= 0.9, np.sort(distance)  # the segment's own Gaussians are the blob's


def test_a_segment_trained_holding_the_one_before_is_refused():
    """Training that held the segment before's Gaussians was removed; its files (``held`` in their metadata) would be
    compressed with those copies as the segment's own, so compressing them is one line saying why."""
    refuse_held(Path("segment_001/model.safetensors"), {"iteration": 10})
    with pytest.raises(OMG4Error, match="trained with --hold-lasting .removed: ") as caught:
        refuse_held(Path("segment_001/model.safetensors"), {"iteration": 10, "held": 30})
    assert "\n" not in str(caught.value)
