"""Import of official Real-Time4DGS checkpoints (rt4dgs §5).

The test writes a checkpoint in the official layout (``torch.save((model_args, iteration))``,
the 19-tuple with ``nn.Parameter`` tensors, a real Adam state dict over the nine named
parameter groups, numpy-float64 learning rates and ``spatial_lr_scale`` as in the official
code) and compares the imported model's time slice with an independent float64
implementation computed from the raw tensors.
"""

import io
import math
import pathlib
import zipfile

import numpy as np
import pytest
import torch
from scipy.special import sph_harm_y

from omg4.app.cli import main as omg4_main
from omg4.errors import CorruptFileError, OMG4Error
from omg4.gaussians import Gaussians4D
from omg4.gaussians.checkpoint import load_gaussians
from omg4.io.rt4dgs_import import import_rt4dgs

GROUPS = ("xyz", "f_dc", "f_rest", "opacity", "scaling", "rotation", "t", "scaling_t", "rotation_r")


def raw_tensors(n, seed=0, temporal_sh=True):
    g = torch.Generator().manual_seed(seed)
    r = {
        "_xyz": torch.randn(n, 3, generator=g),
        "_features_dc": torch.randn(n, 1, 3, generator=g) + 1.0,
        "_features_rest": torch.randn(n, 47, 3, generator=g) * 0.2,
        "_scaling": torch.randn(n, 3, generator=g) * 0.3 - 1.0,
        "_rotation": torch.randn(n, 4, generator=g),
        "_opacity": torch.randn(n, 1, generator=g),
        "_t": torch.rand(n, 1, generator=g) * 10.0,
        "_scaling_t": torch.randn(n, 1, generator=g) * 0.3 + 0.3,
        "_rotation_r": torch.randn(n, 4, generator=g),
    }
    if not temporal_sh:
        r["_features_rest"][:, 15:] = 0.0
    return r


def write_official(path, raw, *, active=(3, 2), rot_4d=True, env_map=None, iteration=30000, items=None):
    """torch.save((model_args, iteration)) exactly as GaussianModel.capture() + train.py write it."""
    P = {k: torch.nn.Parameter(v.clone().requires_grad_(True)) for k, v in raw.items()}
    extent = np.float64(4.4)
    order = ("_xyz", "_features_dc", "_features_rest", "_opacity", "_scaling", "_rotation", "_t", "_scaling_t",
             "_rotation_r")
    lrs = (np.float64(1.6e-4) * extent, 0.0025, 0.0025 / 20, 0.05, 0.005, 0.001, np.float64(1.6e-4) * extent, 0.005,
           0.001)
    groups = [{"params": [P[k]], "lr": lr, "name": name} for k, lr, name in zip(order, lrs, GROUPS)]
    opt = torch.optim.Adam(groups, lr=0.0, eps=1e-15)
    sum((p * p).sum() for p in P.values()).backward()
    opt.step()
    n = raw["_xyz"].shape[0]
    args = (active[0], P["_xyz"], P["_features_dc"], P["_features_rest"], P["_scaling"], P["_rotation"], P["_opacity"],
            torch.zeros(n), torch.zeros(n, 1), torch.zeros(n, 1), torch.zeros(n, 1), opt.state_dict(), extent,
            P["_t"], P["_scaling_t"], P["_rotation_r"], rot_4d, env_map, active[1])
    if items is not None:
        args = items(args)
    torch.save((args, iteration), path)
    return {k: v.detach().clone() for k, v in P.items()}  # the values actually stored


# --- independent float64 oracle -----------------------------------------------------------
def hamilton(a, b):
    w1, x1, y1, z1 = a.T
    w2, x2, y2, z2 = b.T
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=1)


def rotation_4d(ql, qr, flip):
    ql = ql / np.linalg.norm(ql, axis=1, keepdims=True)
    qr_conj = qr / np.linalg.norm(qr, axis=1, keepdims=True) * [1, -1, -1, -1]
    A = np.stack([hamilton(hamilton(ql, np.tile(e, (len(ql), 1))), qr_conj) for e in np.eye(4)], axis=2)
    return A[:, ::-1, ::-1] if flip else A


def real_sh(d, degree):
    theta, phi = np.arccos(np.clip(d[:, 2], -1, 1)), np.arctan2(d[:, 1], d[:, 0])
    out = []
    for l in range(degree + 1):
        for m in range(-l, l + 1):
            y = sph_harm_y(l, abs(m), theta, phi)
            out.append(math.sqrt(2) * (y.real if m > 0 else y.imag) if m else y.real)
    return np.stack(out, 1)


