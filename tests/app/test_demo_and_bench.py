"""The main job and the benchmark run end to end at tiny sizes and write what they promise."""

import json
import runpy
from dataclasses import asdict, replace
from pathlib import Path

import av
import numpy as np
import torch
import pytest
from PIL import Image

from omg4.app.bench import rate_distortion_curves, row_file, run_bench
from omg4.app.demo import CONTROL_ROW, QUICK, SMOKE_CHECK_NOTE, check_demo_folder, run_demo
from omg4.codec.container import read_container
from omg4.codec.payload import CompactGrids
from omg4.train import Trainer, make_config

COARSE = CompactGrids(positions=12, rotations=7, times=7)


def _recording_evaluate(monkeypatch) -> list:
    """Patch ``omg4.evaluate.evaluate`` to record the type of every model it evaluates."""
    import omg4.evaluate

    kinds, evaluate = [], omg4.evaluate.evaluate

    def recording(model, *args, **kwargs):
        kinds.append(type(model))
        return evaluate(model, *args, **kwargs)

    monkeypatch.setattr(omg4.evaluate, "evaluate", recording)
    return kinds


def test_quick_demo_writes_results_plot_video_and_file(tmp_path, monkeypatch, capsys):
    from omg4.models.windowed import WindowedModel

    import omg4.app.demo

    out = tmp_path / "demo"
    evaluated, video = _recording_evaluate(monkeypatch), []
    write_video = omg4.app.demo.side_by_side_video

    def recording_video(path, views, models, *args, **kwargs):
        video.extend(models)
        return write_video(path, views, models, *args, **kwargs)

    monkeypatch.setattr(omg4.app.demo, "side_by_side_video", recording_video)
    results = run_demo(out, replace(QUICK, equal_training_control=True), log=lambda *_: None)
    # every model renders as it would from its file (FPS like with like): render-only, windowed
    assert len(evaluated) == 4 and all(issubclass(kind, WindowedModel) for kind in evaluated)
    assert len(video) == 2 and all(isinstance(model, WindowedModel) for model in video)
    saved = json.loads((out / "results.json").read_text())
    methods = saved["methods"]
    assert set(methods) == {"Real-Time4DGS (baseline)", "OMG4-M", CONTROL_ROW}
    # the control trains as long as the baseline (60) and the tiny schedule's fine-tuning together:
    # sampling 4, pruning 4, two merge rounds of 4, appearance 8, SVQ 4 + 4
    control = saved["equal_training_control"]
    assert control["iterations"] == 60 + 32
    # timings are the parts' seconds, which add up to the run; the speeds stand apart
    assert set(saved["timings"]) == {"synth_s", "train_s", "compress_s", "control_s", "eval_s", "outputs_s"}
    assert saved["speeds"]["train_steps_per_second"] > 0
    assert set(saved["speeds"]["compress_steps_per_second"]) == {r["stage"] for r in saved["compression"]["stages"]}
    # the seeds study reads the demo's results as they are
    study = runpy.run_path(str(Path(__file__).parents[2] / "benchmarks" / "studies" / "demo_seeds.py"),
                           run_name="demo_seeds")
    row = study["row_of"](saved)
    assert row["wall_s"] == sum(saved["timings"].values()) and row["delta_psnr"] == (
        methods["OMG4-M"]["psnr"] - methods["Real-Time4DGS (baseline)"]["psnr"])
    assert json.loads((out / "control" / "config.json").read_text())["train_config"]["iterations"] == 92
    assert control["delta_psnr"] == methods["OMG4-M"]["psnr"] - methods[CONTROL_ROW]["psnr"]
    frames = control["per_frame_difference"]["psnr"]
    assert frames["min"] <= control["delta_psnr"] <= frames["max"] and frames["min"] < frames["max"]
    check_demo_folder(out)  # everything it wrote is an output a re-run may replace
    for row in methods.values():
        assert {"psnr", "ssim", "lpips_alex", "psnr_dynamic", "ssim_dynamic", "fps", "num_gaussians",
                "storage_mb"} <= set(row)
        assert np.isfinite(row["psnr"]) and np.isfinite(row["psnr_dynamic"]) and row["fps"] > 0
        assert row["fps_detail"]["timed_with"] == "models alternating frame by frame"
        assert row["fps"] == row["fps_detail"]["fps"]
        assert row["fps_detail"]["frames"] == len(results["per_view"]["OMG4-M"])  # every test view, one pass
        assert 0 < row["dynamic_fraction"] < 1
    omg4_file = out / "scene_M.omg4"
    assert methods["OMG4-M"]["storage_mb"] == omg4_file.stat().st_size / 2**20
    paper_file = out / "scene_M_paper_codec.omg4"
    assert saved["paper_codec_mb"] == paper_file.stat().st_size / 2**20
    from omg4.models.compact import load_omg4

    a, b = load_omg4(omg4_file), load_omg4(paper_file)  # one model, two coders
    assert a.num_gaussians == b.num_gaussians
    # the compact coder puts positions on a 15-bit grid over the box (then fp16): each near a paper-file position
    xa, xb = a.values["xyz"].double(), b.values["xyz"].double()
    step = float((xb.max(0).values - xb.min(0).values).max()) / (2 ** 15 - 1)
    nearest = torch.cdist(xa, xb).min(dim=1).values
    assert (nearest <= step + 2.0 ** -10 * xa.abs().max(dim=1).values).all()
    # the quality gate of the compact coder on a tiny pipeline run: smaller, same images within 0.05 dB / 0.002 SSIM
    paper = saved["paper_codec"]
    assert omg4_file.stat().st_size < paper_file.stat().st_size
    assert abs(methods["OMG4-M"]["psnr"] - paper["psnr"]) <= 0.05
    assert abs(methods["OMG4-M"]["ssim"] - paper["ssim"]) <= 0.002
    assert "PSNR dyn" in saved["table"]
    assert methods["OMG4-M"]["num_gaussians"] < methods["Real-Time4DGS (baseline)"]["num_gaussians"]
    assert Image.open(out / "rate_distortion.png").size[0] > 100
    with av.open(str(out / "side_by_side.mp4")) as c:
        frames = list(c.decode(video=0))
    assert len(frames) == len(results["per_view"]["OMG4-M"])  # one frame per test view
    assert frames[0].width == 3 * QUICK.width  # ground truth | baseline | OMG4
    assert "| OMG4-M |" in saved["table"]
    # a smoke check says so, last, under its numbers, and records it
    assert saved["smoke_check"] is True and capsys.readouterr().out.rstrip().endswith(SMOKE_CHECK_NOTE)


