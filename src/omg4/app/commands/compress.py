"""``omg4 compress DATA --model CKPT --out FILE.omg4 [--config FILE] [--set KEY=VALUE]``: run the OMG4 pipeline.

Every :class:`~omg4.compress.pipeline.CompressConfig` field (the merge and stage-length ones included) is
reachable (:mod:`omg4.settings`); ``<out>.config.json`` records them all with the codec and its grids, and
``--config`` of it reproduces the run."""

from __future__ import annotations

import argparse
import json
from dataclasses import astuple, replace
from pathlib import Path

from omg4.app.commands.common import (GRID_BITS_HELP, MAX_BATCH_SIZE, add_background_argument, add_codec_argument,
                                  add_device_arguments, add_distributed_arguments, add_force_argument,
                                  add_paper_argument, add_rate_weight_argument, add_scene_arguments, add_settings_arguments,
                                  compact_grids, device_from_args, fill_device_arguments, float_in, int_at_least,
                                  load_scene_from_args, seed, segment_scenes, settings_from_args)
from omg4.codec.sequence import DEFAULT_KEY_INTERVAL
from omg4.compress.appearance_stage import PREDICTED_MLPS
from omg4.compress.modes import BY_SETTING
from omg4.compress.pipeline import FULL_STAGES, CompressConfig
from omg4.compress.score import SCORE_WEIGHTINGS
from omg4.compress.time_balance import TIME_SAMPLINGS
from omg4.gaussians.backbone import BACKBONES
from omg4.compress.schedule import MINIMIZING_STAGES, SCHEDULES, STAGE_NAMES


#: the CompressConfig fields this command has its own flags for
SHORTCUTS = ("paper", "preset", "schedule", "stages", "num_merge", "batch_size", "tau_gs", "prune_quantile", "rate_weight",
             "official_score_quirk", "score_weighting", "frame_floor", "time_sampling", "baseline_iterations", "background", "backend",
             "device", "seed", "predicted_mlp", "codec", "key_interval", "kernels")
#: options of the command itself that a config file may set (as the record beside the output does)
COMMAND_KEYS = ("codec", "grid_bits")


