"""Loading any model file as a render-only model: a checkpoint, an ``.omg4`` file or sequence, a training run."""

from __future__ import annotations

import os
from pathlib import Path

import torch

from omg4.codec.container import has_magic
from omg4.codec.sequence import is_sequence
from omg4.data.segments import is_segmented_run, read_run_plan
from omg4.errors import CorruptFileError, OMG4Error
from omg4.gaussians.checkpoint import load_gaussians, run_model
from omg4.models.compact import load_omg4
from omg4.models.sequence import SequenceModel, load_sequence
from omg4.models.windowed import WindowedModel


def load_model(path: str | os.PathLike, device: torch.device | str = "cpu"):
    """A render-only model on ``device`` from a checkpoint (``.safetensors``), a compressed ``.omg4`` file, an
    ``.omg4`` sequence of segments, a training run's folder (its ``model.safetensors``) or a segmented training
    run's folder (``segments.json``).

    Single models come with a per-time-window visibility index (:class:`~omg4.models.windowed.WindowedModel`)
    and the file's metadata as ``.meta`` (scene name, time range, normalization); sequences and segmented runs
    are :class:`~omg4.models.sequence.SequenceModel` s, decoding each segment when first shown.
    """
    path = Path(path)
    if is_segmented_run(path):
        return load_segmented_run(path, device)
    path = run_model(path)
    if not path.is_file():
        raise OMG4Error(f"model file {path} does not exist")
    if is_sequence(path):
        return load_sequence(path, device)
    if has_magic(path):
        return load_omg4(path, device)
    if path.suffix.lower() == ".omg4":
        raise CorruptFileError(f"{path}: not an .omg4 file (wrong magic bytes)")
    model, meta = load_gaussians(path, device)
    return WindowedModel(model.params, model.config, model.active_sh_degree, model.active_sh_degree_t, meta=meta)


def load_segmented_run(run_dir: Path, device: torch.device | str = "cpu"):
    """A :class:`~omg4.models.sequence.SequenceModel` of a segmented run's final models (one per segment)."""
    plan = read_run_plan(run_dir)
    models = [run_dir / seg["folder"] / "model.safetensors" for seg in plan["segments"]]
    missing = [str(m) for m in models if not m.is_file()]
    if missing:
        raise OMG4Error(f"{run_dir}: segment models not trained yet ({missing[0]}{' …' if len(missing) > 1 else ''});"
                        " resume the training with --resume")
    return SequenceModel([tuple(seg["time_range"]) for seg in plan["segments"]],
                         lambda k: load_model(models[k], device), meta={"fps": plan["fps"]},
                         storage_bytes=sum(m.stat().st_size for m in models))


__all__ = ["load_model", "load_segmented_run"]
