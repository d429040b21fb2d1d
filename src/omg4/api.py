"""The public Python API: the few calls a script needs, each a thin layer over the package's modules.

Scene → baseline → ``.omg4`` file → model → images and metrics::

    scene = omg4.load_scene("data/coffee_martini", downscale=2)
    run = omg4.train_baseline(scene, omg4.train_config("official"), "runs/cm")
    omg4.compress_to_file(run.model, scene, omg4.CompressConfig(preset="M"), "cm_M.omg4")
    model = omg4.load_model("cm_M.omg4")
    image = omg4.render_frame(model, scene.test_views[0].camera, 0.5)
    metrics = omg4.evaluate_model(model, scene.test_views)

Documented in ``docs/api.md``; everything is importable as ``omg4.<name>`` (names that do not shadow the
package's modules: ``omg4.train`` and ``omg4.compress`` stay packages).
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from omg4.compress import api as compress_api
from omg4.compress.api import compress_to_file
from omg4.compress.pipeline import CompressConfig
from omg4.data import load_scene
from omg4.data.scene import Camera, Scene
from omg4.data.synthetic import SynthConfig, write_synthetic_scene
from omg4.evaluate import evaluate
from omg4.gaussians import Gaussians4D
from omg4.gaussians.checkpoint import load_gaussians
from omg4.models import load_model
from omg4.render.view import render_view
from omg4.train import make_config, segmented
from omg4.train.config import TrainConfig
from omg4.train.init import initial_points
from omg4.train.segmented import plan_capture, write_plan
from omg4.train.trainer import TrainResult, Trainer


def synthesize_scene(out: str | os.PathLike, *, cameras: int = 16, frames: int = 60, width: int = 128,
                     height: int = 96, seed: int = 0, force: bool = False, progress: bool = False) -> Path:
    """Write the built-in procedural dynamic scene (moving, rotating, colour-changing objects over a textured
    static set) as an N3DV folder at ``out`` (``omg4 synth``); returns the folder. Refuses a non-empty folder
    unless ``force``."""
    write_synthetic_scene(out, SynthConfig(seed=seed, num_cameras=cameras, num_frames=frames, width=width,
                                           height=height), force=force, progress=progress)
    return Path(out)


def train_config(preset: str = "official", **settings) -> TrainConfig:
    """A :class:`TrainConfig` from a preset (``"official"``: the Real-Time4DGS N3DV schedule; ``"cpu-small"``: a
    2-core machine and a small scene) and any of its fields; changing ``iterations`` scales the schedule
    (densification window, opacity resets, SH steps, position decay) unless those are given too."""
    return make_config(preset, **settings)


def train_baseline(scene: Scene, config: TrainConfig | None = None, run_dir: str | os.PathLike = "run", *,
                   resume: bool = False, progress: bool = False, log=None) -> TrainResult:
    """Train the baseline of ``config.backbone`` on ``scene`` into ``run_dir`` (checkpoints, ``config.json`` and
    the final ``model.safetensors``); ``resume`` continues the folder's last checkpoint. Initial points: the
    scene's ``points3d.ply``, else random points in the common view volume (``omg4 train --init`` has more)."""
    return Trainer(scene, config or TrainConfig(), run_dir, resume=resume, progress=progress, log=log).run()


def train_segments(data: str | os.PathLike, run_dir: str | os.PathLike, segment_frames: int,
                   config: TrainConfig | None = None, *, overlap: int | None = None, init: str = "auto",
                   teach: bool = True, **scene_options) -> list[dict]:
    """Train a long capture (``data``: an N3DV or Panoptic folder) as segments of ``segment_frames`` frames sharing
    ``overlap`` (default: :func:`omg4.train.segmented.default_overlap`), as ``omg4 train --segment-frames`` does:
    the plan (``segments.json``) and one run folder per segment in ``run_dir``; segments already trained are kept,
    so a second call resumes. ``teach``: a segment's shared frames show the crossfade from the segment before;
    ``scene_options``: :func:`load_scene`'s reader options (``downscale``, ``cameras``, ...). Returns one summary
    per segment."""
    cfg = config or TrainConfig()
    capture = load_scene(data, decode=False, progress=False, background=cfg.background, **scene_options)
    plan = plan_capture(capture, segment_frames, overlap)
    write_plan(Path(run_dir), plan)
    return segmented.train_segments(Path(run_dir), plan, cfg, _segment_scenes(data, cfg.background, scene_options),
                                    lambda scene: initial_points(scene, init, cfg), teach=teach)


def compress_segments(run_dir: str | os.PathLike, data: str | os.PathLike, out: str | os.PathLike,
                      config: CompressConfig | None = None, *, codec: str | None = None, teach: bool = True,
                      key_interval: int | None = None, progress: bool = False, **scene_options) -> dict:
    """Compress every segment of a run of :func:`train_segments` into one sequence file ``out`` (``omg4 compress``
    of a segmented run; every ``key_interval``-th segment coded alone, the others predicted from the one before;
    ``codec`` and ``key_interval`` left None follow the config's mode, :mod:`omg4.compress.modes`); the report gives
    each segment's and the file's bytes, duration and bitrate."""
    cfg = config or CompressConfig()
    return compress_api.compress_segments(run_dir, _segment_scenes(data, cfg.background, scene_options), cfg, out,
                                          codec=codec, teach=teach, key_interval=key_interval, progress=progress)


def _segment_scenes(data, background, options: dict):
    return lambda start, stop: load_scene(data, frames=range(start, stop), background=background, progress=False,
                                          **options)


def load_baseline(path: str | os.PathLike, device: torch.device | str = "cpu") -> Gaussians4D:
    """A trained baseline checkpoint (``model.safetensors``, any backbone) as a trainable model on ``device``."""
    return load_gaussians(path, device)[0]


def render_frame(model, camera: Camera, time: float, *, background: torch.Tensor | None = None, backend: str = "auto",
           device: torch.device | str = "cpu") -> torch.Tensor:
    """The image [H, W, 3] (float, unclamped) of ``model`` — a baseline, or a model from :func:`load_model` — seen
    by ``camera`` at ``time``."""
    with torch.no_grad():
        return render_view(model, camera, time, background=background, backend=backend, device=device)[0].image


def evaluate_model(model, views: list, *, lpips_nets: tuple[str, ...] = ("alex",), backend: str = "auto",
                   device: torch.device | str = "cpu", progress: bool = True) -> dict:
    """PSNR, SSIM, LPIPS (AlexNet by default; ``()`` for none), PSNR and SSIM over the moving pixels, FPS,
    Gaussian count and per-view rows of ``model`` on ``views`` (a scene's ``test_views``); see
    :func:`omg4.evaluate.evaluate` for every option."""
    return evaluate(model, views, lpips_nets=lpips_nets, backend=backend, device=device, progress=progress)


__all__ = ["synthesize_scene", "load_scene", "train_config", "train_baseline", "train_segments", "load_baseline",
           "compress_to_file", "compress_segments", "load_model", "render_frame", "evaluate_model", "Scene", "Camera",
           "TrainConfig", "CompressConfig", "TrainResult"]
