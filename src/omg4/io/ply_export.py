"""Standard 3DGS ``.ply`` export of a time slice (data §5).

Layout read by SuperSplat, PlayCanvas and most viewers: ``binary_little_endian``, one
``vertex`` element with float properties ``x y z nx ny nz f_dc_0..2 f_rest_0.. opacity
scale_0..2 rot_0..3``; ``f_rest`` is channel-major (all R coefficients, then G, then B);
``opacity`` is a logit, ``scale_i`` = log σ_i, ``rot`` a (w, x, y, z) quaternion.

A 4D model at time τ becomes: centre = conditional mean, covariance = conditional
covariance → log-scales + quaternion (eigendecomposition), opacity = logit(σ(o)·p_t),
Gaussians with p_t ≤ the cull threshold dropped, and the 4D SH time terms at τ folded into
3D SH (rt4dgs §1.4, §2). The slice is written in the 3DGS viewers' y-down world
(:data:`omg4.io.worlds.PLY`: (x, y, z) → (−x, −z, −y) of omg4's +Z-up one), so SuperSplat and PlayCanvas show it
upright; a ``comment from_omg4_world`` header line holds the matrix. With a :class:`Normalization` the slice is
mapped back to the dataset's original world instead (positions, covariances and the SH view directions), written
as it is, and a ``comment up`` line names that world's up direction. Written with numpy only (``plyfile`` is GPL).
"""

from __future__ import annotations

import copy
import os

import numpy as np
import torch

from omg4.atomic import atomic_path
from omg4.data.scene import Normalization
from omg4.errors import OMG4Error
from omg4.gaussians.model import Gaussians4D, StaticSlice, static_slice
from omg4.gaussians.sh import rgb_to_sh, sh_basis
from omg4.io import worlds
from omg4.render.view import TimeSlice


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) of rotation matrices, inverse of the 3DGS ``build_rotation``.

    Shepperd's method, vectorized: each row uses the largest of the four diagonal
    combinations. R: [M, 3, 3] proper rotations → [M, 4].
    """
    r = R
    diag = np.stack([1 + r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2], 1 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2],
                     1 - r[:, 0, 0] + r[:, 1, 1] - r[:, 2, 2], 1 - r[:, 0, 0] - r[:, 1, 1] + r[:, 2, 2]], axis=1)
    a = 0.5 * np.sqrt(np.maximum(diag, 1e-30))  # [M, 4] candidate |w|, |x|, |y|, |z|
    wx, wy, wz = r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]
    xy, xz, yz = r[:, 0, 1] + r[:, 1, 0], r[:, 0, 2] + r[:, 2, 0], r[:, 1, 2] + r[:, 2, 1]
    cand = np.stack([
        np.stack([a[:, 0], wx / (4 * a[:, 0]), wy / (4 * a[:, 0]), wz / (4 * a[:, 0])], 1),
        np.stack([wx / (4 * a[:, 1]), a[:, 1], xy / (4 * a[:, 1]), xz / (4 * a[:, 1])], 1),
        np.stack([wy / (4 * a[:, 2]), xy / (4 * a[:, 2]), a[:, 2], yz / (4 * a[:, 2])], 1),
        np.stack([wz / (4 * a[:, 3]), xz / (4 * a[:, 3]), yz / (4 * a[:, 3]), a[:, 3]], 1),
    ], axis=1)  # [M, 4 candidates, 4]
    q = cand[np.arange(len(r)), diag.argmax(axis=1)]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def covariance_to_scale_rotation(covars: np.ndarray, min_var: float = 1e-24) -> tuple[np.ndarray, np.ndarray]:
    """Log-scales and quaternions with ``R diag(σ²) Rᵀ = Σ`` (eigendecomposition).

    covars: [M, 3, 3] symmetric PSD → (log σ [M, 3], quaternion (w, x, y, z) [M, 4]).
    Eigenvalues below ``min_var`` are raised to it. A non-finite covariance (a scale that overflows float64) is a
    one-line :class:`OMG4Error`.
    """
    if not np.isfinite(covars).all():
        raise OMG4Error("a Gaussian's covariance is not finite (its scale overflows float64); nothing written")
    lam, vec = np.linalg.eigh(covars)
    vec = vec.copy()
    vec[np.linalg.det(vec) < 0, :, 2] *= -1  # proper rotation
    return 0.5 * np.log(np.maximum(lam, min_var)), rotation_to_quaternion(vec)


def sh_rotation_matrix(rotation: np.ndarray, degree: int, num_samples: int = 64) -> np.ndarray:
    """Block-diagonal X [K, K], K = (degree+1)², with Σ_j c_j Y_j(R d) = Σ_k (X c)_k Y_k(d) for every d.

    Each degree-l block is the exact linear map between the (2l+1)-dimensional SH spaces,
    found by least squares on fixed sample directions. rotation: [3, 3] orthogonal.
    """
    rng = np.random.default_rng(0)
    d = rng.normal(size=(num_samples, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    A = sh_basis(torch.from_numpy(d), degree).numpy()
    B = sh_basis(torch.from_numpy(d @ np.asarray(rotation, dtype=np.float64).T), degree).numpy()
    K = A.shape[1]
    X = np.zeros((K, K))
    for l in range(degree + 1):  # at most 4 blocks
        s = slice(l * l, (l + 1) ** 2)
        X[s, s] = np.linalg.lstsq(A[:, s], B[:, s], rcond=None)[0]
    return X


def _logit(p: np.ndarray, eps: float = 1e-7) -> np.ndarray:
    p = np.clip(p, eps, 1 - eps)
    return np.log(p) - np.log1p(-p)


def turned_covariances_and_sh(covars: np.ndarray, sh: np.ndarray,
                              turn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A slice's covariances [M, 3, 3] and SH [M, K, 3] in a world turned by ``turn`` [3, 3] (x → turn · x): turn Σ turnᵀ,
    and the SH whose colour along turn · d is the one before along d (:func:`sh_rotation_matrix` of turnᵀ)."""
    degree = int(round(np.sqrt(sh.shape[1]))) - 1
    return (np.einsum("ij,njk,lk->nil", turn, covars, turn),
            np.einsum("kj,njc->nkc", sh_rotation_matrix(turn.T, degree), sh))