def oracle(raw, tau, cam, period, flip, degree=3, degree_t=2):
    p = {k: v.double().numpy() for k, v in raw.items()}
    s = np.exp(np.concatenate([p["_scaling"], p["_scaling_t"]], 1))
    R = rotation_4d(p["_rotation"], p["_rotation_r"], flip)
    cov = np.einsum("nij,nj,nkj->nik", R, s**2, R)
    var_t, cov_xt = cov[:, 3, 3], cov[:, :3, 3]
    dt = tau - p["_t"][:, 0]
    p_t = np.exp(-0.5 * dt**2 / var_t)
    keep = np.nonzero(p_t > 0.05)[0]
    mean3 = p["_xyz"] + cov_xt / var_t[:, None] * dt[:, None]
    cov3 = cov[:, :3, :3] - np.einsum("ni,nj->nij", cov_xt, cov_xt) / var_t[:, None, None]
    d = mean3[keep] - cam
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    Y = real_sh(d, degree)
    c = np.concatenate([p["_features_dc"], p["_features_rest"]], 1)[keep]
    rgb = sum(np.cos(2 * np.pi * b * (p["_t"][keep, 0] - tau) / period)[:, None]
              * np.einsum("nk,nkc->nc", Y, c[:, 16 * b:16 * b + len(Y[0])]) for b in range(degree_t + 1))
    opac = p_t[keep] / (1 + np.exp(-p["_opacity"][keep, 0]))
    return keep, mean3[keep], cov3[keep], np.maximum(rgb + 0.5, 0), opac


