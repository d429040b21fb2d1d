"""Import of official Real-Time4DGS checkpoints (``chkpnt*.pth``, rt4dgs §5).

The official file is ``torch.save((model_args, iteration))`` with ``model_args`` the 19-tuple
of ``GaussianModel.capture()`` (gaussian_dim = 4): CUDA ``nn.Parameter`` tensors, the Adam
``state_dict`` and plain numbers. It is read with ``torch.load(weights_only=True)``: no code
from the file runs. The only non-tensor globals such files contain are numpy scalars
(``spatial_lr_scale`` and the learning rates are ``numpy.float64`` in the official code), so
numpy's scalar constructor and a few dtype classes are allow-listed for the load, under both
their numpy-2 and numpy-1 module names.

The file does not record the time range (needed for the SH period) or the 4D rotation
convention, so both come from the caller (§5 conversion notes).
"""

from __future__ import annotations

import os
import pickle
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from omg4.errors import CorruptFileError, OMG4Error
from omg4.gaussians.checkpoint import save_gaussians
from omg4.gaussians.model import GaussianConfig, Gaussians4D

# index in the 19-tuple of GaussianModel.capture() (rt4dgs §5) → our parameter name
OFFICIAL_PARAM_INDEX = {
    "xyz": 1, "features_dc": 2, "features_rest": 3, "scaling": 4, "rotation": 5, "opacity": 6,
    "t": 13, "scaling_t": 14, "rotation_r": 15,
}
IDX_ACTIVE_SH, IDX_OPTIMIZER, IDX_LR_SCALE, IDX_ROT_4D, IDX_ENV_MAP, IDX_ACTIVE_SH_T = 0, 11, 12, 16, 17, 18
NUM_ITEMS_4D, NUM_ITEMS_3D = 19, 12


def _numpy_safe_globals() -> list:
    """The numpy globals a checkpoint with numpy scalars needs (numpy-2 and numpy-1 names)."""
    scalar = np._core.multiarray.scalar
    dtypes = [np.dtypes.Float64DType, np.dtypes.Float32DType, np.dtypes.Int64DType, np.dtypes.Int32DType,
              np.dtypes.BoolDType]
    return [scalar, (scalar, "numpy.core.multiarray.scalar"), np.dtype, *dtypes]


@dataclass
class ImportResult:
    """What :func:`import_rt4dgs` produced: the model, its iteration, and one-line warnings."""

    model: Gaussians4D
    iteration: int | None
    spatial_lr_scale: float | None
    warnings: list[str] = field(default_factory=list)


def read_official_checkpoint(path: str | os.PathLike) -> tuple[tuple, int | None]:
    """``(model_args, iteration)`` of an official checkpoint, loaded with ``weights_only=True`` on the CPU."""
    path = Path(path)
    if not path.is_file():
        raise CorruptFileError(f"{path}: no such checkpoint file")
    try:
        with torch.serialization.safe_globals(_numpy_safe_globals()):
            obj = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        raise CorruptFileError(f"{path}: cannot be loaded safely: damaged, or holds Python objects other than "
                               "tensors, numbers and containers") from None
    except Exception as e:  # torch raises many kinds on damaged or foreign files
        raise CorruptFileError(f"{path}: not a loadable torch checkpoint ({type(e).__name__})") from None
    if not (isinstance(obj, (tuple, list)) and len(obj) == 2 and isinstance(obj[0], (tuple, list))):
        raise CorruptFileError(f"{path}: expected torch.save((model_args, iteration)) of Real-Time4DGS")
    model_args, iteration = obj
    if len(model_args) == NUM_ITEMS_3D:
        raise CorruptFileError(f"{path}: a 3D Gaussian (gaussian_dim=3) checkpoint; only 4D ones can be imported")
    if len(model_args) != NUM_ITEMS_4D:
        raise CorruptFileError(f"{path}: model_args has {len(model_args)} items, expected {NUM_ITEMS_4D} "
                               "(Real-Time4DGS gaussian_dim=4)")
    return tuple(model_args), (int(iteration) if isinstance(iteration, (int, np.integer)) else None)


def _sh_layout(path: Path, num_coeffs: int) -> tuple[int, int]:
    """(sh_degree, sh_degree_t) of an official coefficient count: 16·(deg_t + 1) with spatial degree 3."""
    for deg_t in range(3):
        if num_coeffs == 16 * (deg_t + 1):
            return 3, deg_t
    raise CorruptFileError(f"{path}: {num_coeffs} SH coefficients per channel; expected 16, 32 or 48")


