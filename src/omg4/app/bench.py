"""The paper's measurements on one scene: the baseline, the ablation rows and the size presets.

The rows are the baseline's backbone's (:attr:`omg4.gaussians.backbone.Backbone.paper_rows`): for
Real-Time4DGS (paper Tab. 4 and Tab. 1) GS+AC; GS+GP+AC; GS+GP+GM+AC (= OMG4-M); GS and GP applied at
once, then GM+AC; and the L / M / S / T presets; for FreeTimeGS (paper Tab. 3) attribute compression
only, and OMG4 at its L and S presets. Every row reports PSNR, SSIM,
LPIPS-alex, PSNR and SSIM over the moving pixels, FPS, #Gaussians, MB, bytes per Gaussian
and the compression wall time, and the same pipeline result written with the paper's coder
(its MB, PSNR and SSIM: the comparison point of the "compact" codec). With rate weights β > 0
(beyond the paper: entropy-constrained codebooks, :class:`omg4.compress.pipeline.CompressConfig`)
every row runs once per β ("OMG4-M, β=30"), so the figure shows each coder's rate–distortion
front. With several compact-codec grids (beyond the paper: :class:`omg4.codec.coders.CompactGrids`) each
row's model is also written at every further grid, a re-encoding of the same pipeline result ("OMG4-M,
grids 12/7/7"), one more curve per grid. The SD scores of the baseline and the dynamic-region masks are
computed once and shared by every row.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import torch

from omg4.app.report import Curves, equal_training_row, format_table, rate_distortion_plot
from omg4.atomic import write_text_atomic
from omg4.codec.payload import CompactGrids
from omg4.compress.modes import choice_value

def bench_table(rows: dict[str, dict]) -> str:
    """The paper's columns plus bytes per Gaussian, the same model's size and quality with the paper's coder,
    and compression time."""
    base = format_table(rows).splitlines()
    head = base[0] + " B/Gaussian | MB, paper coder | PSNR, paper coder | SSIM, paper coder | compress s |"
    sep = base[1] + "---|---|---|---|---|"
    lines = [head, sep]
    for line, r in zip(base[2:], rows.values()):
        cells = [f"{r[key]:{fmt}}" if r.get(key) else "-" for key, fmt in
                 (("bytes_per_gaussian", ".1f"), ("paper_codec_mb", ".3f"), ("paper_codec_psnr", ".2f"),
                  ("paper_codec_ssim", ".4f"), ("compress_s", ".0f"))]
        lines.append(f"{line} " + " | ".join(cells) + " |")
    return "\n".join(lines)


def row_label(name: str, rate_weight: float, grids: CompactGrids = CompactGrids()) -> str:
    """A bench row's name at rate weight β and compact grids: ``name``, ", β=30" unless β = 0, ", grids 12/7/7"
    unless the default grids."""
    return (name + ("" if rate_weight == 0 else f", β={rate_weight:g}")
            + ("" if grids == CompactGrids() else f", grids {grids.label}"))


def row_file(out: Path, name: str, rate_weight: float, grids: CompactGrids = CompactGrids()) -> Path:
    """The ``.omg4`` file of a bench row at rate weight β and compact grids in ``out`` (its paper-coder copy adds
    ``_paper_codec``)."""
    stem = name.replace(" ", "_").replace("(", "").replace(")", "").replace("+", "-")
    beta = "" if rate_weight == 0 else f"_beta{rate_weight:g}".replace("+", "")
    grid = "" if grids == CompactGrids() else "_grids" + grids.label.replace("/", "-")
    return out / (stem + beta + grid + ".omg4")


def run_bench(scene, baseline, baseline_path: Path, out: Path, *, schedule: str = "cpu", batch_size: int = 4,
              baseline_iterations: int = 30000, rows: list[str] | None = None, paper: bool = False,
              codec: str | None = None,
              backend: str = "auto", device: torch.device | str = "cpu", rate_weights: tuple[float, ...] = (0.0,),
              grids: tuple[CompactGrids, ...] = (CompactGrids(),), control: tuple[Path, int | None] | None = None,
              log=print) -> dict:
    """Compress ``baseline`` once per row of its backbone (``Backbone.paper_rows``) and rate weight, write each result
    at every compact grid of ``grids`` (the first by the pipeline run, the others re-encoded from its paper-coder
    copy), and evaluate everything on the test views, computing on ``device``. ``baseline_path`` must be the checkpoint
    ``baseline`` was loaded from: its row is evaluated as a render-only model loaded from that file, as the compressed
    rows are from theirs. ``paper``: every row compressed the paper's way (:mod:`omg4.compress.modes`; ``codec``
    None: the mode's coder). ``control``: the checkpoint of the equal-training control (a baseline trained for as many
    steps as the baseline and the full pipeline's fine-tuning together) and the steps it records, evaluated as the
    baseline is, its row recording how many steps equal training takes. In a distributed job every rank compresses
    and evaluates its share of the views (:mod:`omg4.distributed`) and rank 0 alone writes and prints."""
    from omg4 import distributed
    from omg4.codec.payload import check_codec, decode_payload, encode_payload
    from omg4.compress.api import compress_to_file
    from omg4.compress.pipeline import FULL_STAGES, CompressConfig
    from omg4.compress.score import compute_sd_scores
    from omg4.errors import OMG4Error
    from omg4.evaluate import dynamic_masks, evaluate
    from omg4.models import load_model
    from omg4.models.compact import load_omg4

    codec = CompressConfig(paper=paper, codec=codec).choice("codec")
    table_rows = baseline.config.schema.paper_rows
    names = rows or list(table_rows)
    for g in grids:
        check_codec(codec, g)
    runs = [(n, b) for n in names for b in rate_weights]
    outputs = [(n, b, g) for n, b in runs for g in grids]
    if (len({row_label(*o) for o in outputs}) < len(outputs)
            or len({row_file(out, *o) for o in outputs}) < len(outputs)):
        raise OMG4Error(f"bench rows {names} at rate weights {list(rate_weights)} and grids "
                        f"{[g.label for g in grids]} would share names or files: give distinct rows, grids and rate "
                        "weights that differ in their first 6 digits")
    main = distributed.world().main
    log = log if main else (lambda *_: None)
    out.mkdir(parents=True, exist_ok=True)
    baseline = baseline.to(device)
    scores_path = out / "sd_scores.npz"
    if not distributed.gather_objects(_reusable(scores_path, baseline.num_gaussians), "looking for the SD scores")[0]:
        scores = compute_sd_scores(baseline, scene.train_views, backend=backend, device=device, progress=main)
        if main:
            scores.save(scores_path)
        distributed.barrier("writing the SD scores")
    results: dict[str, dict] = {}
    masks = dynamic_masks(scene.test_views)  # one dynamic region for every row
    log("evaluating the baseline")
    base_name = baseline.config.schema.title
    # rendered as the compressed rows are: a render-only model loaded from its file (visibility windows,
    # conditioning at load), so the FPS columns compare like with like
    results[base_name] = evaluate(load_model(baseline_path, device), scene.test_views,
                                  storage_bytes=baseline_path.stat().st_size, backend=backend, device=device,
                                  masks=masks)
    if control is not None:
        control_path, control_iterations = control
        equal = baseline_iterations + CompressConfig(schedule=schedule).fine_tuning_iterations()
        log(f"evaluating the equal-training control ({control_iterations or 'unknown'} steps; the baseline's and the "
            f"full pipeline's fine-tuning together: {equal})")
        if control_iterations != equal:
            log(f"warning: the control was trained for {control_iterations or 'an unknown number of'} steps, not "
                f"{equal}: its row is a differently trained baseline, not the equal-training control")
        results[equal_training_row(base_name)] = {
            **evaluate(load_model(control_path, device), scene.test_views, storage_bytes=control_path.stat().st_size,
                       backend=backend, device=device, masks=masks),
            "iterations": control_iterations, "equal_training_iterations": equal}
    for name, beta in runs:
        preset, stages = table_rows[name]
        path = row_file(out, name, beta, grids[0])
        log(f"row {row_label(name, beta)}: preset {preset}, stages {','.join(stages)}")
        cfg = CompressConfig(paper=paper, preset=preset, stages=stages, schedule=schedule, batch_size=batch_size,
                             baseline_iterations=baseline_iterations, backend=backend, device=str(device),
                             rate_weight=beta)
        paper_copy = path.with_name(path.stem + "_paper_codec.omg4")
        report = compress_to_file(baseline, scene, cfg, path, codec=codec, scores_path=scores_path,
                                  paper_copy=paper_copy, precision=grids[0], log=log, progress=True)
        paper_r = None if codec == choice_value("codec", paper=True) else evaluate(
            load_omg4(paper_copy, device), scene.test_views, lpips_nets=(), backend=backend, device=device,
            masks=masks, fps_views=1, progress=False)
        payload = decode_payload(paper_copy) if len(grids) > 1 else None  # the pipeline's values, for re-encoding
        for g in grids:
            if g != grids[0]:
                path = row_file(out, name, beta, g)
                if main:
                    encode_payload(payload, path, codec=codec, precision=g)
                distributed.barrier("writing a bench file")
            r = evaluate(load_omg4(path, device), scene.test_views, storage_bytes=path.stat().st_size,
                         backend=backend, device=device, masks=masks)
            paper_coded = paper_r or r
            r.update(compress_s=report["wall_time_s"], bytes_per_gaussian=path.stat().st_size / r["num_gaussians"],
                     paper_codec_mb=report["paper_file_bytes"] / 2**20, paper_codec_psnr=paper_coded["psnr"],
                     paper_codec_ssim=paper_coded["ssim"], rate_weight=beta, grids=asdict(g), preset=preset,
                     full_pipeline=stages == FULL_STAGES, stages=report["stages"], file=str(path),
                     mode=report["config"]["mode"])
            results[row_label(name, beta, g)] = r
            if main:
                write_text_atomic(out / "bench.json", json.dumps(_strip(results), indent=2))
    if not main:
        return results
    base = results[base_name]
    base["bytes_per_gaussian"] = baseline_path.stat().st_size / base["num_gaussians"]
    table = bench_table(results)
    write_text_atomic(out / "bench.md", table + "\n")
    write_text_atomic(out / "bench.json", json.dumps(_strip(results), indent=2))
    points, curves = rate_distortion_curves(results, codec)
    rate_distortion_plot(out / "rate_distortion.png", points, f"{scene.name}: rate-distortion", curves)
    print(table)
    return results


def rate_distortion_curves(results: dict[str, dict], codec: str) -> tuple[dict[str, dict], Curves]:
    """The bench figure's content: stand-alone rows (the baseline, the ablations) and one curve per coder, rate
    weight and grid through the full-pipeline rows, their points labelled by preset — ``codec``'s files at every β
    and grid, and the paper coder's copies of the β = 0 runs (the comparison point)."""
    points = {name: r for name, r in results.items() if not r.get("full_pipeline")}
    curves: Curves = {}
    for r in results.values():
        if not r.get("full_pipeline"):
            continue
        beta, grids = r["rate_weight"], CompactGrids(**{"exact": 0, **r.get("grids", {})})  # saved before exact: 0
        curves.setdefault(row_label(f"{codec} coder", beta, grids), {})[r["preset"]] = (r["storage_mb"], r["psnr"])
        if not beta and codec != choice_value("codec", paper=True):
            curves.setdefault("paper coder", {})[r["preset"]] = (r["paper_codec_mb"], r["paper_codec_psnr"])
    return points, curves


def _strip(results: dict[str, dict]) -> dict:
    return {k: {kk: vv for kk, vv in v.items() if kk != "per_view"} for k, v in results.items()}


def _reusable(scores_path: Path, num_gaussians: int) -> bool:
    """Whether an earlier run's SD scores can serve again: they exist and hold the frame ranks pruning's frame floor
    needs (an older omg4 wrote none: they are computed again). A damaged file is left for the compression to refuse."""
    from omg4.compress.score import SDScores
    from omg4.errors import CorruptFileError

    if not scores_path.exists():
        return False
    try:
        return SDScores.load(scores_path, num_gaussians).frame_rank is not None
    except CorruptFileError:
        return True


__all__ = ["bench_table", "rate_distortion_curves", "row_file", "row_label", "run_bench"]

