"""Standard 3DGS .ply export of a time slice, read back with an independent tiny PLY reader."""

import math

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from scipy.special import sph_harm_y

from omg4.data.scene import Normalization
from omg4.gaussians import GaussianConfig, Gaussians4D
from omg4.io.ply_export import export_ply, export_time_slice_ply, rotation_to_quaternion

C0 = 0.28209479177387814


PLY_WORLD = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, -1.0, 0.0]])
"""The 3DGS viewers' y-down world a .ply is written in, from omg4's +Z-up one: (x, y, z) → (−x, −z, −y)."""


def read_ply(path):
    """Minimal binary_little_endian float-only PLY reader → (names, structured array)."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    n = int(next(ln for ln in lines if ln.startswith("element vertex")).split()[2])
    names = [ln.split()[2] for ln in lines if ln.startswith("property")]
    assert all(ln.split()[1] == "float" for ln in lines if ln.startswith("property"))
    body = data[end:]
    assert len(body) == n * 4 * len(names)
    return names, np.frombuffer(body, dtype=[(nm, "<f4") for nm in names], count=n)


def quat_to_matrix(q):
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    return Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # scipy uses (x, y, z, w)


def eval_real_sh(coeffs, d):
    """Σ_k Y_k(d) c_k with the 3DGS real SH basis built from scipy. coeffs [N, K, 3]."""
    theta, phi = np.arccos(np.clip(d[:, 2], -1, 1)), np.arctan2(d[:, 1], d[:, 0])
    degree = int(round(math.sqrt(coeffs.shape[1]))) - 1
    cols = []
    for l in range(degree + 1):
        for m in range(-l, l + 1):
            y = sph_harm_y(l, abs(m), theta, phi)
            cols.append(math.sqrt(2) * (y.real if m > 0 else y.imag) if m else y.real)
    return np.einsum("nk,nkc->nc", np.stack(cols, 1), coeffs)


def model64(n=60, seed=0, degrees=(3, 2)):
    g = torch.Generator().manual_seed(seed)
    params = {
        "xyz": torch.randn(n, 3, generator=g), "t": torch.rand(n, 1, generator=g) * 10,
        "scaling": torch.randn(n, 3, generator=g) * 0.4 - 1.5, "scaling_t": torch.randn(n, 1, generator=g) * 0.3 + 0.5,
        "rotation": torch.randn(n, 4, generator=g), "rotation_r": torch.randn(n, 4, generator=g),
        "opacity": torch.randn(n, 1, generator=g), "features_dc": torch.randn(n, 1, 3, generator=g) + 1.5,
        "features_rest": torch.randn(n, 47, 3, generator=g) * 0.1,
    }
    return Gaussians4D({k: v.double() for k, v in params.items()}, GaussianConfig(time_range=(0.0, 10.0)), *degrees)


def ply_gaussians(names, v):
    means = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    log_s = np.stack([v[f"scale_{i}"] for i in range(3)], 1).astype(np.float64)
    q = np.stack([v[f"rot_{i}"] for i in range(4)], 1).astype(np.float64)
    R = quat_to_matrix(q)
    cov = R @ (np.exp(2 * log_s)[:, :, None] * np.swapaxes(R, 1, 2))
    n_rest = sum(nm.startswith("f_rest_") for nm in names)
    k = n_rest // 3 + 1
    sh = np.zeros((len(v), k, 3))
    sh[:, 0] = np.stack([v[f"f_dc_{c}"] for c in range(3)], 1)
    rest = np.stack([v[f"f_rest_{i}"] for i in range(n_rest)], 1).reshape(len(v), 3, k - 1)  # channel-major
    sh[:, 1:] = np.transpose(rest, (0, 2, 1))
    return means, cov, 1 / (1 + np.exp(-v["opacity"].astype(np.float64))), sh


def test_export_layout_and_values(tmp_path):
    model, tau, cam = model64(), 3.7, np.array([0.4, -5.0, 0.7])
    count = export_ply(tmp_path / "s.ply", model, tau)
    names, v = read_ply(tmp_path / "s.ply")
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert names[54:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    sl = model.slice_at(tau, torch.from_numpy(cam))
    assert count == len(v) == sl.index.numel() and 0 < count < 60
    means, cov, opac, sh = ply_gaussians(names, v)  # in the y-down world
    np.testing.assert_allclose(means, sl.means.numpy() @ PLY_WORLD.T, atol=2e-6)
    np.testing.assert_allclose(cov, PLY_WORLD @ sl.covars.numpy() @ PLY_WORLD.T, rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(opac, sl.opacities.numpy(), rtol=1e-5, atol=1e-7)
    d = means - PLY_WORLD @ cam  # the camera in the same world: the colours it sees are the model's
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    np.testing.assert_allclose(np.maximum(eval_real_sh(sh, d) + 0.5, 0), sl.colors.numpy(), atol=2e-5)
    assert not np.any([v["nx"], v["ny"], v["nz"]])
    header = (tmp_path / "s.ply").read_bytes().split(b"end_header")[0].decode().splitlines()
    written = next(ln for ln in header if ln.startswith("comment from_omg4_world ")).split()[2:]
    np.testing.assert_array_equal(np.array(written, float).reshape(3, 3), PLY_WORLD)


def test_export_keeps_active_degree(tmp_path):
    model = model64(degrees=(1, 0))
    export_ply(tmp_path / "s.ply", model, 5.0)
    names, v = read_ply(tmp_path / "s.ply")
    assert sum(nm.startswith("f_rest_") for nm in names) == 9
    cam = np.array([3.0, 1.0, -2.0])
    sl = model.slice_at(5.0, torch.from_numpy(cam))
    means, _, _, sh = ply_gaussians(names, v)
    d = (means - PLY_WORLD @ cam) / np.linalg.norm(means - PLY_WORLD @ cam, axis=1, keepdims=True)
    np.testing.assert_allclose(np.maximum(eval_real_sh(sh, d) + 0.5, 0), sl.colors.numpy(), atol=2e-5)


def test_export_in_original_world(tmp_path):
    """x_n = s (R x_o + t): positions, covariances and view-dependent colours map back to the original world."""
    model, tau = model64(seed=1), 6.0
    R = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    norm = Normalization(scale=0.25, rotation=R, translation=np.array([1.0, -2.0, 0.5]))
    cam_n = np.array([0.2, -4.0, 1.0])
    cam_o = norm.invert_points(cam_n)
    export_ply(tmp_path / "o.ply", model, tau, normalization=norm)
    names, v = read_ply(tmp_path / "o.ply")
    means, cov, opac, sh = ply_gaussians(names, v)
    sl = model.slice_at(tau, torch.from_numpy(cam_n))
    np.testing.assert_allclose(means, norm.invert_points(sl.means.numpy()), rtol=1e-6, atol=1e-5)
    cov_o = np.einsum("ji,njk,kl->nil", R, sl.covars.numpy(), R) / 0.25**2
    np.testing.assert_allclose(cov, cov_o, rtol=1e-4, atol=1e-6)
    d = (means - cam_o) / np.linalg.norm(means - cam_o, axis=1, keepdims=True)
    np.testing.assert_allclose(np.maximum(eval_real_sh(sh, d) + 0.5, 0), sl.colors.numpy(), atol=5e-5)
    np.testing.assert_allclose(opac, sl.opacities.numpy(), rtol=1e-5, atol=1e-7)


def test_time_slice_export_bakes_colours(tmp_path):
    model = model64(seed=2)
    sl = model.slice_at(2.0, torch.tensor([0.0, 0.0, -4.0], dtype=torch.float64))
    assert export_time_slice_ply(tmp_path / "t.ply", sl) == sl.index.numel()
    names, v = read_ply(tmp_path / "t.ply")
    assert not any(nm.startswith("f_rest_") for nm in names)
    dc = np.stack([v[f"f_dc_{c}"] for c in range(3)], 1)
    np.testing.assert_allclose(0.5 + C0 * dc, sl.colors.numpy(), atol=1e-6)


def test_rotation_to_quaternion_round_trip():
    q = np.random.default_rng(3).normal(size=(500, 4))
    q[:4] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]  # each Shepperd branch
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    back = rotation_to_quaternion(quat_to_matrix(q))
    np.testing.assert_allclose(np.abs(np.sum(back * q, axis=1)), 1.0, atol=1e-12)  # same up to sign
    np.testing.assert_allclose(quat_to_matrix(back), quat_to_matrix(q), atol=1e-12)


def test_empty_slice_writes_valid_file(tmp_path):
    assert export_ply(tmp_path / "e.ply", model64(), -1000.0) == 0
    names, v = read_ply(tmp_path / "e.ply")
    assert len(v) == 0 and len(names) == 62


def test_float32_model_exports_like_float64(tmp_path):
    m64 = model64(seed=4)
    m32 = Gaussians4D({k: v.float() for k, v in m64.params.items()}, m64.config, 3, 2)
    export_ply(tmp_path / "a.ply", m64, 4.0)
    export_ply(tmp_path / "b.ply", m32, 4.0)
    (names, a), (_, b) = read_ply(tmp_path / "a.ply"), read_ply(tmp_path / "b.ply")
    means_a, cov_a, _, sh_a = ply_gaussians(names, a)
    means_b, cov_b, _, sh_b = ply_gaussians(names, b)
    np.testing.assert_allclose(means_b, means_a, atol=1e-5)
    np.testing.assert_allclose(cov_b, cov_a, atol=1e-5)
    np.testing.assert_allclose(sh_b, sh_a, atol=1e-5)


def test_values_beyond_float32_are_refused_and_nothing_is_written(tmp_path):
    import pytest

    from omg4.errors import OMG4Error

    model = model64()
    model.params["features_dc"][:] = 1e300  # finite in the float64 model, not in the file's float32
    with pytest.raises(OMG4Error, match="not finite in float32"):
        export_ply(tmp_path / "m.ply", model, 5.0)
    assert not (tmp_path / "m.ply").exists()


def test_normalization_records_that_are_no_similarity_transform_are_refused():
    import pytest

    good = Normalization(2.0, Rotation.from_euler("xyz", [0.3, -0.2, 1.0]).as_matrix(), np.array([0.5, 0.0, -1.0]))
    assert Normalization.from_json(good.to_json()).scale == 2.0
    for change, match in ((dict(scale=0.0), "positive"), (dict(scale=float("nan")), "positive"),
                          (dict(rotation=(2 * np.eye(3)).tolist()), "orthonormal"),
                          (dict(rotation=np.full((3, 3), np.nan).tolist()), "orthonormal"),
                          (dict(translation=[0.0, float("inf"), 0.0]), "translation")):
        with pytest.raises(ValueError, match=match):
            Normalization.from_json({**good.to_json(), **change})
