"""Safe checkpoints of :class:`Gaussians4D` models (safetensors, no pickle).

A checkpoint is a safetensors file holding the backbone's raw parameters as float32 (written
from CPU copies whatever the model's device; read onto the caller's device) and one
metadata entry ``"omg4"``: a JSON object with ``format`` (``"omg4-<backbone>"``: ``omg4-rt4dgs``,
``omg4-freetimegs``), ``version``,
``config`` (:class:`GaussianConfig`), the active SH degrees, the Gaussian count and the
caller's ``metadata`` (scene normalization, time range, iteration, ...). Files are written
atomically; anything unreadable or of another kind raises :class:`CorruptFileError`.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import save_file

from omg4.atomic import atomic_path
from omg4.errors import CorruptFileError, OMG4Error
from omg4.gaussians.backbone import BACKBONES
from omg4.gaussians.model import GaussianConfig, Gaussians4D, param_shapes

FORMAT_VERSION = 1
_META_KEY = "omg4"


def save_gaussians(path: str | os.PathLike, model: Gaussians4D, metadata: dict | None = None) -> None:
    """Write ``model`` (params as float32) and JSON-serializable ``metadata`` to ``path`` atomically."""
    tensors = {k: model.params[k].detach().to("cpu", torch.float32).contiguous()
               for k in model.config.schema.param_names}
    header = {
        "format": f"omg4-{model.config.backbone}",
        "version": FORMAT_VERSION,
        "config": model.config.to_json(),
        "active_sh_degree": model.active_sh_degree,
        "active_sh_degree_t": model.active_sh_degree_t,
        "num_gaussians": model.num_gaussians,
        "metadata": metadata or {},
    }
    text = json.dumps(header)
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata={_META_KEY: text})


def _read_header(path: Path) -> tuple[dict, dict[str, tuple[int, ...]]]:
    """(omg4 header, {tensor name: shape}) without reading tensor data."""
    if not path.is_file():
        raise CorruptFileError(f"{path}: no such checkpoint file")
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            shapes = {k: tuple(f.get_slice(k).get_shape()) for k in f.keys()}
    except Exception as e:  # safetensors raises several kinds on damaged files
        raise CorruptFileError(f"{path}: not an omg4 model file (no .omg4 magic bytes, and not a readable "
                               f"safetensors checkpoint: {type(e).__name__})") from None
    try:
        header = json.loads(meta[_META_KEY])
    except (KeyError, ValueError):
        raise CorruptFileError(f"{path}: a safetensors file but not an omg4 checkpoint (no omg4 metadata)") from None
    if not isinstance(header, dict) or _backbone_of_format(header.get("format")) is None:
        kinds = " or ".join(b.title for b in BACKBONES.values())
        raise CorruptFileError(f"{path}: not an omg4 {kinds} checkpoint")
    if header.get("version") != FORMAT_VERSION:
        raise CorruptFileError(f"{path}: checkpoint format version {header.get('version')} is not supported "
                               f"(this omg4 reads version {FORMAT_VERSION})")
    if not isinstance(header.get("metadata") or {}, dict):
        raise CorruptFileError(f"{path}: the checkpoint's metadata is not a JSON object")
    return header, shapes


def _backbone_of_format(name: object) -> str | None:
    """The backbone named by a checkpoint's ``format`` (``"omg4-<backbone>"``), None for anything else."""
    if isinstance(name, str) and name.startswith("omg4-") and name[5:] in BACKBONES:
        return name[5:]
    return None


def _config_of(path: Path, header: dict) -> GaussianConfig:
    try:
        config = GaussianConfig.from_json(header["config"])
    except (KeyError, TypeError, ValueError) as e:
        raise CorruptFileError(f"{path}: invalid model config in checkpoint ({e})") from None
    if _backbone_of_format(header["format"]) != config.backbone:
        raise CorruptFileError(f"{path}: a {header['format']} checkpoint whose config names the {config.backbone} "
                               "backbone")
    return config


