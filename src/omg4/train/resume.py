"""What a resumed training run trains with: the settings its folder records, not the command line's defaults.

A run folder's ``config.json`` records every :class:`~omg4.train.config.TrainConfig` field it started with
(a segmented run: each segment's folder, the first segment's holding the run's own). Resuming takes those.
A setting given again, or the preset named again, must agree with the record; one that differs is a one-line
error, unless it comes as an explicit override (``omg4 train --resume --set iterations=6000``), which is applied and recorded. Where the
run computes and how often it reports (device, rasterizer, kernels, test and checkpoint intervals) are the current
command's choice: they do not change what is learnt.
"""

from __future__ import annotations

import json
from pathlib import Path

from omg4.data.segments import is_segmented_run, read_run_plan
from omg4.errors import OMG4Error
from omg4.settings import apply_settings
from omg4.train.config import TrainConfig, setting_of
from omg4.train.run_state import latest_iteration

PLACEMENT_FIELDS = ("device", "backend", "kernels", "test_interval", "checkpoint_interval")
"""Fields a resumed run may take from the current command: where it computes and how often it reports."""


def _record(run_dir: str | Path) -> tuple[dict, Path] | None:
    """(the parsed ``config.json`` of ``run_dir`` — a segmented run's first segment's —, its path), or None."""
    run_dir = Path(run_dir)
    if is_segmented_run(run_dir):
        segments = read_run_plan(run_dir)["segments"]
        run_dir = run_dir / segments[0]["folder"] if segments else run_dir
    path = run_dir / "config.json"
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
        if not isinstance(record, dict):
            raise TypeError("not a JSON object")
        return record, path
    except (OSError, ValueError, TypeError) as exc:
        raise OMG4Error(f"{path}: not a readable training record ({exc})") from None


def recorded_config(run_dir: str | Path) -> TrainConfig | None:
    """The settings ``run_dir`` records (its ``config.json``; a segmented run's first segment's), or None when the
    folder records none. A damaged record is a one-line error."""
    found = _record(run_dir)
    if found is None:
        return None
    record, path = found
    try:
        return TrainConfig.from_dict(record["train_config"])
    except (KeyError, TypeError, ValueError) as exc:
        raise OMG4Error(f"{path}: not a readable training record ({exc})") from None


def recorded_preset(run_dir: str | Path) -> str | None:
    """The preset ``run_dir``'s settings started from, where its record names one."""
    found = _record(run_dir)
    preset = found[0].get("preset") if found else None
    return preset if isinstance(preset, str) else None


def resumed_config(recorded: TrainConfig, *, asked: dict, preset: str | None = None,
                   recorded_preset: str | None = None, overrides: dict | None = None) -> TrainConfig:
    """The settings a resumed run trains with: ``recorded``, then the placement fields of ``asked`` (the values the
    command was given explicitly, by flag or settings file), then ``overrides`` (``--set``); both by dotted names
    (``strategy.densify_until``).

    Raises:
        OMG4Error: a value of ``asked`` other than a placement field differs from the record, or the named
            ``preset`` from the one the run started from (one line naming the setting, both values and the way to
            change it).
    """
    if preset is not None and recorded_preset is not None and preset != recorded_preset:
        raise OMG4Error(f"--preset {preset} contradicts the run's recorded preset {recorded_preset} (its "
                        "config.json); resume without it, or change single settings with --set KEY=VALUE")
    for name, value in asked.items():
        if value is None or name in PLACEMENT_FIELDS or name in (overrides or {}):
            continue
        old = setting_of(recorded, name)
        if _normalized(value) != _normalized(old):
            raise OMG4Error(f"{name} {value!r} contradicts the run's recorded {name} {old!r} (its config.json); "
                            f"resume without it, or change the setting with --set {name}=VALUE")
    placement = {k: v for k, v in asked.items() if k in PLACEMENT_FIELDS and v is not None}
    return apply_settings(recorded, {**placement, **(overrides or {})})


def _normalized(value):
    return tuple(value) if isinstance(value, list) else value


def finished(run_dir: str | Path, cfg: TrainConfig) -> bool:
    """Whether ``run_dir`` holds its final model and a checkpoint at (or past) ``cfg.iterations``."""
    run_dir = Path(run_dir)
    last = latest_iteration(run_dir)
    return (run_dir / "model.safetensors").is_file() and last is not None and last >= cfg.iterations


__all__ = ["PLACEMENT_FIELDS", "recorded_config", "recorded_preset", "resumed_config", "finished"]
