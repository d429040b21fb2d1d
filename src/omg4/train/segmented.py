"""Training a long capture segment by segment (:mod:`omg4.data.segments`): one baseline per segment.

The run folder holds the plan (``segments.json``: each segment's frames, time range and folder) and one
ordinary run folder per segment (``segment_000/``: checkpoints, ``config.json``, ``model.safetensors``). A
segment whose model exists is done; one with checkpoints resumes from its last; so a stopped run continues
segment by segment. Only one segment's frames, Gaussians and optimizer are held at a time. In a distributed
job the ranks either train every segment together (data-parallel, the default) or each train whole segments
on their own (``parallel="segments"``: rank r takes segments r, r + W, …).

Neighbours agree where they are blended (beyond the paper): a segment starts from the Gaussians of the one
before that can be drawn in its time range (:func:`warm_start`), so the two render the same shared frames at its
first step, and it learns those frames as the crossfade from that segment's renders into the video
(:func:`omg4.optimize.teaching.taught_by`), so the blend of the two models moves from one to the other without a jump. Such a segment
holds at most as many Gaussians as the first one (:func:`segment_budget`), so memory stays flat however long the
capture. ``teach=False``, and ``parallel="segments"``, where the segment before may not be trained yet, start every
segment afresh and learn every frame from the video.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
from pathlib import Path
from typing import Callable

import torch

from omg4 import distributed
from omg4.atomic import write_text_atomic
from omg4.data.scene import Scene
from omg4.data.segments import PLAN_FILE, Segment, plan_segments, segment_folder, shared_frames
from omg4.errors import OMG4Error
from omg4.gaussians.checkpoint import describe_checkpoint
from omg4.gaussians.model import Gaussians4D
from omg4.gaussians.visibility import peak_marginal
from omg4.models import load_model
from omg4.optimize.teaching import taught_by
from omg4.render.projection import ALPHA_THRESHOLD
from omg4.train.config import TrainConfig
from omg4.train.run_state import latest_iteration
from omg4.train.trainer import Trainer, initial_model

logger = logging.getLogger(__name__)

PARALLEL_MODES = ("data", "segments")


def default_overlap(segment_frames: int) -> int:
    """The frames neighbouring segments share unless told: a sixth of a segment, at least one."""
    return max(1, round(segment_frames / 6))


def plan_capture(capture: Scene, segment_frames: int, overlap: int | None = None) -> dict:
    """The plan (:func:`segment_plan`) that cuts a multi-view video capture (``capture``: its views need not be
    decoded) into segments of ``segment_frames`` frames sharing ``overlap`` (default :func:`default_overlap`).
    A scene without a frame sequence (Blender, D-NeRF) or with gaps in its frames is a one-line error."""
    if capture.format not in ("n3dv", "panoptic"):
        raise OMG4Error(f"--segment-frames cuts multi-view video into segments of frames; a {capture.format} scene "
                        "has no frame sequence to cut")
    frames = sorted({v.frame_index for v in capture.train_views})
    if frames != list(range(frames[0], frames[-1] + 1)):
        raise OMG4Error("--segment-frames needs a contiguous range of frames")
    fps = len(frames) / (capture.time_range[1] - capture.time_range[0])
    overlap = default_overlap(segment_frames) if overlap is None else overlap
    return segment_plan(plan_segments(len(frames), segment_frames, overlap), fps, frames[0], segment_frames, overlap)


def segment_plan(segments: list[Segment], fps: float, first_frame: int, segment_frames: int | None,
                 overlap: int) -> dict:
    """The plan a segmented run records (frames counted from the capture's first, times in seconds)."""
    return {"fps": fps, "segment_frames": segment_frames, "overlap": overlap, "segments": [
        {"index": s.index, "frames": [first_frame + s.start, first_frame + s.stop],
         "time_range": [(first_frame + s.start) / fps, (first_frame + s.stop) / fps], "folder": segment_folder(s.index)}
        for s in segments]}


def write_plan(run_dir: Path, plan: dict) -> None:
    """Record ``plan`` in ``run_dir`` (rank 0); a folder already holding another plan is refused."""
    path = Path(run_dir) / PLAN_FILE
    if path.exists():
        try:
            existing = json.loads(path.read_text())
        except (OSError, ValueError):
            existing = None
        if existing != json.loads(json.dumps(plan)):
            raise OMG4Error(f"{run_dir} holds a run with other segments: use another --out, or --force to start afresh")
        return
    if distributed.world().main:
        Path(run_dir).mkdir(parents=True, exist_ok=True)
        write_text_atomic(path, json.dumps(plan, indent=2) + "\n")


def warm_start(teacher, scene: Scene, cfg: TrainConfig, points=None) -> Gaussians4D:
    """The model a segment starts from: ``teacher``'s (the segment before's, as :func:`omg4.models.load_model`
    gives its checkpoint) Gaussians that can be drawn somewhere in ``scene``'s time range — opacity times the
    peak temporal marginal over the range (:func:`~omg4.gaussians.visibility.peak_marginal`) at least the
    rasterizer's :data:`~omg4.render.projection.ALPHA_THRESHOLD`, so no other carried Gaussian could change a
    frame — joined by Gaussians made from ``points`` (:func:`~omg4.train.trainer.initial_model`) for what the
    segment before never showed, as many as ``cfg.strategy.max_gaussians`` leaves room for (the most opaque carried
    Gaussians first when they alone exceed it)."""
    values = {k: v.detach().to("cpu") for k, v in teacher.values.items()}
    var_t = teacher.config.schema.motion(values, teacher.config)[2]
    opacity = torch.sigmoid(values["opacity"].reshape(-1).double())
    peak = opacity * peak_marginal(values["t"], var_t, *scene.time_range)
    keep = peak >= ALPHA_THRESHOLD
    config = dataclasses.replace(teacher.config, time_range=tuple(scene.time_range))
    alive = torch.nonzero(keep).reshape(-1)
    budget = cfg.strategy.max_gaussians
    if budget and len(alive) > budget:
        alive = alive[torch.argsort(opacity[alive], descending=True, stable=True)[:budget]].sort().values
    parts = [{k: values[k][alive] for k in config.schema.param_names}]
    if not budget or len(alive) < budget:
        room = budget - len(alive) if budget else 0  # 0: no cap
        parts.append(initial_model(scene, cfg.with_strategy(max_gaussians=room), points).params)
    return Gaussians4D({k: torch.cat([part[k].detach() for part in parts]) for k in config.schema.param_names},
                       config)  # the trainer sets the active SH degrees of each step


def segment_budget(cfg: TrainConfig, first_count: int) -> TrainConfig:
    """The training settings of a segment that starts from the one before (:func:`warm_start`): at most as many
    Gaussians as the first segment, which learnt from the video alone, holds (``first_count``), or
    ``cfg.strategy.max_gaussians`` when that is smaller. Without it the carried Gaussians stay and densification adds
    a fresh segment's worth on top, so every segment would be larger than the one before."""
    budget = cfg.strategy.max_gaussians
    return cfg.with_strategy(max_gaussians=min(budget, first_count) if budget else first_count)


def train_segments(run_dir: Path, plan: dict, cfg: TrainConfig, load_scene: Callable[[int, int], Scene],
                   initial_points: Callable[[Scene], object], *, parallel: str = "data", check_replicas: int = 0,
                   teach: bool = True, log=None, preset: str | None = None) -> list[dict]:
    """Train every segment of ``plan`` not yet done; returns one summary per segment (this rank's, in segment
    order; with ``parallel="segments"`` the others' segments are read from their folders)."""
    log = log or logger.info
    if parallel not in PARALLEL_MODES:
        raise OMG4Error(f"unknown --parallel {parallel!r} (choose from {', '.join(PARALLEL_MODES)})")
    world = distributed.world()
    mine = world.shard(plan["segments"]) if parallel == "segments" else plan["segments"]
    for seg in mine:
        folder = Path(run_dir) / seg["folder"]
        if (folder / "model.safetensors").is_file():
            log(f"segment {seg['index']}: done")
            continue
        with distributed.alone() if parallel == "segments" else contextlib.nullcontext():
            resume = latest_iteration(folder) is not None
            scene = load_scene(*seg["frames"])
            points = None if resume else initial_points(scene)
            before = plan["segments"][seg["index"] - 1] if seg["index"] else None
            shared = shared_frames(before, seg) if teach and parallel != "segments" else None
            start, seg_cfg = None, cfg
            if shared is not None:
                first = Path(run_dir) / plan["segments"][0]["folder"] / "model.safetensors"
                before_path = Path(run_dir) / before["folder"] / "model.safetensors"
                teacher = load_model(before_path, cfg.device)
                seg_cfg = segment_budget(cfg, describe_checkpoint(first)["num_gaussians"])
                if not resume:
                    start = warm_start(teacher, scene, seg_cfg, points)
                scene = taught_by(scene, teacher, shared, background=cfg.background, backend=cfg.backend,
                                  device=cfg.device)
            log(f"segment {seg['index']}: frames {seg['frames'][0]}-{seg['frames'][1] - 1}"
                f"{' (resuming)' if resume else ''}")
            Trainer(scene, seg_cfg, folder, points=points, model=start, resume=resume, log=log,
                    check_replicas=check_replicas, preset=preset).run()
            del scene
    distributed.barrier("training the segments")
    return [{"index": seg["index"], "frames": seg["frames"],
             **describe_checkpoint(Path(run_dir) / seg["folder"] / "model.safetensors")} for seg in plan["segments"]]


__all__ = ["PARALLEL_MODES", "default_overlap", "plan_capture", "segment_plan", "write_plan", "warm_start",
           "segment_budget", "train_segments"]