def test_bench_rows_on_a_tiny_scene(tiny_scene, tmp_path, monkeypatch):
    from omg4.models.windowed import WindowedModel

    cfg = make_config("cpu-small", iterations=20, batch_size=1, checkpoint_interval=0, densify_until=0,
                      backend="cpu")
    base = Trainer(tiny_scene, cfg, tmp_path / "run", progress=False, log=lambda *_: None).run()
    # the equal-training control: 20 steps and the tiny schedule's 32 fine-tuning steps (4 + 4 + 2 × 4 + 8 + 4 + 4)
    control = Trainer(tiny_scene, replace(cfg, iterations=52), tmp_path / "control", progress=False,
                      log=lambda *_: None).run()
    evaluated, lines = _recording_evaluate(monkeypatch), []
    results = run_bench(tiny_scene, base.model, base.model_path, tmp_path / "bench", schedule="tiny", batch_size=1,
                        baseline_iterations=20, rows=["GS+AC", "(GS+GP)+GM+AC", "OMG4-T"], backend="cpu",
                        rate_weights=(0.0, 30.0), grids=(COARSE, CompactGrids()), control=(control.model_path, 52),
                        log=lines.append)
    assert evaluated and all(issubclass(kind, WindowedModel) for kind in evaluated)  # the baseline too
    assert results["Real-Time4DGS, equal training"]["equal_training_iterations"] == 52
    assert results["Real-Time4DGS, equal training"]["num_gaussians"] == control.model.num_gaussians
    assert not any(line.startswith("warning") for line in lines)
    # the first grid is the pipeline run's file (compress_to_file), the default one re-encoded from its paper copy
    assert list(results) == ["Real-Time4DGS", "Real-Time4DGS, equal training", "GS+AC, grids 12/7/7", "GS+AC", "GS+AC, β=30, grids 12/7/7", "GS+AC, β=30",
                             "(GS+GP)+GM+AC, grids 12/7/7", "(GS+GP)+GM+AC", "(GS+GP)+GM+AC, β=30, grids 12/7/7",
                             "(GS+GP)+GM+AC, β=30", "OMG4-T, grids 12/7/7", "OMG4-T", "OMG4-T, β=30, grids 12/7/7",
                             "OMG4-T, β=30"]
    # every row compressed omg4's way, not only the first (each row's config is built from run_bench's own `paper`);
    # the rate weight β = 30 is the one choice set away from the defaults
    assert {name: r["mode"] for name, r in results.items() if "mode" in r} == {
        name: "mixed (rate_weight=30.0)" if "β=30" in name else "omg4"
        for name in results if name.startswith(("GS", "(GS", "OMG4"))}
    n = base.model.num_gaussians
    assert results["GS+AC"]["num_gaussians"] == round(0.2 * n)  # sampling only
    assert results["(GS+GP)+GM+AC"]["num_gaussians"] < results["GS+AC"]["num_gaussians"]
    assert results["OMG4-T"]["num_gaussians"] < results["GS+AC"]["num_gaussians"]
    files = {Path(r["file"]).name for name, r in results.items() if "file" in r}
    assert len(files) == 12 and {"OMG4-T_beta30.omg4", "OMG4-T_beta30_grids12-7-7.omg4"} <= files
    for row in ("GS+AC", "OMG4-T, β=30"):  # the same pipeline result on both grids
        fine, coarse = results[row], results[row + ", grids 12/7/7"]
        assert coarse["num_gaussians"] == fine["num_gaussians"] and coarse["storage_mb"] < fine["storage_mb"]
        assert coarse["paper_codec_mb"] == fine["paper_codec_mb"] and coarse["grids"] == asdict(COARSE)
        for r, bits in ((coarse, 7), (fine, 9)):
            assert read_container(r["file"])[0]["encodings"]["quat.rotation"] == f"smallest-three-{bits}"
    table = (tmp_path / "bench" / "bench.md").read_text()
    assert "B/Gaussian" in table and "| GS+AC, β=30 |" in table and "PSNR, paper coder" in table
    saved = json.loads((tmp_path / "bench" / "bench.json").read_text())
    for row in ("GS+AC", "OMG4-T, β=30"):  # both coders' sizes, the paper's from its own file
        first = Path(saved[row + ", grids 12/7/7"]["file"])  # the pipeline run's file names its paper copy
        paper_file = first.with_name(first.stem + "_paper_codec.omg4")
        assert saved[row]["paper_codec_mb"] == paper_file.stat().st_size / 2**20 > saved[row]["storage_mb"]
        # and its images: the paper coder's copy evaluated on the same views. The coders' gate (0.05 dB, 0.002 SSIM)
        # is the demo's, tested above; on these 120 Gaussians of a 20-step model the grids have moved PSNR by up to
        # 0.09 dB and SSIM by 0.0021 from run to run, while another row's file is 0.9 dB and 0.03 or more away
        assert abs(saved[row]["paper_codec_psnr"] - saved[row]["psnr"]) <= 0.25
        assert abs(saved[row]["paper_codec_ssim"] - saved[row]["ssim"]) <= 0.005
    assert saved["OMG4-T, β=30"]["rate_weight"] == 30.0 and saved["OMG4-T"]["rate_weight"] == 0.0
    assert saved["GS+AC"]["bytes_per_gaussian"] > 0 and (tmp_path / "bench" / "rate_distortion.png").exists()
    points, curves = rate_distortion_curves(results, "compact")
    assert set(points) == {name for name in results if not name.startswith("OMG4-T")}

    def point(row):
        return {"T": (results[row]["storage_mb"], results[row]["psnr"])}

    assert curves == {"compact coder": point("OMG4-T"), "compact coder, grids 12/7/7": point("OMG4-T, grids 12/7/7"),
                      "compact coder, β=30": point("OMG4-T, β=30"),
                      "compact coder, β=30, grids 12/7/7": point("OMG4-T, β=30, grids 12/7/7"),
                      "paper coder": {"T": (results["OMG4-T"]["paper_codec_mb"], results["OMG4-T"]["paper_codec_psnr"])}}


