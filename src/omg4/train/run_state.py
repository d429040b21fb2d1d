"""Checkpoints of a training run: model, optimizer and densification state, written atomically.

A run folder holds ``config.json``, ``checkpoints/model_XXXXXXX.safetensors`` (the model in
the safe format of :mod:`omg4.gaussians.checkpoint`) and ``checkpoints/state_XXXXXXX.pt``
(optimizer moments and densification statistics: tensors and plain numbers only, read back
with ``torch.load(weights_only=True)``). The state file is written after the model file, so
a state file's presence marks a complete checkpoint. Both hold CPU tensors whatever the
training device; :func:`load_run_checkpoint` puts them on the device asked for.
"""

from __future__ import annotations

import re
from pathlib import Path

import torch

from omg4.atomic import atomic_path
from omg4.errors import CorruptFileError, OMG4Error
from omg4.gaussians.checkpoint import load_gaussians, save_gaussians

_STATE_RE = re.compile(r"state_(\d{7})\.pt$")
RUN_FILES = ("config.json", "model.safetensors", "checkpoints", "segments.json")
"""What a run folder holds (the final model beside its configuration and checkpoints)."""


def checkpoint_paths(run_dir: Path, iteration: int) -> tuple[Path, Path]:
    folder = Path(run_dir) / "checkpoints"
    return folder / f"model_{iteration:07d}.safetensors", folder / f"state_{iteration:07d}.pt"


def save_run_checkpoint(run_dir: Path, iteration: int, model, optimizer, stats, metadata: dict,
                        extra_state: dict | None = None, keep_last: int = 2) -> Path:
    """Write the checkpoint of ``iteration`` (``extra_state``: more of the training state, by name) and remove older
    ones beyond ``keep_last``."""
    model_path, state_path = checkpoint_paths(run_dir, iteration)
    save_gaussians(model_path, model, {**metadata, "iteration": iteration})
    state = _to_cpu({
        "iteration": iteration,
        "optimizer": optimizer.state_dict(),
        "stats": {"grad_sum": stats.grad_sum, "visible_views": stats.visible_views, "max_radii": stats.max_radii},
        **(extra_state or {}),
    })
    with atomic_path(state_path) as tmp:
        torch.save(state, tmp)
    for old in sorted(_complete_iterations(run_dir))[:-keep_last]:
        for p in checkpoint_paths(run_dir, old):
            p.unlink(missing_ok=True)
    return model_path


def _to_cpu(obj):
    """``obj`` (nested dicts, lists and tuples) with every tensor moved to the CPU."""
    if isinstance(obj, torch.Tensor):
        return obj.cpu()
    if isinstance(obj, dict):
        return {k: _to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_to_cpu(v) for v in obj)
    return obj


def _complete_iterations(run_dir: Path) -> list[int]:
    folder = Path(run_dir) / "checkpoints"
    if not folder.is_dir():
        return []
    its = [int(m.group(1)) for p in folder.iterdir() if (m := _STATE_RE.search(p.name))]
    return [i for i in its if checkpoint_paths(run_dir, i)[0].exists()]


def latest_iteration(run_dir: Path) -> int | None:
    """The last complete checkpoint's iteration, or None."""
    its = _complete_iterations(run_dir)
    return max(its) if its else None


def load_run_checkpoint(run_dir: Path, iteration: int, device: torch.device | str = "cpu"):
    """(model, metadata, state dict) of a saved iteration: the model and the densification
    statistics on ``device``; the optimizer state stays on the CPU (``Optimizer.load_state_dict``
    moves it to its parameters' device)."""
    model_path, state_path = checkpoint_paths(run_dir, iteration)
    model, metadata = load_gaussians(model_path, device)
    try:
        state = torch.load(state_path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many kinds on damaged files
        raise CorruptFileError(f"{state_path}: cannot read training state ({type(e).__name__})") from None
    state["stats"] = {k: v.to(device) for k, v in state["stats"].items()}
    return model, metadata, state


def holds_files(run_dir: Path) -> bool:
    """Whether ``run_dir`` exists and holds anything (a run's files or others): training there needs
    ``--resume`` or ``--force``, so an earlier run is never silently replaced or mixed with a new one."""
    run_dir = Path(run_dir)
    try:
        return run_dir.is_dir() and any(run_dir.iterdir())
    except OSError as exc:
        raise OMG4Error(f"cannot look into {run_dir}: {exc.strerror or exc}") from None


def clear_run(run_dir: Path) -> None:
    """Delete a run's checkpoints and final model (``--force``), so a fresh run cannot resume from or keep them.
    Other files in the folder are left alone."""
    run_dir = Path(run_dir)
    folder = run_dir / "checkpoints"
    if folder.is_dir():
        for p in folder.iterdir():
            if re.fullmatch(r"(model_\d{7}\.safetensors|state_\d{7}\.pt)", p.name):
                p.unlink()
    (run_dir / "model.safetensors").unlink(missing_ok=True)
