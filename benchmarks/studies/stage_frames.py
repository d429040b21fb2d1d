"""Which compression stage opens a test frame's dip: OMG4-M's PSNR on every test frame after each stage, beside the
baseline's, with what each time holds then.

For each demo run given (an ``omg4 demo --out FOLDER`` output: its ``scene``, ``baseline`` and SD scores), the
compression runs again as the demo runs it (preset M, the demo's stage lengths, batch 2, the run's seed) and, at the
end of every stage's fine-tuning (before the next stage's event) and at the end, records per test frame:

* ``psnr``: the pipeline's model on the test camera (before entropy coding), and the baseline's;
* ``alive``: the Gaussians the frame's time slice keeps after the temporal cull, and ``opacity_mass``: the sum of
  their opacities there (opacity × temporal marginal, rt4dgs §1.4; the appearance MLP's opacity once it has one);
* ``score_mass`` (once, the baseline's): Σ of the SD scores (static + |dynamic|) × marginal at the frame's time;
* ``draws`` (at the end): how many fine-tuning steps drew a view of the frame's time (the deficit sampler's or
  the uniform draw's).

``--frame-floor F`` sets pruning's frame floor (default: the code's; ``0``: the pruning of the paper's Eq. 2, as
these runs had before the floor); where the run's score file has no frame ranks (written before them) the pipeline
computes the scores again.

Usage: ``python benchmarks/studies/stage_frames.py DEMO_FOLDER [DEMO_FOLDER ...] [--frame-floor F] [--json PATH]``;
about 4 minutes a run on two cores. Record: ``benchmarks/results/stage_frames.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the omg4 command: idle threads must not spin

import numpy as np  # noqa: E402
import torch  # noqa: E402

from omg4.testing.records import save_record  # noqa: E402

RESULTS = Path(__file__).resolve().parents[1] / "results" / "stage_frames.json"
def frames(model, views, background) -> dict[str, list]:
    """Per test view: ``psnr`` of ``model``'s clamped render, ``alive`` (the Gaussians its time slice keeps after the
    temporal cull) and ``opacity_mass`` (the sum of their opacities there: opacity × temporal marginal)."""
    from omg4.metrics import psnr
    from omg4.render.view import render_view, view_image

    out = {"psnr": [], "alive": [], "opacity_mass": []}
    with torch.no_grad():
        for v in views:
            rendered, sl = render_view(model, v.camera, v.timestamp, background=background, backend="cpu")
            out["psnr"].append(float(psnr(rendered.image.clamp(0, 1), view_image(v))))
            out["alive"].append(int(sl.index.numel()))
            out["opacity_mass"].append(float(sl.opacities.sum()))
    return out


def run_one(folder: Path, frame_floor: float | None = None) -> dict:
    from omg4.app.demo import DEMO_LENGTHS
    from omg4.compress.pipeline import CompressConfig, CompressionPipeline
    from omg4.compress.score import SDScores
    from omg4.data import load_scene
    from omg4.gaussians.checkpoint import load_gaussians
    from omg4.gaussians.covariance import temporal_marginal

    seed = json.loads((folder / "baseline" / "config.json").read_text())["train_config"]["seed"]  # the demo's
    scene = load_scene(folder / "scene", progress=False)
    baseline = load_gaussians(folder / "baseline" / "model.safetensors")[0]
    views = sorted(scene.test_views, key=lambda v: v.timestamp)
    times = np.array([v.timestamp for v in views])
    background = torch.zeros(3)
    cfg = CompressConfig(preset="M", lengths=DEMO_LENGTHS, batch_size=2, seed=seed, baseline_iterations=1500,
                         frame_floor=frame_floor)
    scores = SDScores.load(folder / "scene_M.omg4.scores.npz", baseline.num_gaussians)
    if scores.frame_rank is None and cfg.choice("frame_floor") > 0:
        scores = None  # the pipeline computes them again, with the frame ranks
    values = {k: v.detach() for k, v in baseline.params.items()}
    _, _, var_t = baseline.config.schema.motion({k: v.double() for k, v in values.items()}, baseline.config)
    marginal = temporal_marginal(torch.as_tensor(times)[:, None] - values["t"].double().reshape(-1)[None], var_t)
    baseline_frames = frames(baseline, views, background)
    pipe = CompressionPipeline(baseline, scene, cfg, scores=scores, progress=False, log=lambda *_: None)
    scores = pipe.ensure_scores()
    weight = (scores.static + scores.dynamic.abs()).double()
    out = {"seed": seed, "frame_floor": cfg.choice("frame_floor"), "times": times.tolist(), "baseline": baseline_frames,
           "score_mass": (marginal * weight[None]).sum(1).tolist(), "stages": {}}
    apply_event, draws = pipe.apply_event, np.zeros(len(times), np.int64)
    frame_of = {t: i for i, t in enumerate(times.tolist())}

    def record(name: str) -> None:
        out["stages"][name] = {**frames(pipe.model, views, background), "gaussians": pipe.model.num_gaussians}

    def recording_event(name, round_index, iteration):
        if pipe.records:  # the stage before, at the end of its fine-tuning
            record(pipe.records[-1].stage)
        return apply_event(name, round_index, iteration)

    def counted(draw):
        def drawing(count, generator):
            batch = draw(count, generator)
            for i in batch.tolist():
                draws[frame_of[scene.train_views[i].timestamp]] += 1
            return batch
        return drawing

    pipe.apply_event = recording_event
    pipe.time_balance.draw = counted(pipe.time_balance.draw)  # the demo's default draw (deficit)
    pipe.run()
    record(pipe.records[-1].stage)
    out["draws"] = draws.tolist()
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("demos", nargs="+", type=Path, help="omg4 demo output folders")
    ap.add_argument("--frame-floor", type=float, default=None, help="pruning's frame floor (default: the code's)")
    ap.add_argument("--json", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    runs = {}
    for folder in args.demos:
        run = run_one(folder, args.frame_floor)
        runs[str(run["seed"])] = run
        final = list(run["stages"].values())[-1]["psnr"]
        delta = np.array(final) - np.array(run["baseline"]["psnr"])
        print(f"seed {run['seed']}: mean {delta.mean():+.3f} dB, worst {delta.min():+.3f} dB at frame "
              f"{int(delta.argmin())}", flush=True)
    command = shlex.join(["python", "benchmarks/studies/stage_frames.py", *(sys.argv[1:] if argv is None else argv)])
    save_record(args.json, {"command": command, "runs": runs})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
