"""One call from a trained baseline to an ``.omg4`` file (or a minimized checkpoint).

Computes (or reuses) the SD scores, runs the OMG4 pipeline, and encodes the result with
fp16 positions, time centres, codebooks and MLP weights (paper §4.4; omg4 §8).
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from omg4 import distributed
from omg4.codec.container import has_magic
from omg4.codec.payload import CompactGrids, CompressedPayload, check_codec, decode_payload, encode_payload
from omg4.codec.rig import rig_json
from omg4.codec.sequence import MAX_KEY_INTERVAL, read_index, valid_key_interval, write_sequence
from omg4.compress.model import CompressibleModel
from omg4.compress.pipeline import CompressConfig, CompressionPipeline
from omg4.compress.score import SDScores
from omg4.compress.stream import SegmentBefore
from omg4.data.scene import Scene
from omg4.data.segments import HOLD_LASTING_REMOVED, read_run_plan, shared_frames
from omg4.errors import OMG4Error
from omg4.gaussians import Gaussians4D
from omg4.gaussians.checkpoint import load_gaussians, run_model, save_gaussians
from omg4.models.compact import CompactModel
from omg4.optimize.teaching import taught_by

logger = logging.getLogger(__name__)


def baseline_file(path: str | Path) -> Path:
    """The checkpoint of a trained baseline: ``path`` itself (``model.safetensors``) or a training run's folder's;
    an ``.omg4`` file (already compressed) is a one-line error that says so."""
    path = run_model(path)
    if path.is_file() and has_magic(path):
        raise OMG4Error(f"{path} is a compressed .omg4 file: compression starts from the trained baseline "
                        "(its model.safetensors or its run folder)")
    return path


def read_baseline(path: str | Path, device="cpu") -> tuple[Gaussians4D, dict]:
    """The trained baseline to compress (:func:`baseline_file`) and its file's metadata (``iteration``: the steps
    it was trained for)."""
    return load_gaussians(baseline_file(path), device)


def trained_iterations(metadata: dict) -> int | None:
    """The steps a baseline was trained for, as its checkpoint records them (None when it does not)."""
    value = metadata.get("iteration")
    return value if isinstance(value, int) and not isinstance(value, bool) and value > 0 else None


def build_payload(model: CompressibleModel, meta: dict) -> CompressedPayload:
    """The file contents of a fully compressed model (every SVQ attribute and the MLPs present), as CPU arrays."""
    missing = [g.name for g in model.config.schema.svq_groups if g.name not in model.quantizers]
    if model.appearance is None or missing:
        raise OMG4Error(f"the model is not fully compressed (missing: {', '.join(missing) or 'appearance MLPs'}); "
                        "run every stage or use --stop-after to write a checkpoint")
    payload_meta = {
        **meta,
        "gaussian_config": model.config.to_json(),
        "active_sh_degree": model.active_sh_degree,
        "active_sh_degree_t": model.active_sh_degree_t,
    }
    return CompressedPayload(
        xyz=model.params["xyz"].detach().cpu().numpy().astype(np.float32),
        t=model.params["t"].detach().cpu().numpy().reshape(-1).astype(np.float32),
        attributes={a: q.to_quantized() for a, q in model.quantizers.items()},
        mlp=model.appearance.to_fp16_state(),
        meta=payload_meta,
        rotations=model.config.schema.quaternion_groups(),
        log_scaled=model.config.schema.log_scaled_groups(),
        carried=model.carried_rows if model.num_carried else None,
    )


def compress_to_file(baseline: Gaussians4D, scene: Scene, cfg: CompressConfig, out: str | Path, *,
                     codec: str | None = None, stop_after: str | None = None, scores_path: str | Path | None = None,
                     paper_copy: str | Path | None = None, precision: CompactGrids = CompactGrids(),
                     progress: bool = False, log=None, check_replicas: int = 0,
                     before: SegmentBefore | None = None) -> dict:
    """Run OMG4 on ``baseline`` and write ``out`` (``codec``: None, the coder of ``cfg``'s mode; ``precision``: the
    compact codec's grids); returns a JSON-ready report. The file's header and the report name the mode of the
    run (:meth:`CompressConfig.mode`: ``"paper"``, ``"omg4"`` or which choices were mixed).

    ``before``: for a predicted segment of a sequence, the segment before, decoded (:mod:`omg4.compress.stream`); the
    compression keeps its codebooks, starts from its appearance MLPs (``cfg.predicted_mlp``) and may carry its
    Gaussians (``cfg.carry``), and the file stores what it kept as references to it, the MLPs as their change, and no
    camera rig (a sequence's rig is its first segment's; docs/file-format.md §8a).

    ``paper_copy``: also write the same pipeline result with the paper-faithful coder there (the
    comparison point of the "compact" codec; its size is reported as ``paper_file_bytes``).

    SD scores are read from ``scores_path`` when given, else computed and saved beside
    ``out`` as ``<out>.scores.npz`` so ablation runs can reuse them: at once when no such file exists,
    else once ``out`` is written, so a failed run leaves an earlier run's scores as they were.

    In a distributed job (:mod:`omg4.distributed`) every rank runs the pipeline on its share of the views and
    rank 0 alone writes; every rank returns once the files exist.
    """
    main = distributed.world().main
    out = Path(out)
    cfg = replace(cfg, codec=codec) if codec else cfg
    codec = cfg.choice("codec")
    check_codec(codec, precision)  # before the pipeline's minutes, not after
    t0 = time.perf_counter()
    scores = SDScores.load(scores_path, baseline.num_gaussians) if scores_path else None
    pipeline = CompressionPipeline(baseline, scene, cfg, scores=scores, progress=progress, log=log,
                                   check_replicas=check_replicas, before=before)
    scores_out, unsaved = out.with_name(out.name + ".scores.npz"), None
    if scores is None and any(s in cfg.stages for s in ("sample", "prune", "sample+prune")):
        unsaved = pipeline.ensure_scores()
        if not scores_out.exists():  # nothing to lose: kept for a re-run even if a later stage fails
            if main:
                unsaved.save(scores_out)
            unsaved = None
    model = pipeline.run(stop_after=stop_after)
    meta = {"preset": pipeline.size.name, "stages": list(cfg.stages), "mode": cfg.mode(), "scene": scene.name,
            "time_range": list(scene.time_range), "normalization": scene.normalization.to_json()}
    if before is None:  # a predicted segment leaves the rig to its sequence's first segment
        meta["rig"] = rig_json(scene.cameras(), len(scene.test_cameras()))
    if cfg.rate_weight:  # provenance of entropy-constrained codebooks; paper-faithful files stay as they were
        meta["rate_weight"] = cfg.rate_weight
    if model.carry_decision is not None:  # a predicted segment: what it carried and why
        meta["carry"] = model.carry_decision
    paper: dict[str, int] = {}  # the paper coder's file size, when a copy is written
    sections: dict[str, int] = {}
    file_bytes = None
    reference = before.sections if before is not None else None
    if main:
        if stop_after is not None:
            save_gaussians(out, model.to_gaussians(), {**meta, "stopped_after": stop_after})
        else:
            payload = build_payload(model, meta)
            sections = encode_payload(payload, out, codec=codec, precision=precision, reference=reference)
            if paper_copy is not None:
                paper["paper_file_bytes"] = sum(encode_payload(payload, paper_copy, codec="paper",
                                                               reference=reference).values())
        if unsaved is not None:  # an earlier run's scores give way only to a finished run's
            unsaved.save(scores_out)
        file_bytes = out.stat().st_size
    sections, paper, file_bytes = distributed.gather_objects((sections, paper, file_bytes),
                                                             "writing the compressed file")[0]
    return {
        "output": str(out),
        "file_bytes": file_bytes,
        "sections": sections,
        **paper,
        "num_gaussians": model.num_gaussians + model.num_carried,
        "carried_gaussians": model.num_carried,
        "baseline_gaussians": baseline.num_gaussians,
        "wall_time_s": time.perf_counter() - t0,
        "stages": [{**asdict(r), "steps_per_second": r.steps_per_second} for r in pipeline.records],
        "config": {"preset": pipeline.size.name, "backbone": baseline.config.backbone, "stages": list(cfg.stages),
                   "mode": meta["mode"],
                   "schedule": cfg.schedule, "codec": codec, "grids": asdict(precision),
                   "tau_gs": pipeline.size.tau_gs, "prune_quantile": pipeline.size.prune_quantile,
                   "rate_weight": cfg.rate_weight,
                   "device": str(pipeline.device)},
    }


def refuse_held(path: Path, metadata: dict) -> None:
    """A segment trained with ``--hold-lasting`` (``held`` in the ``metadata`` of its file ``path``) is a one-line
    error: that training was removed, and its held Gaussians would be compressed as the segment's own."""
    if "held" in metadata:
        raise OMG4Error(f"{path}: trained with --hold-lasting ({HOLD_LASTING_REMOVED}): train the segments again")


def compress_segments(run_dir: str | Path, load_scene, cfg: CompressConfig, out: str | Path, *,
                      codec: str | None = None, precision: CompactGrids = CompactGrids(), progress: bool = False,
                      log=None, check_replicas: int = 0, teach: bool = True,
                      key_interval: int | None = None) -> dict:
    """Compress every segment of a segmented training run (:mod:`omg4.train.segmented`) and write them as one
    sequence file (:mod:`omg4.codec.sequence`) at ``out``; ``load_scene(start, stop)`` gives a segment's scene.
    ``codec`` and ``key_interval`` left None follow ``cfg``'s mode (:mod:`omg4.compress.modes`).

    Every ``key_interval``-th segment (the first included) is a key segment, coded alone; each other one is
    predicted from the segment before (beyond the paper): compressed with that segment's decoded codebooks, kept as
    they are, and its appearance MLPs as a start (``cfg.predicted_mlp``), and stored with references to them and
    the MLPs' change (``compress_to_file``'s ``before``).

    One segment's scene and models are held at a time, and the segment before's compressed model: with ``teach``
    a segment's training views of the frames it shares with the one before show the crossfade from that model's
    renders into the video (:func:`omg4.optimize.teaching.taught_by`), so the two compressed models agree where
    playback shows mostly the one before (beyond the paper). Returns the report: per segment the
    :func:`compress_to_file` report, and the file's bytes, duration and bitrate.
    """
    log = log or logger.info
    cfg = replace(cfg, **{k: v for k, v in (("codec", codec), ("key_interval", key_interval)) if v is not None})
    codec, key_interval = cfg.choice("codec"), cfg.choice("key_interval")
    if not valid_key_interval(key_interval):
        raise OMG4Error(f"the key interval must be an integer from 1 to {MAX_KEY_INTERVAL}, got {key_interval!r}")

    run_dir, out = Path(run_dir), Path(out)
    plan = read_run_plan(run_dir)
    main = distributed.world().main
    work = out.with_name(f".{out.name}.segments")  # each segment's file, until the sequence is written
    if main:
        work.mkdir(parents=True, exist_ok=True)
    parts, references, reports, t0 = [], [], [], time.perf_counter()
    teacher, before, previous = None, None, None  # previous: the segment before's decoded payload
    try:
        for i, seg in enumerate(plan["segments"]):
            predicted = previous is not None and i % key_interval != 0
            segment_before = SegmentBefore.decoded(previous) if predicted else None
            references.append(i - 1 if predicted else None)
            log(f"segment {seg['index']}: frames {seg['frames'][0]}-{seg['frames'][1] - 1}"
                + (f", predicted from segment {i - 1}" if predicted else ", a key segment" if key_interval > 1 else ""))
            scene = load_scene(*seg["frames"])
            shared = shared_frames(before, seg) if teacher is not None else None
            if shared is not None:
                scene = taught_by(scene, teacher, shared, background=cfg.background, backend=cfg.backend,
                                  device=cfg.device)
            trained_path = run_dir / seg["folder"] / "model.safetensors"
            baseline, trained = load_gaussians(trained_path, cfg.device)
            refuse_held(trained_path, trained)
            path = work / f"segment_{seg['index']:03d}.omg4"
            reports.append(compress_to_file(baseline, scene, cfg, path, precision=precision,
                                            progress=progress, log=log, check_replicas=check_replicas,
                                            before=segment_before))
            if main:
                parts.append((tuple(seg["frames"]), tuple(seg["time_range"]), path.read_bytes()))
            if (teach or key_interval > 1) and seg is not plan["segments"][-1]:
                # every rank decodes rank 0's file: the next segment's teacher and reference
                blob = distributed.gather_objects(parts[-1][2] if main else None, "sharing the segment")[0]
                previous = decode_payload(blob, segment_before.sections if segment_before is not None else None)
                if teach:
                    teacher, before = CompactModel(previous, cfg.device), seg
            del scene, baseline
        mode = cfg.mode(sequence=True)
        if main:
            write_sequence(out, parts, fps=plan["fps"], meta={"segment_frames": plan["segment_frames"],
                                                              "overlap": plan["overlap"], "mode": mode},
                           references=references, key_interval=key_interval)
    finally:
        if main:
            shutil.rmtree(work, ignore_errors=True)
    distributed.barrier("writing the sequence")
    index = read_index(out)
    return {"output": str(out), "file_bytes": index.total_bytes, "segments": reports, "key_interval": key_interval,
            "mode": mode,
            "references": [e.reference for e in index.segments],
            "num_gaussians": sum(r["num_gaussians"] for r in reports), "duration_s": index.duration_s,
            "bitrate_mbps": index.bitrate_mbps, "wall_time_s": time.perf_counter() - t0}
