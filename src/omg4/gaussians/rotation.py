"""3D and 4D rotations from quaternions (w, x, y, z).

A 4D rotation is built from a left and a right unit quaternion as in Real-Time4DGS
(rt4dgs §1.2): ``A = M_l(q_l) @ M_r(q_r)`` where ``M_l`` is left multiplication by
``q_l`` and ``M_r`` is right multiplication by the conjugate of ``q_r``. Two conventions:

* ``"flip"`` (official code since commit 900c592, our default): ``R4 = P A P`` with ``P`` the
  index reversal, i.e. ``R4[i, j] = A[3 - i, 3 - j]``. Then ``q_l == q_r`` gives a pure spatial
  rotation that leaves the time axis untouched (a static Gaussian).
* ``"legacy"`` (official code before 900c592): ``R4 = A``.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

ROTATION_CONVENTIONS = ("flip", "legacy")


def normalize_quaternion(q: torch.Tensor) -> torch.Tensor:
    """``q / ‖q‖`` along the last axis (``F.normalize`` like the official code). q: [..., 4]."""
    return F.normalize(q, dim=-1)


def build_rotation_3d(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices of (unnormalized) quaternions, the 3DGS ``build_rotation`` formula.

    Args:
        q: [N, 4] quaternions (w, x, y, z); normalized here.
    Returns:
        [N, 3, 3] rotation matrices.
    """
    w, x, y, z = normalize_quaternion(q).unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def left_isoclinic(q: torch.Tensor) -> torch.Tensor:
    """M_l of rt4dgs §1.2: the matrix of ``v ↦ q ⊗ v``. q: [N, 4] unit → [N, 4, 4]."""
    a, b, c, d = q.unbind(-1)
    rows = (a, -b, -c, -d,
            b, a, -d, c,
            c, d, a, -b,
            d, -c, b, a)
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 4, 4)


def right_isoclinic(q: torch.Tensor) -> torch.Tensor:
    """M_r of rt4dgs §1.2: the matrix of ``v ↦ v ⊗ conj(q)``. q: [N, 4] unit → [N, 4, 4]."""
    p, qq, r, s = q.unbind(-1)
    rows = (p, qq, r, s,
            -qq, p, -s, r,
            -r, s, p, -qq,
            -s, -r, qq, p)
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 4, 4)


@functools.lru_cache(maxsize=None)
def product_table(convention: str, dtype: torch.dtype, device: str) -> torch.Tensor:
    """[16, 16] constant C with ``R4(q_l, q_r).flatten() = (q_l ⊗ q_r).flatten() @ C``.

    Every entry of ``M_l(q_l) @ M_r(q_r)`` is bilinear in the two quaternions, so row ``4a + b``
    of C is the rotation built from the basis quaternions ``e_a`` and ``e_b``.
    """
    if convention not in ROTATION_CONVENTIONS:
        raise ValueError(f"unknown rotation convention '{convention}' (expected one of {ROTATION_CONVENTIONS})")
    eye = torch.eye(4, dtype=torch.float64, device="cpu")
    table = left_isoclinic(eye).repeat_interleave(4, 0) @ right_isoclinic(eye).repeat(4, 1, 1)  # [16, 4, 4]
    if convention == "flip":
        table = table.flip(-2, -1)
    return table.reshape(16, 16).to(dtype=dtype, device=device)


def build_rotation_4d(q_l: torch.Tensor, q_r: torch.Tensor, convention: str = "flip") -> torch.Tensor:
    """4D rotation from a left and a right quaternion (rt4dgs §1.2).

    Computed in closed form as one ``[N, 16] @ [16, 16]`` product of the quaternions' outer
    product with a constant table (no batched 4×4 matrix products).

    Args:
        q_l: [N, 4] left quaternion (w, x, y, z), unnormalized.
        q_r: [N, 4] right quaternion, unnormalized.
        convention: ``"flip"`` (official current) or ``"legacy"`` (official before 900c592).
    Returns:
        [N, 4, 4] rotation matrices acting on (x, y, z, t) column vectors.
    """
    table = product_table(convention, q_l.dtype, str(q_l.device))
    outer = normalize_quaternion(q_l).unsqueeze(-1) * normalize_quaternion(q_r).unsqueeze(-2)  # [N, 4, 4]
    return (outer.reshape(-1, 16) @ table).reshape(*q_l.shape[:-1], 4, 4)


__all__ = ["ROTATION_CONVENTIONS", "normalize_quaternion", "build_rotation_3d", "left_isoclinic", "right_isoclinic",
           "build_rotation_4d", "product_table"]
