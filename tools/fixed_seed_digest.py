"""Digests of fixed-seed runs of both backbones: a bar of equality between two versions of omg4.

For Real-Time4DGS and FreeTimeGS: trains a baseline on a tiny synthetic scene (5 cameras × 6 frames,
64×48; 120 iterations with densification or relocation), compresses it with every OMG4 stage (a few
iterations each), decodes the file and renders the test view, then prints SHA-256 digests of the trained
parameters, of the decoded per-Gaussian values, codebooks and MLP weights, and of the rendered image; and of the
written scene's files (its videos must come out the same in every run: ``write_video(reproducible=True)``).
With ``--against CHECKOUT`` the same runs are made with that checkout's code too (its ``src`` first on
``PYTHONPATH``) and the record says which digests are equal — refactorings that must not change behaviour keep
every digest — and, where they differ, by how much the trained parameters (after the run, and after its first
step) and the rendered view do. The file's
bytes are listed too, but its header may legitimately change (new metadata fields).

Usage: ``python tools/fixed_seed_digest.py [--against CHECKOUT [--against-kernels reference]] [--work DIR]
[--print]``; about 40 s a version. Recorded in ``benchmarks/results/fixed_seed_digest.json`` (``--print``: printed
only).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import torch


def digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = a.detach().cpu().numpy() if torch.is_tensor(a) else np.asarray(a)
        h.update(str(a.dtype).encode() + str(a.shape).encode() + np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def main() -> None:
    from omg4.compress.api import compress_to_file
    from omg4.compress.pipeline import CompressConfig
    from omg4.compress.schedule import StageLengths
    from omg4.data import load_scene
    from omg4.data.synthetic import SynthConfig, write_synthetic_scene
    from omg4.train import Trainer, make_config

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("runs/fixed_seed_digest"))
    ap.add_argument("--against", type=Path, help="another checkout whose code makes the same runs for comparison")
    ap.add_argument("--against-kernels", choices=("fused", "reference"), default=None,
                    help="the --against side's per-Gaussian kernels (OMG4_KERNELS; e.g. this checkout against itself "
                         "on the pure-torch reference)")
    ap.add_argument("--print", action="store_true", help="print the digests as JSON and record nothing")
    args = ap.parse_args()
    scene_dir = args.work / "scene"
    write_synthetic_scene(scene_dir, SynthConfig(num_cameras=5, num_frames=6, width=64, height=48, num_points=600),
                          progress=False, force=True)
    scene = load_scene(scene_dir, progress=False)
    scene_files = digest(*(np.frombuffer(f.read_bytes(), np.uint8) for f in sorted(scene_dir.iterdir())))
    results = {}
    for backbone in ("rt4dgs", "freetimegs"):
        extra = {"max_gaussians": 1500} if backbone == "freetimegs" else {}
        cfg = make_config("cpu-small", iterations=120, batch_size=2, checkpoint_interval=0, densify_from=20,
                          densify_interval=40, densify_until=100, backend="cpu", backbone=backbone, **extra)
        trained = Trainer(scene, cfg, args.work / f"run_{backbone}", progress=False, log=lambda *_: None).run()
        one_step = Trainer(scene, make_config("cpu-small", iterations=1, batch_size=2, checkpoint_interval=0,
                                              backend="cpu", backbone=backbone, **extra),
                           args.work / f"run1_{backbone}", progress=False, log=lambda *_: None).run()
        lengths = StageLengths(sample=3, prune=3, merge=3, appearance=6, svq3d=3, svq4d=3)
        path = args.work / f"model_{backbone}.omg4"
        compress_to_file(trained.model, scene, CompressConfig(lengths=lengths, batch_size=2, backend="cpu"), path,
                         progress=False, log=lambda *_: None)
        results[backbone] = {"scene_files": scene_files,
                             **digests(trained, one_step, path, scene, args.work / f"arrays_{backbone}.npz")}
    if args.print:
        print(json.dumps(results))
        return
    record = {"command": "python tools/fixed_seed_digest.py" + (f" --against {args.against}" if args.against else "")
              + (f" --against-kernels {args.against_kernels}" if args.against_kernels else ""), "digests": results}
    if args.against:
        import os
        import subprocess

        env = {**os.environ, "PYTHONPATH": str(args.against.resolve() / "src"),
               **({"OMG4_KERNELS": args.against_kernels} if args.against_kernels else {})}
        out = subprocess.run([sys.executable, __file__, "--print", "--work", str(args.work / "against")], env=env,
                             check=True, capture_output=True, text=True).stdout
        other = json.loads(out.strip().splitlines()[-1])
        commit = subprocess.run(["git", "rev-parse", "--short=10", "HEAD"], cwd=args.against, capture_output=True,
                                text=True).stdout.strip()
        record.update(against_commit=commit, against=other,
                      equal={b: {k: results[b][k] == other.get(b, {}).get(k) for k in results[b]} for b in results},
                      differences={b: differences(args.work / f"arrays_{b}.npz",
                                                  args.work / "against" / f"arrays_{b}.npz") for b in results})
    from omg4.testing.records import save_record

    save_record(Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "fixed_seed_digest.json", record)
    print(json.dumps(record.get("equal", results), indent=2))


def differences(mine: Path, other: Path) -> dict:
    """How far apart two runs' arrays lie: the largest difference of the trained parameters (after the whole run,
    and after its first step from the same initialization) relative to each parameter's largest magnitude, and of
    the rendered test view's pixels (absolute, in [0, 1])."""
    a, b = np.load(mine), np.load(other)

    def largest_relative(keys) -> float:
        return max((float(np.abs(a[k] - b[k]).max() / max(np.abs(b[k]).max(), 1e-30)) for k in keys if a[k].size),
                   default=0.0)

    params = [k for k in a.files if k != "image" and k in b.files and a[k].shape == b[k].shape]
    trained = [k for k in params if not k.startswith(ONE_STEP)]
    same_shape = a["image"].shape == b["image"].shape
    return {"trained_params_max_relative": largest_relative(trained), "compared_params": len(trained),
            "one_step_params_max_relative": largest_relative([k for k in params if k.startswith(ONE_STEP)]),
            "rendered_image_max_abs": float(np.abs(a["image"] - b["image"]).max()) if same_shape else None}