def test_bench_refuses_rate_weights_that_would_share_rows_or_files(tiny_scene, tmp_path):
    from types import SimpleNamespace

    from omg4.errors import OMG4Error

    from omg4.gaussians.backbone import RT4DGS

    baseline = SimpleNamespace(config=SimpleNamespace(backbone="rt4dgs", schema=RT4DGS))  # refused before use
    for rows, weights in ((["OMG4-T"], (0.1234561, 0.1234562)), (["OMG4-T", "OMG4-T"], (0.0,))):
        with pytest.raises(OMG4Error, match="share names or files"):
            run_bench(tiny_scene, baseline, tmp_path / "m.safetensors", tmp_path / "bench", rows=rows,
                      rate_weights=weights, log=lambda *_: None)
    with pytest.raises(OMG4Error, match="share names or files"):  # one grid given twice
        run_bench(tiny_scene, baseline, tmp_path / "m.safetensors", tmp_path / "bench", rows=["OMG4-T"],
                  grids=(COARSE, CompactGrids(12, 7, 7)), log=lambda *_: None)
    with pytest.raises(OMG4Error, match="compact codec only"):  # grids with the paper coder
        run_bench(tiny_scene, baseline, tmp_path / "m.safetensors", tmp_path / "bench", rows=["OMG4-T"],
                  codec="paper", grids=(COARSE,), log=lambda *_: None)
    # exponents keep their sign in file names: 1e6 and 1e-6 are two files
    assert row_file(tmp_path, "OMG4-T", 1e6) != row_file(tmp_path, "OMG4-T", 1e-6)
    assert not (tmp_path / "bench").exists()  # refused before anything was written


def test_bench_reuses_scores_only_with_the_frame_ranks_pruning_needs(tmp_path):
    """An earlier bench's scores serve again when they hold frame ranks; an older omg4's (none) are computed again; a
    damaged file is left to the compression's one-line refusal."""
    from omg4.app.bench import _reusable
    from omg4.compress.score import SDScores

    path = tmp_path / "sd_scores.npz"
    assert not _reusable(path, 4)
    SDScores(torch.rand(4, dtype=torch.float64), torch.randn(4, dtype=torch.float64)).save(path)
    assert not _reusable(path, 4)
    SDScores(torch.rand(4, dtype=torch.float64), torch.randn(4, dtype=torch.float64), torch.arange(4)).save(path)
    assert _reusable(path, 4)
    path.write_bytes(b"not a score file")
    assert _reusable(path, 4)
