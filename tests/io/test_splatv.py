""".splatv export, read back with an independent parser of splaTV's layout and checked against our time slices."""

import json

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from omg4.data.scene import Camera
from omg4.gaussians import GaussianConfig, Gaussians4D
from omg4.io.splatv import export_splatv

C0 = 0.28209479177387814
T0, T1 = 2.0, 12.0


def read_splatv(path):
    """(header dict, record fields) following splaTV's hybrid.js: u32 magic 0x674B, u32 JSON length, JSON, texture."""
    data = path.read_bytes()
    magic, length = np.frombuffer(data[:8], "<u4")
    assert magic == 0x674B
    (header,) = json.loads(data[8:8 + length].decode("utf-8"))
    body = np.frombuffer(data[8 + length:], "<u4")
    assert header["type"] == "splat" and header["texwidth"] == 4096
    assert body.nbytes == header["size"] == header["texwidth"] * header["texheight"] * 16
    words = body.reshape(-1, 16)

    def halves(col):
        pairs = words[:, col].astype("<u4").view("<u2").reshape(-1, 2)  # low half first
        return pairs.view(np.float16).astype(np.float64)

    fields = {
        "pos": words[:, 0:3].copy().view("<f4").astype(np.float64),
        "quat": np.concatenate([halves(3), halves(4)], axis=1),
        "scale": np.concatenate([halves(5), halves(6)[:, :1]], axis=1),
        "rgba": words[:, 7:8].copy().view(np.uint8).reshape(-1, 4).astype(np.float64) / 255.0,
        "motion": np.concatenate([halves(c) for c in (8, 9, 10, 11, 12)], axis=1)[:, :9],
        "omega": np.concatenate([halves(13), halves(14)], axis=1),
        "trbf": halves(15),
    }
    return header, fields


def viewer_state(fields, t):
    """What splaTV's vertex shader computes at normalized time ``t``: position, covariance, opacity."""
    dt = t - fields["trbf"][:, 0]
    m = fields["motion"]
    pos = fields["pos"] + m[:, 0:3] * dt[:, None] + m[:, 3:6] * dt[:, None] ** 2 + m[:, 6:9] * dt[:, None] ** 3
    q = fields["quat"] + fields["omega"] * dt[:, None]
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    cov = R @ (fields["scale"][:, :, None] ** 2 * np.swapaxes(R, 1, 2))
    opacity = fields["rgba"][:, 3] * np.exp(-((dt / fields["trbf"][:, 1]) ** 2))
    return pos, cov, opacity


def rt4dgs_model(n=50, seed=0):
    g = torch.Generator().manual_seed(seed)
    p = {"xyz": torch.randn(n, 3, generator=g), "t": T0 + torch.rand(n, 1, generator=g) * (T1 - T0),
         "scaling": torch.randn(n, 3, generator=g) * 0.3 - 1.5, "scaling_t": torch.randn(n, 1, generator=g) * 0.3 + 0.3,
         "rotation": torch.randn(n, 4, generator=g), "rotation_r": torch.randn(n, 4, generator=g),
         "opacity": torch.randn(n, 1, generator=g), "features_dc": torch.randn(n, 1, 3, generator=g) * 0.5,
         "features_rest": torch.zeros(n, 47, 3)}
    return Gaussians4D({k: v.double() for k, v in p.items()}, GaussianConfig(time_range=(T0, T1)), 0, 0)


def freetime_model(n=50, seed=1):
    g = torch.Generator().manual_seed(seed)
    p = {"xyz": torch.randn(n, 3, generator=g), "t": T0 + torch.rand(n, 1, generator=g) * (T1 - T0),
         "scaling": torch.randn(n, 3, generator=g) * 0.3 - 1.5, "rotation": torch.randn(n, 4, generator=g),
         "opacity": torch.randn(n, 1, generator=g), "features_dc": torch.randn(n, 1, 3, generator=g) * 0.5,
         "features_rest": torch.zeros(n, 15, 3), "duration": torch.randn(n, 1, generator=g) * 0.3 + 0.5,
         "velocity": torch.randn(n, 3, generator=g) * 0.2}
    config = GaussianConfig(time_range=(T0, T1), backbone="freetimegs", sh_degree_t=0)
    return Gaussians4D({k: v.double() for k, v in p.items()}, config, 0, 0)


CAMERA = Camera(K=np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]]), viewmat=np.eye(4), width=64, height=48,
                name="cam00")