def in_export_world(means: np.ndarray, covars: np.ndarray, sh: np.ndarray, normalization: Normalization | None,
                    turn: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A slice of omg4's normalized world (means [M, 3], covariances, SH) in the world an export writes: with
    ``normalization``, the dataset's original world as it is; else omg4's turned by ``turn`` (:mod:`omg4.io.worlds`)
    into the format's convention."""
    if normalization is not None:
        return _to_original_world(means, covars, sh, normalization)
    return (means @ turn.T, *turned_covariances_and_sh(covars, sh, turn))


def original_up(normalization: Normalization) -> np.ndarray:
    """The normalized world's +z (omg4's up) in the dataset's original world."""
    return np.asarray(normalization.rotation, np.float64).T @ [0.0, 0.0, 1.0]


def _to_original_world(means: np.ndarray, covars: np.ndarray, sh: np.ndarray,
                       normalization: Normalization) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Map a slice from the normalized world (x_n = s (R x + t)) back to the original world."""
    R, s = np.asarray(normalization.rotation, dtype=np.float64), float(normalization.scale)
    covars, sh = turned_covariances_and_sh(covars, sh, R.T)  # Rᵀ Σ R; directions d_n = R d_o
    return normalization.invert_points(means), covars / (s * s), sh


def write_3dgs_ply(path: str | os.PathLike, means: np.ndarray, covars: np.ndarray, opacities: np.ndarray,
                   sh: np.ndarray, comments: tuple[str, ...] = ()) -> None:
    """Write Gaussians in the standard 3DGS layout (atomically), in the world they are given.

    Args:
        means: [M, 3]; covars: [M, 3, 3]; opacities: [M] in (0, 1);
        sh: [M, K, 3] coefficient-major SH (K = 1, 4, 9 or 16; DC first).
        comments: header ``comment`` lines (ASCII, one line each).
    """
    m, k = sh.shape[0], sh.shape[1]
    if k not in (1, 4, 9, 16):
        raise ValueError(f"{k} SH coefficients is not a 3DGS layout")
    log_scales, quats = covariance_to_scale_rotation(np.asarray(covars, dtype=np.float64))
    rest = np.transpose(sh[:, 1:, :], (0, 2, 1)).reshape(m, 3 * (k - 1))  # channel-major
    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(rest.shape[1])]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    columns = np.concatenate([means, np.zeros((m, 3)), sh[:, 0, :], rest, _logit(np.asarray(opacities))[:, None],
                              log_scales, quats], axis=1)
    with np.errstate(over="ignore", invalid="ignore"):
        columns = columns.astype("<f4")
    if not np.isfinite(columns).all():
        raise OMG4Error(f"{path}: the model's values are not finite in float32 (NaN or beyond ±3.4e38); nothing "
                        "written")
    header = "\n".join(["ply", "format binary_little_endian 1.0", *[f"comment {c}" for c in comments],
                        f"element vertex {m}",
                        *[f"property float {n}" for n in names], "end_header"]) + "\n"
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(np.ascontiguousarray(columns).tobytes())


def export_ply(path: str | os.PathLike, model, timestamp: float, *, normalization: Normalization | None = None) -> int:
    """Write the time slice of ``model`` at ``timestamp`` as a standard 3DGS ``.ply``.

    ``model``: a :class:`Gaussians4D` or a render-only model (a loaded checkpoint or decoded
    ``.omg4`` file, :func:`omg4.models.load_model`; its appearance MLPs give the SH). The
    model's active SH degrees are kept (spatial degree → f_rest count; temporal bands folded
    at τ). The output is in the 3DGS viewers' world (module docstring), or with ``normalization`` in the dataset's
    original one. A sequence of segments writes the slice of the segment weighing most at ``timestamp``. Returns
    the number of Gaussians written.
    """
    means, covars, opacities, sh = world_slice(model, timestamp, normalization, worlds.PLY)
    write_3dgs_ply(path, means, covars, opacities, sh, _world_comments(normalization))
    return len(means)


def _world_comments(normalization: Normalization | None) -> tuple[str, ...]:
    """The header comments naming the world a ``.ply`` export writes (:func:`in_export_world`)."""
    if normalization is not None:
        return "omg4 world: original", "up " + " ".join(f"{x:.9g}" for x in original_up(normalization))
    return ("omg4 world: normalized, y down (3DGS viewers)",
            "from_omg4_world " + " ".join(f"{x:g}" for x in worlds.PLY.ravel()))


def world_slice(model, timestamp: float, normalization: Normalization | None, turn: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(means [M, 3], covariances [M, 3, 3], opacities [M], 3D SH [M, K, 3]) of the time slice of ``model`` at
    ``timestamp`` (:func:`slice_in_float64`; a sequence: its segment weighing most there), float64, in the world an
    export writes (:func:`in_export_world`: omg4's turned by ``turn``, or with ``normalization`` the dataset's)."""
    if hasattr(model, "segment_at"):
        model = model.segment_at(timestamp)
    sl = slice_in_float64(model, timestamp)
    means, covars, sh = in_export_world(sl.means.numpy(), sl.covars.numpy(), sl.sh.numpy(), normalization, turn)
    return means, covars, sl.opacities.numpy(), sh