def run_model(path: str | os.PathLike) -> Path:
    """``path`` itself, or for a training run's folder its final ``model.safetensors``, so a run folder is accepted
    wherever a model file is; a run folder without its final model yet (it holds ``config.json`` or
    ``checkpoints/``) or any other folder is a one-line error."""
    path = Path(path)
    if not path.is_dir():
        return path
    model = path / "model.safetensors"
    if model.is_file():
        return model
    if (path / "config.json").is_file() or (path / "checkpoints").is_dir():
        raise OMG4Error(f"{path} is a training run without its final model yet: finish it with omg4 train --resume")
    raise OMG4Error(f"{path} is a folder, not a model file or a training run")


def load_gaussians(path: str | os.PathLike, device: torch.device | str = "cpu") -> tuple[Gaussians4D, dict]:
    """Read a checkpoint written by :func:`save_gaussians`.

    Returns:
        (model, metadata): parameters as float32 tensors on ``device`` without gradients,
        and the caller's metadata dict given at save time.
    Raises:
        CorruptFileError: missing, truncated, damaged or wrong-kind file, non-finite values, or no Gaussians.
    """
    path = Path(path)
    header, shapes = _read_header(path)
    config = _config_of(path, header)
    n = shapes.get("xyz", (0,))[0]
    if n == 0:
        raise CorruptFileError(f"{path}: the checkpoint holds no Gaussians")
    expected = param_shapes(n, config)
    names = config.schema.param_names
    for k in names:
        if shapes.get(k) != expected[k]:
            raise CorruptFileError(f"{path}: parameter '{k}' has shape {shapes.get(k)}, expected {expected[k]}")
    try:
        with safe_open(str(path), framework="pt") as f:
            params = {k: f.get_tensor(k) for k in names}
    except Exception as e:
        raise CorruptFileError(f"{path}: cannot read checkpoint tensors ({type(e).__name__})") from None
    for k, v in params.items():
        if v.dtype != torch.float32:
            raise CorruptFileError(f"{path}: parameter '{k}' has dtype {v.dtype}, expected float32")
        if not torch.isfinite(v).all():
            raise CorruptFileError(f"{path}: parameter '{k}' contains NaN or Inf")
    for k in (k for k in names if config.schema.attribute(k).activation == "quaternion"):
        if (params[k] == 0).all(dim=-1).any():  # normalized at use: a zero quaternion has no rotation
            raise CorruptFileError(f"{path}: parameter '{k}' holds a zero quaternion")
    try:
        model = Gaussians4D(params, config, header["active_sh_degree"], header["active_sh_degree_t"])
    except (KeyError, TypeError, ValueError) as e:
        raise CorruptFileError(f"{path}: inconsistent checkpoint ({e})") from None
    return model.to(device), dict(header.get("metadata") or {})


def describe_checkpoint(path: str | os.PathLike) -> dict:
    """Summary for ``omg4 info`` from the header alone: kind, Gaussian count, degrees, time range, size."""
    path = Path(path)
    header, shapes = _read_header(path)
    config = _config_of(path, header)
    size = path.stat().st_size
    meta = header.get("metadata") or {}
    return {
        "kind": f"{config.backbone}-checkpoint",
        "path": str(path),
        "format_version": header["version"],
        "num_gaussians": int(shapes.get("xyz", (0,))[0]),
        "sh_degree": config.sh_degree,
        "sh_degree_t": config.sh_degree_t,
        "active_sh_degree": header.get("active_sh_degree"),
        "active_sh_degree_t": header.get("active_sh_degree_t"),
        "backbone": config.backbone,
        "time_range": list(config.time_range),
        "rotation_convention": config.rotation_convention,
        "sh_direction": config.sh_direction,
        "file_size_bytes": size,
        "file_size_mb": size / 2**20,
        "metadata_keys": sorted(meta),
        **({"iteration": meta["iteration"]} if "iteration" in meta else {}),
    }


__all__ = ["FORMAT_VERSION", "save_gaussians", "load_gaussians", "describe_checkpoint"]