@pytest.mark.parametrize("make", [rt4dgs_model, freetime_model], ids=["rt4dgs", "freetimegs"])
def test_the_viewer_reproduces_every_time_slice(make, tmp_path):
    model = make()
    n = export_splatv(tmp_path / "m.splatv", model, [CAMERA])
    header, f = read_splatv(tmp_path / "m.splatv")
    assert n == model.num_gaussians and header["texheight"] == 1
    assert np.all(f["rgba"][n:] == 0) and np.all(f["trbf"][n:] == 0)  # zero records after the last Gaussian
    (cam,) = header["cameras"]
    assert cam["fx"] == 100.0 and cam["position"] == [0.0, 0.0, 0.0] and cam["img_name"] == "cam00"
    # records are sorted; each one's static position is a model mean, exactly in float32
    xyz = model.params["xyz"].float().double().numpy()
    order = [int(np.flatnonzero((xyz == p).all(1))[0]) for p in f["pos"][:n]]
    assert sorted(order) == list(range(n))
    for tau in (T0 + 1.3, 7.0, T1 - 0.4):
        pos, cov, opacity = viewer_state({k: v[:n] for k, v in f.items()}, (tau - T0) / (T1 - T0))
        sl = model.slice_at(tau, torch.zeros(3, dtype=torch.float64))
        rows = {int(i): k for k, i in enumerate(sl.index)}
        shown = [j for j, g in enumerate(order) if g in rows]
        assert len(shown) == len(rows) > 5
        dt = (tau - T0) / (T1 - T0) - f["trbf"][:n, 0]
        temporal = np.exp(-((dt / f["trbf"][:n, 1]) ** 2))
        assert np.all(temporal[shown] >= 0.02)  # splaTV's own cull keeps every Gaussian ours keeps
        ours = [rows[order[j]] for j in shown]
        np.testing.assert_allclose(pos[shown], sl.means[ours].numpy(), atol=5e-3, rtol=2e-3)  # fp16 velocity
        expected = sl.covars[ours].numpy()  # fp16 quaternions and scales: errors of a few 1e-4 of each matrix's size
        size = np.abs(expected).max(axis=(1, 2), keepdims=True)
        assert np.all(np.abs(cov[shown] - expected) <= 3e-3 * size)
        np.testing.assert_allclose(opacity[shown], sl.opacities[ours].numpy(), atol=6e-3)  # u8 alpha, fp16 times
    # colour: the DC colour at the Gaussian's own time centre (degree 0 here, so exact up to u8)
    dc = model.params["features_dc"][:, 0].numpy()[order]
    np.testing.assert_allclose(f["rgba"][:n, :3], np.clip(C0 * dc + 0.5, 0, 1), atol=0.5 / 255 + 1e-9)


def test_time_dependent_colour_is_taken_at_the_time_centre(tmp_path):
    model = rt4dgs_model()
    model.params["features_rest"][:, 15] = 0.3  # the first temporal band's DC coefficient
    model.active_sh_degree_t = 1
    export_splatv(tmp_path / "m.splatv", model, [CAMERA])
    _, f = read_splatv(tmp_path / "m.splatv")
    n = model.num_gaussians
    xyz = model.params["xyz"].float().double().numpy()
    order = [int(np.flatnonzero((xyz == p).all(1))[0]) for p in f["pos"][:n]]
    dc = model.params["features_dc"][:, 0].numpy()[order] + 0.3  # cos(0) = 1 at Δt = 0
    np.testing.assert_allclose(f["rgba"][:n, :3], np.clip(C0 * dc + 0.5, 0, 1), atol=0.5 / 255 + 1e-9)


def test_a_camera_is_required(tmp_path):
    with pytest.raises(ValueError, match="at least one camera"):
        export_splatv(tmp_path / "m.splatv", rt4dgs_model(), [])
    assert not (tmp_path / "m.splatv").exists()


def test_library_reader_agrees_with_the_independent_parser_and_refuses_other_files(tmp_path):
    from omg4.errors import CorruptFileError
    from omg4.io.splatv import read_splatv as library_read, splatv_state

    model = freetime_model()
    export_splatv(tmp_path / "m.splatv", model, [CAMERA])
    _, ours = library_read(tmp_path / "m.splatv")
    _, independent = read_splatv(tmp_path / "m.splatv")
    n = model.num_gaussians
    assert len(ours["xyz"]) == n
    for key, other in (("xyz", "pos"), ("quat", "quat"), ("scale", "scale"), ("rgba", "rgba"), ("motion", "motion")):
        np.testing.assert_array_equal(ours[key], independent[other][:n])
    pos, _, opacity = viewer_state({k: v[:n] for k, v in independent.items()}, 0.5)
    means, _, _, opacities = splatv_state(ours, 0.5, min_opacity=0.0)
    np.testing.assert_allclose(means, pos)
    np.testing.assert_allclose(opacities, opacity)
    good = (tmp_path / "m.splatv").read_bytes()
    (tmp_path / "bad.splatv").write_bytes(b"\x00\x00" + good[2:])  # valid JSON, wrong magic
    with pytest.raises(CorruptFileError, match="no 0x674B magic"):
        library_read(tmp_path / "bad.splatv")
    (tmp_path / "short.splatv").write_bytes(good[:-64])  # one record short
    with pytest.raises(CorruptFileError, match="texture bytes"):
        library_read(tmp_path / "short.splatv")


def test_values_beyond_fp16_are_clipped_without_warnings_and_float32_overflow_is_refused(tmp_path):
    import warnings

    from omg4.errors import OMG4Error

    model = rt4dgs_model()
    camera = Camera(K=np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]]), viewmat=np.eye(4), width=64, height=48,
                    name="c")
    model.params["scaling"][3] = 20.0  # exp(20) ≈ 4.9e8: clipped to fp16's largest value
    model.params["t"][4] = 1e12  # a time centre 10^11 clip lengths away: clipped to fp16's largest value
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        export_splatv(tmp_path / "m.splatv", model, [camera])
    _, fields = read_splatv(tmp_path / "m.splatv")
    assert np.isfinite(fields["scale"]).all() and fields["scale"].max() == 65504.0
    assert np.isfinite(fields["trbf"]).all() and fields["trbf"][:, 0].max() == 65504.0  # (centre, time scale)
    model.params["scaling"][3] = 800.0  # exp(800) overflows float64
    with pytest.raises(OMG4Error, match="covariance is not finite"):
        export_splatv(tmp_path / "huge.splatv", model, [camera])
    model.params["scaling"][3] = 0.0
    model.params["xyz"][2, 0] = 1e300
    with pytest.raises(OMG4Error, match="positions beyond the float32 range"):
        export_splatv(tmp_path / "far.splatv", model, [camera])
    assert not (tmp_path / "far.splatv").exists()