def model_in_float64(model) -> tuple[dict[str, torch.Tensor], "torch.nn.Module | None"]:
    """(per-Gaussian values, appearance MLPs or None) of a :class:`Gaussians4D` or a render-only model, as
    float64 CPU copies: exports compute in double precision whatever the model's device."""
    values = model.params if isinstance(model, Gaussians4D) else model.values
    values = {k: v.detach().to("cpu", torch.float64) for k, v in values.items()}
    appearance = getattr(model, "appearance", None)
    if appearance is not None:
        appearance = copy.deepcopy(appearance).to("cpu", torch.float64)
    return values, appearance


def slice_in_float64(model, timestamp: float) -> StaticSlice:
    """:func:`~omg4.gaussians.model.static_slice` of ``model`` at ``timestamp``, computed in float64 on the CPU."""
    if not np.isfinite(timestamp):
        raise OMG4Error(f"export time must be finite, got {timestamp}")
    values, appearance = model_in_float64(model)
    with torch.no_grad():
        return static_slice(values, model.config, model.active_sh_degree, model.active_sh_degree_t, float(timestamp),
                            appearance=appearance)


def export_time_slice_ply(path: str | os.PathLike, time_slice: TimeSlice, *,
                          normalization: Normalization | None = None) -> int:
    """Write any model's :class:`TimeSlice` (view-dependent colours baked to DC) as a 3DGS ``.ply``, in the world
    :func:`export_ply` writes."""
    sl = {k: getattr(time_slice, k).detach().to("cpu", torch.float64).numpy()
          for k in ("means", "covars", "colors", "opacities")}
    means, covars, sh = in_export_world(sl["means"], sl["covars"], rgb_to_sh(sl["colors"])[:, None, :], normalization,
                                        worlds.PLY)
    write_3dgs_ply(path, means, covars, sl["opacities"], sh, _world_comments(normalization))
    return int(means.shape[0])


__all__ = ["rotation_to_quaternion", "covariance_to_scale_rotation", "sh_rotation_matrix", "turned_covariances_and_sh",
           "in_export_world", "original_up", "write_3dgs_ply",
           "export_ply", "export_time_slice_ply", "model_in_float64", "slice_in_float64", "world_slice"]