def _params_from_args(path: Path, args: tuple) -> dict[str, torch.Tensor]:
    params = {}
    for name, idx in OFFICIAL_PARAM_INDEX.items():
        v = args[idx]
        if not isinstance(v, torch.Tensor) or v.layout != torch.strided:
            kind = type(v).__name__ if not isinstance(v, torch.Tensor) else f"a {v.layout} tensor"
            raise CorruptFileError(f"{path}: item {idx} ({name}) is {kind}, expected a dense tensor")
        params[name] = v.detach().to("cpu", torch.float32).contiguous().clone()
    if params["xyz"].ndim != 2 or params["xyz"].shape[1] != 3:
        raise CorruptFileError(f"{path}: _xyz has shape {tuple(params['xyz'].shape)}, expected [N, 3]")
    n = params["xyz"].shape[0]
    if n == 0:
        raise CorruptFileError(f"{path}: the checkpoint holds no Gaussians")
    k_rest = params["features_rest"].shape[1] if params["features_rest"].ndim == 3 else -1
    expected = {"t": (n, 1), "scaling": (n, 3), "scaling_t": (n, 1), "rotation": (n, 4), "rotation_r": (n, 4),
                "opacity": (n, 1), "features_dc": (n, 1, 3), "features_rest": (n, k_rest, 3)}
    for name, shape in expected.items():
        if tuple(params[name].shape) != shape:
            raise CorruptFileError(f"{path}: _{name} has shape {tuple(params[name].shape)}, expected {list(shape)} "
                                   f"for N={n}")
    for name, v in params.items():
        if not torch.isfinite(v).all():
            raise CorruptFileError(f"{path}: _{name} contains NaN or Inf")
    for name in ("rotation", "rotation_r"):  # normalized at use: a zero quaternion has no rotation
        if (params[name] == 0).all(dim=1).any():
            raise CorruptFileError(f"{path}: _{name} holds a zero quaternion")
    return params


def import_rt4dgs(path: str | os.PathLike, time_range: tuple[float, float], *, legacy_rotation: bool = False,
                  sh_direction: str = "conditioned") -> ImportResult:
    """Convert an official ``chkpnt*.pth`` into a :class:`Gaussians4D` (raw values kept as they are).

    Args:
        path: the official checkpoint.
        time_range: (t0, t1) the model was trained with (``time_duration``; N3V [0, 10],
            D-NeRF [0, 1]); T = t1 − t0 is the 4D SH period.
        legacy_rotation: use the pre-900c592 unflipped 4D rotation (rt4dgs §1.2).
        sh_direction: ``"conditioned"`` or ``"canonical"`` (official CUDA forward, rt4dgs §1.6-1).
    """
    path = Path(path)
    t0, t1 = float(time_range[0]), float(time_range[1])
    if not (np.isfinite([t0, t1]).all() and t1 > t0):
        raise OMG4Error(f"--time-range must be two finite numbers T0 < T1, got {t0} {t1}")
    args, iteration = read_official_checkpoint(path)
    if not (isinstance(args[IDX_ROT_4D], (bool, np.bool_)) and args[IDX_ROT_4D]):
        raise CorruptFileError(f"{path}: rot_4d is {args[IDX_ROT_4D]!r}; only rot_4d=True checkpoints are supported")
    params = _params_from_args(path, args)
    num_coeffs = params["features_rest"].shape[1] + 1
    sh_degree, sh_degree_t = _sh_layout(path, num_coeffs)
    active = args[IDX_ACTIVE_SH], args[IDX_ACTIVE_SH_T]
    if not all(isinstance(a, (int, np.integer)) for a in active):
        raise CorruptFileError(f"{path}: active SH degrees {active!r} are not integers")
    active_deg, active_deg_t = int(active[0]), int(active[1])
    if not (0 <= active_deg <= sh_degree and 0 <= active_deg_t <= sh_degree_t):
        raise CorruptFileError(f"{path}: active SH degrees ({active_deg}, {active_deg_t}) exceed the stored "
                               f"layout ({sh_degree}, {sh_degree_t})")
    warnings = []
    if sh_degree_t > 0 and not params["features_rest"][:, 15:].any():
        hint = "" if legacy_rotation else "; if so, import with --legacy-rotation"
        warnings.append(f"all temporal SH coefficients are zero: probably trained before commit 3fe460f "
                        f"(September 2024) with the unflipped 4D rotation{hint}")
    if args[IDX_ENV_MAP] is not None:
        warnings.append("the checkpoint has an environment map; it is not imported (background will be black)")
    lr_scale = args[IDX_LR_SCALE]
    config = GaussianConfig(time_range=(t0, t1), sh_degree=sh_degree, sh_degree_t=sh_degree_t,
                            rotation_convention="legacy" if legacy_rotation else "flip", sh_direction=sh_direction)
    model = Gaussians4D(params, config, active_deg, active_deg_t)
    return ImportResult(model=model, iteration=iteration,
                        spatial_lr_scale=float(lr_scale) if isinstance(lr_scale, (int, float, np.number)) else None,
                        warnings=warnings)


def import_rt4dgs_file(path: str | os.PathLike, out: str | os.PathLike, time_range: tuple[float, float], *,
                       legacy_rotation: bool = False, sh_direction: str = "conditioned") -> ImportResult:
    """:func:`import_rt4dgs` and write the model as an omg4 checkpoint to ``out`` (atomically)."""
    result = import_rt4dgs(path, time_range, legacy_rotation=legacy_rotation, sh_direction=sh_direction)
    metadata = {
        "source": "rt4dgs-official",
        "source_file": Path(path).name,
        "iteration": result.iteration,
        "spatial_lr_scale": result.spatial_lr_scale,
        "time_range": list(result.model.config.time_range),
    }
    save_gaussians(out, result.model, metadata)
    return result


__all__ = ["ImportResult", "OFFICIAL_PARAM_INDEX", "read_official_checkpoint", "import_rt4dgs", "import_rt4dgs_file"]