def configure(p: argparse.ArgumentParser) -> None:
    add_scene_arguments(p)
    add_paper_argument(p)
    p.add_argument("--model", required=True, type=Path,
                   help="trained baseline checkpoint (.safetensors), or a segmented run's folder (train "
                        "--segment-frames): every segment is compressed into one sequence file")
    p.add_argument("--out", required=True, type=Path,
                   help="output .omg4 file (with --stop-after: a .safetensors checkpoint of the minimized model)")
    p.add_argument("--preset", choices=sorted({name for b in BACKBONES.values() for name in b.size_presets}),
                   help="size preset (paper appendix): " + "; ".join(
                       f"{', '.join(b.size_presets)} for {b.title} (default {b.default_preset})"
                       for b in BACKBONES.values()))
    p.add_argument("--schedule", choices=list(SCHEDULES),
                   help="fine-tuning lengths: official (1000 per stage, 5000 MLP; the default on cuda), cpu (a fifth; "
                        "the default elsewhere), short (a tenth, 600 MLP), tiny (smoke test)")
    p.add_argument("--stages",
                   help="comma-separated stages in order, from " + ", ".join(STAGE_NAMES) + " (default "
                        + ",".join(FULL_STAGES) + "; ablations: e.g. sample,appearance,svq3d,svq4d or "
                        "sample+prune,merge,appearance,svq3d,svq4d)")
    p.add_argument("--stop-after", choices=list(MINIMIZING_STAGES),
                   help="stop after this stage and write a checkpoint of the minimized model")
    p.add_argument("--batch-size", type=int_at_least(1, MAX_BATCH_SIZE),
                   help=f"views per fine-tuning step (default {CompressConfig.batch_size}, at most {MAX_BATCH_SIZE})")
    # the preset's sampling ratio, in (0, 1], and pruning quantile, in [0, 1), overridden (left to --settings)
    p.add_argument("--tau-gs", type=float_in(0.0, 1.0), help=argparse.SUPPRESS)
    p.add_argument("--prune-quantile", type=float_in(0.0, 1.0, low_open=False, high_open=True), help=argparse.SUPPRESS)
    add_codec_argument(p, from_settings=True)
    p.add_argument("--grid-bits", type=compact_grids, metavar="POS,ROT,TIME[,W,LS[,CB[,EX]]]", help=GRID_BITS_HELP)
    add_rate_weight_argument(p)
    p.add_argument("--scores", type=Path, help="reuse SD scores saved by an earlier run (.npz)")
    # settings with flags of their own that --help leaves to --settings (--paper switches the choices among them)
    p.add_argument("--num-merge", type=int_at_least(1), help=argparse.SUPPRESS)
    p.add_argument("--official-score-quirk", action="store_true", default=None, help=argparse.SUPPRESS)
    p.add_argument("--score-weighting", choices=list(SCORE_WEIGHTINGS), help=argparse.SUPPRESS)
    p.add_argument("--time-sampling", choices=list(TIME_SAMPLINGS), help=argparse.SUPPRESS)
    p.add_argument("--frame-floor", type=float, help=argparse.SUPPRESS)
    p.add_argument("--baseline-iterations", type=int_at_least(1), help=argparse.SUPPRESS)
    p.add_argument("--predicted-mlp", choices=list(PREDICTED_MLPS), help=argparse.SUPPRESS)
    add_background_argument(p)
    add_device_arguments(p, from_settings=True)
    p.add_argument("--seed", type=seed, help=f"random seed (default {CompressConfig.seed})")
    p.add_argument("--json", type=Path, help="write the stage log and sizes as JSON")
    p.add_argument("--independent-segments", action="store_true",
                   help="a segmented run: each segment learns every frame from the video (by default a segment "
                        "learns the frames it shares with the one before as the crossfade from that segment's "
                        "compressed renders into the video)")
    p.add_argument("--key-interval", type=int, metavar="N",
                   help="a segmented run: every N-th segment is coded alone and the others are predicted from the "
                        "segment before (they take its codebooks and store its appearance MLPs as a change), so a "
                        f"seek decodes at most N segments; 1 codes every segment alone (default {DEFAULT_KEY_INTERVAL}; "
                        "1 with --paper)")
    add_force_argument(p)
    add_distributed_arguments(p)
    add_settings_arguments(p, CompressConfig, shortcuts=SHORTCUTS, section="compress_config",
                           defaults="the lengths shown are the official schedule's; one set alone changes only "
                                    "that stage of the run's schedule")


def run(args) -> int:
    from omg4 import distributed
    from omg4.app.outputs import check_outputs
    from omg4.atomic import write_text_atomic
    from omg4.codec.payload import CompactGrids, check_codec
    from omg4.compress.api import compress_to_file, read_baseline, trained_iterations
    from omg4.data.segments import is_segmented_run
    from omg4.errors import OMG4Error

    settings = settings_from_args(args, CompressConfig, section="compress_config", extra=COMMAND_KEYS)
    grid_text = settings.pop("grid_bits", None)
    precision = args.grid_bits or (compact_grids(grid_text) if grid_text else CompactGrids())
    if args.stop_after and args.grid_bits:
        raise OMG4Error("--grid-bits sets how an .omg4 file is coded; --stop-after writes a checkpoint instead")
    fill_device_arguments(args, settings)
    world, device = distributed.init(device_from_args(args))
    cfg = pipeline_config(args, settings, device)
    codec = cfg.choice("codec")
    check_codec(codec, precision)
    computes_scores = args.scores is None and any(s in cfg.stages for s in ("sample", "prune", "sample+prune"))
    scores_out = args.out.with_name(args.out.name + ".scores.npz") if computes_scores else None
    record = args.out.with_name(args.out.name + ".config.json")
    check_outputs({"--out": args.out, "--json": args.json, "the SD scores": scores_out, "the config record": record},
                  inputs=[args.data, args.model, args.scores, args.config], datasets=[args.data], force=args.force)
    if args.key_interval is not None and not is_segmented_run(args.model):
        raise OMG4Error("--key-interval applies to a segmented training run (a sequence of segments), not one model")
    if is_segmented_run(args.model):
        return _compress_segments(args, cfg, codec, precision, record, world)
    baseline, metadata = read_baseline(args.model, device)
    if "baseline_iterations" not in settings and args.baseline_iterations is None:
        recorded = trained_iterations(metadata)
        if recorded is not None:
            cfg = replace(cfg, baseline_iterations=recorded)
        elif world.main:
            print(f"{args.model} does not record how long it trained: assuming {cfg.baseline_iterations} iterations "
                  "(--baseline-iterations sets it)")
    scene = distributed.main_first(lambda: load_scene_from_args(args, background=cfg.background))
    report = compress_to_file(baseline, scene, cfg, args.out, codec=codec, stop_after=args.stop_after,
                              scores_path=args.scores, precision=precision, check_replicas=args.check_replicas,
                              progress=True)
    if not world.main:
        return 0
    report["world_size"] = world.size
    write_record(record, cfg, codec, precision)
    print(f"wrote {args.out} ({report['file_bytes'] / 2**20:.3f} MB, {report['num_gaussians']} Gaussians, "
          f"{report['wall_time_s']:.0f} s, mode {report['config']['mode']}) and its settings {record}")
    if args.json:
        write_text_atomic(args.json, json.dumps(report, indent=2))
    return 0