ONE_STEP = "one_step/"
"""Prefix of the parameters after the first training step in a run's arrays."""


def digests(trained, one_step, path: Path, scene, arrays: Path) -> dict:
    """The digests of one backbone's run: trained parameters, decoded values, rendered test view, file; the trained
    parameters, those after ``one_step`` (a run of one step) and the rendered view are kept at ``arrays`` (.npz)
    for :func:`differences`."""
    from omg4 import load_model  # the public name: the same in every version compared
    from omg4.codec.payload import decode_payload
    from omg4.render.view import render_view

    payload = decode_payload(path)
    decoded = load_model(path)
    view = scene.test_views[0]
    image = render_view(decoded, view.camera, view.timestamp, backend="cpu")[0].image
    params = trained.model.params
    np.savez(arrays, image=image.numpy(), **{k: v.detach().numpy() for k, v in params.items()},
             **{ONE_STEP + k: v.detach().numpy() for k, v in one_step.model.params.items()})
    result = {
        "trained_gaussians": trained.model.num_gaussians,
        "trained_params": digest(*(params[k] for k in sorted(params))),
        "compressed_gaussians": decoded.num_gaussians,
        "payload_values": digest(payload.xyz, payload.t,
                                 *(a for name in sorted(payload.attributes)
                                   for a in (*payload.attributes[name].codebooks, *payload.attributes[name].indices)),
                                 *(payload.mlp[k] for k in sorted(payload.mlp))),
        "rendered_image": digest(image),
        "file_bytes": path.stat().st_size,
        "file": hashlib.sha256(path.read_bytes()).hexdigest(),
    }
    return result


if __name__ == "__main__":
    main()