# --- tests -------------------------------------------------------------------------------
@pytest.mark.parametrize("legacy", [False, True])
def test_import_matches_float64_oracle(tmp_path, legacy):
    stored = write_official(tmp_path / "chkpnt30000.pth", raw_tensors(120, seed=1))
    res = import_rt4dgs(tmp_path / "chkpnt30000.pth", (0.0, 10.0), legacy_rotation=legacy)
    m = res.model
    assert res.iteration == 30000 and res.spatial_lr_scale == pytest.approx(4.4) and res.warnings == []
    assert (m.active_sh_degree, m.active_sh_degree_t) == (3, 2)
    assert m.config.rotation_convention == ("legacy" if legacy else "flip")
    for ours in m.params:
        assert torch.equal(m.params[ours], stored["_" + ours]), ours
    cam = np.array([0.5, -3.0, 1.0])
    keep, mean3, cov3, rgb, opac = oracle(stored, 4.2, cam, 10.0, flip=not legacy)
    assert 0 < len(keep) < 120
    m64 = Gaussians4D({k: v.double() for k, v in m.params.items()}, m.config, 3, 2)
    sl = m64.slice_at(4.2, torch.from_numpy(cam))
    np.testing.assert_array_equal(sl.index.numpy(), keep)
    np.testing.assert_allclose(sl.means.numpy(), mean3, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(sl.covars.numpy(), cov3, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(sl.colors.numpy(), rgb, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(sl.opacities.numpy(), opac, rtol=1e-10)
    sl32 = m.slice_at(4.2, torch.from_numpy(cam).float())
    np.testing.assert_allclose(sl32.colors.numpy(), rgb, atol=2e-5)


def test_conventions_differ(tmp_path):
    write_official(tmp_path / "c.pth", raw_tensors(50, seed=2))
    a = import_rt4dgs(tmp_path / "c.pth", (0.0, 10.0)).model.slice_at(5.0, torch.zeros(3))
    b = import_rt4dgs(tmp_path / "c.pth", (0.0, 10.0), legacy_rotation=True).model.slice_at(5.0, torch.zeros(3))
    assert a.index.shape != b.index.shape or (a.means - b.means).abs().max() > 1e-2


def test_numpy1_era_pickle_names_load(tmp_path):
    """Official checkpoints written with numpy 1.x name numpy.core.multiarray.scalar."""
    stored = write_official(tmp_path / "new.pth", raw_tensors(10, seed=3))
    zin = zipfile.ZipFile(tmp_path / "new.pth")
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as z:
        for info in zin.infolist():
            data = zin.read(info.filename)
            if info.filename.endswith("data.pkl"):
                assert b"numpy._core.multiarray" in data
                data = data.replace(b"numpy._core.multiarray", b"numpy.core.multiarray")
            z.writestr(info.filename, data)
    (tmp_path / "old.pth").write_bytes(buf.getvalue())
    res = import_rt4dgs(tmp_path / "old.pth", (0.0, 10.0))
    assert torch.equal(res.model.params["xyz"], stored["_xyz"]) and res.spatial_lr_scale == pytest.approx(4.4)


def test_cli_writes_checkpoint_and_warns_on_static_time_sh(tmp_path, capsys):
    stored = write_official(tmp_path / "chkpnt7000.pth", raw_tensors(30, seed=4, temporal_sh=False), iteration=7000)
    out = tmp_path / "model.safetensors"
    rc = omg4_main(["import-rt4dgs", str(tmp_path / "chkpnt7000.pth"), "--out", str(out), "--time-range", "0", "1",
                    "--json", str(tmp_path / "s.json"), "--sh-direction", "canonical"])
    assert rc == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "warning" in err[0] and "--legacy-rotation" in err[0]
    model, meta = load_gaussians(out)
    assert torch.equal(model.params["features_rest"], stored["_features_rest"])
    assert model.config.sh_direction == "canonical"
    assert model.config.time_range == (0.0, 1.0) and meta["iteration"] == 7000 and meta["source"] == "rt4dgs-official"
    assert (tmp_path / "s.json").exists()


def test_env_map_warns(tmp_path):
    write_official(tmp_path / "e.pth", raw_tensors(5), env_map=torch.nn.Parameter(torch.zeros(3, 8, 8)))
    res = import_rt4dgs(tmp_path / "e.pth", (0.0, 10.0))
    assert any("environment map" in w for w in res.warnings)


def _replace(index, value):
    return lambda args: tuple(value if i == index else a for i, a in enumerate(args))


@pytest.mark.parametrize("items, match", [
    (lambda a: a[:12], "gaussian_dim=3"),
    (lambda a: a[:18], "18 items"),
    (_replace(13, torch.zeros(7, 1)), "_t has shape"),
    (_replace(3, torch.zeros(20, 10, 3)), "SH coefficients"),
    (_replace(16, False), "rot_4d"),
    (_replace(1, torch.full((20, 3), float("nan"))), "NaN"),
    (_replace(5, "not a tensor"), "is str, expected a dense tensor"),
    (_replace(1, torch.zeros(20, 3).to_sparse()), "sparse.*expected a dense tensor"),
    (_replace(5, torch.randn(20, 4).index_fill(0, torch.tensor([3]), 0.0)), "_rotation holds a zero quaternion"),
    (_replace(18, 5), "active SH degrees"),
    (_replace(1, torch.zeros(20)), "_xyz has shape"),
    (lambda a: tuple(v[:0] if isinstance(v, torch.Tensor) and v.ndim else v for v in a), "no Gaussians"),
])
def test_malformed_checkpoints(tmp_path, items, match):
    write_official(tmp_path / "bad.pth", raw_tensors(20), items=items)
    with pytest.raises(CorruptFileError, match=match) as e:
        import_rt4dgs(tmp_path / "bad.pth", (0.0, 10.0))
    assert "\n" not in str(e.value)


class _Evil:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (pathlib.Path.touch, (self.marker,))


def test_unsafe_pickle_is_refused_without_running_code(tmp_path):
    marker = tmp_path / "pwned"
    torch.save(((_Evil(marker),) * 19, 1), tmp_path / "evil.pth")
    with pytest.raises(CorruptFileError, match="cannot be loaded safely"):
        import_rt4dgs(tmp_path / "evil.pth", (0.0, 10.0))
    assert not marker.exists()


def test_bad_files_and_arguments(tmp_path, capsys):
    with pytest.raises(CorruptFileError, match="no such"):
        import_rt4dgs(tmp_path / "missing.pth", (0.0, 10.0))
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint at all")
    with pytest.raises(CorruptFileError, match="junk.pth: (not a loadable|cannot be loaded safely)"):
        import_rt4dgs(tmp_path / "junk.pth", (0.0, 10.0))
    torch.save({"state": 1}, tmp_path / "dict.pth")
    with pytest.raises(CorruptFileError, match="model_args, iteration"):
        import_rt4dgs(tmp_path / "dict.pth", (0.0, 10.0))
    write_official(tmp_path / "ok.pth", raw_tensors(4))
    with pytest.raises(OMG4Error, match="time-range"):
        import_rt4dgs(tmp_path / "ok.pth", (5.0, 5.0))
    rc = omg4_main(["import-rt4dgs", str(tmp_path / "junk.pth"), "--out", str(tmp_path / "o.safetensors"),
                    "--time-range", "0", "10"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "junk.pth" in err[0]
    assert not (tmp_path / "o.safetensors").exists()