def pipeline_config(args, settings: dict, device) -> CompressConfig:
    """The run's :class:`CompressConfig`: the defaults, the file and ``--set`` (``settings``), then the flags; the
    device's default schedule (:func:`~omg4.compress.schedule.default_schedule`) unless one is named; stage
    lengths set one by one start from the schedule's. ``--paper`` sets every choice of
    :data:`omg4.compress.modes.CHOICES` that no flag of its own names, whatever a file or ``--set`` says of it."""
    from omg4.compress.schedule import default_schedule
    from omg4.settings import apply_settings

    flags = {name: getattr(args, name) for name in SHORTCUTS if name not in ("stages", "background", "backend",
                                                                            "device")}
    flags.update(stages=tuple(s.strip() for s in args.stages.split(",") if s.strip()) if args.stages else None,
                 background=(1.0, 1.0, 1.0) if args.white_background else None, backend=args.backend,
                 device=str(device))
    lengths = {k: v for k, v in settings.items() if k.startswith("lengths.")}
    given = {**{k: v for k, v in settings.items() if k not in lengths},
             **{k: v for k, v in flags.items() if v is not None}}
    if args.paper:  # the switch outranks a file's (a record's) choices; a flag naming one still sets it
        named = {k for k, v in flags.items() if v is not None} | {
            k[len("setting:"):] for k, v in vars(args).items() if k.startswith("setting:") and v is not None}
        given = {k: v for k, v in given.items() if k not in BY_SETTING or k in named}
    # the mode first: the choices no setting names take its values
    cfg = apply_settings(CompressConfig(schedule=default_schedule(device), paper=bool(given.pop("paper", False))),
                         given)
    if lengths:
        if cfg.lengths is None:
            cfg = replace(cfg, lengths=cfg.stage_lengths())
        cfg = apply_settings(cfg, lengths)
    return cfg


def write_record(path, cfg: CompressConfig, codec: str, precision) -> None:
    """``<out>.config.json``: every setting of the run, the codec and its grids (a valid ``--config``)."""
    from omg4.atomic import write_text_atomic
    from omg4.settings import config_dict

    write_text_atomic(path, json.dumps({"compress_config": config_dict(cfg.resolved()), "mode": cfg.mode(), "codec": codec,
                                        "grid_bits": ",".join(map(str, astuple(precision)))}, indent=2) + "\n")


def _compress_segments(args, cfg, codec, precision, record, world) -> int:
    """A segmented run: every segment compressed, one sequence file written."""
    from omg4.atomic import write_text_atomic
    from omg4.compress.api import compress_segments
    from omg4.errors import OMG4Error

    if args.stop_after or args.scores:
        raise OMG4Error("a segmented run compresses into one sequence file: --stop-after and --scores take one model")
    report = compress_segments(args.model, segment_scenes(args, cfg.background), cfg, args.out, codec=codec,
                               precision=precision, check_replicas=args.check_replicas,
                               teach=not args.independent_segments, progress=True, key_interval=args.key_interval)
    if not world.main:
        return 0
    write_record(record, cfg, codec, precision)
    print(f"wrote {args.out}: {len(report['segments'])} segments (mode {report['mode']}), "
          f"{report['file_bytes'] / 2**20:.3f} MB, "
          f"{report['bitrate_mbps']:.2f} Mbit/s over {report['duration_s']:.2f} s, {report['wall_time_s']:.0f} s")
    if args.json:
        write_text_atomic(args.json, json.dumps({**report, "world_size": world.size}, indent=2))
    return 0
