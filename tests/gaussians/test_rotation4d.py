"""4D / 3D rotations against an independent quaternion-product oracle (rt4dgs §1.2)."""

import numpy as np
import pytest
import torch

from omg4.gaussians import build_rotation_3d, build_rotation_4d

P = np.eye(4)[::-1]  # index reversal


def qmul(a, b):
    """Hamilton product of quaternions (w, x, y, z), float64 numpy [..., 4]."""
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                     w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                     w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=-1)


def conj(q):
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def oracle_rotation_4d(ql, qr, convention):
    """Columns A e_j = q_l ⊗ e_j ⊗ conj(q_r) (unit quaternions); flip: P A P."""
    ql = ql / np.linalg.norm(ql, axis=-1, keepdims=True)
    qr = qr / np.linalg.norm(qr, axis=-1, keepdims=True)
    cols = [qmul(qmul(ql, np.broadcast_to(e, ql.shape)), conj(qr)) for e in np.eye(4)]
    A = np.stack(cols, axis=-1)
    return P @ A @ P if convention == "flip" else A


def oracle_rotation_3d(q):
    """R v = Im(q ⊗ (0, v) ⊗ conj(q)) for unit q."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    cols = [qmul(qmul(q, np.broadcast_to(np.r_[0.0, e], q.shape)), conj(q))[..., 1:] for e in np.eye(3)]
    return np.stack(cols, axis=-1)


@pytest.fixture
def quats():
    g = np.random.default_rng(1)
    return g.normal(size=(64, 4)) * 3.0, g.normal(size=(64, 4)) * 0.5  # unnormalized on purpose


@pytest.mark.parametrize("convention", ["flip", "legacy"])
def test_rotation_4d_matches_quaternion_oracle(quats, convention):
    ql, qr = quats
    R = build_rotation_4d(torch.from_numpy(ql), torch.from_numpy(qr), convention).numpy()
    np.testing.assert_allclose(R, oracle_rotation_4d(ql, qr, convention), atol=1e-12)


@pytest.mark.parametrize("convention", ["flip", "legacy"])
def test_rotation_4d_orthonormal_det_one(quats, convention):
    ql, qr = quats
    R = build_rotation_4d(torch.from_numpy(ql), torch.from_numpy(qr), convention).numpy()
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(4), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)


@pytest.mark.parametrize("convention", ["flip", "legacy"])
def test_identity_quaternions_give_identity(convention):
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0], [2.5, 0.0, 0.0, 0.0]], dtype=torch.float64)
    R = build_rotation_4d(q, q, convention)
    assert torch.equal(R, torch.eye(4, dtype=torch.float64).expand(2, 4, 4))


def test_equal_quaternions_flip_is_static_spatial_rotation(quats):
    """rt4dgs §1.2: l == r = (w, x, y, z) → blockdiag(R3(w, −z, −y, −x), 1): the t axis is untouched."""
    q = quats[0]
    R = build_rotation_4d(torch.from_numpy(q), torch.from_numpy(q), "flip").numpy()
    w, x, y, z = q.T
    expected_3d = oracle_rotation_3d(np.stack([w, -z, -y, -x], axis=1))
    np.testing.assert_allclose(R[:, :3, :3], expected_3d, atol=1e-12)
    np.testing.assert_allclose(R[:, 3, :], np.broadcast_to([0, 0, 0, 1.0], (len(q), 4)), atol=1e-12)
    np.testing.assert_allclose(R[:, :, 3], np.broadcast_to([0, 0, 0, 1.0], (len(q), 4)), atol=1e-12)


def test_equal_quaternions_legacy_fixes_x_axis(quats):
    """Without the flip, l == r fixes the first (x) axis instead and mixes t with space."""
    q = quats[0]
    R = build_rotation_4d(torch.from_numpy(q), torch.from_numpy(q), "legacy").numpy()
    np.testing.assert_allclose(R[:, :, 0], np.broadcast_to([1.0, 0, 0, 0], (len(q), 4)), atol=1e-12)
    assert np.abs(R[:, 3, :3]).max() > 0.1


def test_rotation_3d_matches_sandwich_product(quats):
    q = quats[0]
    R = build_rotation_3d(torch.from_numpy(q)).numpy()
    np.testing.assert_allclose(R, oracle_rotation_3d(q), atol=1e-12)


def test_unknown_convention_rejected():
    q = torch.tensor([[1.0, 0, 0, 0]])
    with pytest.raises(ValueError, match="convention"):
        build_rotation_4d(q, q, "sideways")
