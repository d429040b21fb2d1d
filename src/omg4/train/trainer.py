"""The baseline training loop of any backbone (rt4dgs §3; FreeTimeGS with ``TrainConfig.backbone``).

Each iteration renders a batch of random (camera, frame) views, back-propagates
``loss_v / B`` per view, and takes one Adam step; the SH degree schedule happens at fixed
iterations, and the backbone's density control (:mod:`omg4.train.strategies`: Real-Time4DGS's
densification, pruning and opacity resets; FreeTimeGS's relocation and regularization) adds,
removes or moves Gaussians through its hooks. Everything random is drawn from generators
seeded by ``(seed, iteration)``, so a run resumed from a checkpoint continues exactly as
an uninterrupted run of the same seed. The model, optimizer state, statistics and images live
on ``TrainConfig.device``; the generators are CPU ones whose draws are moved there.
"""

from __future__ import annotations

import contextlib
import json
import logging
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
import torch
from tqdm.auto import tqdm

from omg4 import distributed
from omg4.atomic import write_text_atomic
from omg4.data import random_initial_points
from omg4.data.scene import PointCloud, Scene, View
from omg4.data.segments import HOLD_LASTING_REMOVED
from omg4.device import resolve_device
from omg4.errors import OMG4Error
from omg4.gaussians import GaussianConfig, Gaussians4D
from omg4.gaussians.backbone import backbone_named
from omg4.gaussians.checkpoint import save_gaussians
from omg4.kernels import using_kernels
from omg4.metrics import psnr
from omg4.optimize.parameters import baseline_lrs, make_adam, set_position_lr, step_optimizers
from omg4.optimize.step import backward_batch, step_generator
from omg4.render.api import resolve_backend
from omg4.render.view import render_image, view_image
from omg4.train.config import TrainConfig
from omg4.train.strategies.densification import DensifyStats
from omg4.train.run_state import latest_iteration, load_run_checkpoint, save_run_checkpoint
from omg4.train.strategies import strategy_for

logger = logging.getLogger(__name__)


@dataclass
class TrainResult:
    """What a finished run produced."""

    model: Gaussians4D
    model_path: Path
    iterations: int
    wall_time_s: float
    history: list[dict] = field(default_factory=list)


def active_sh_degrees(step: int, interval: int, max_deg: int, max_deg_t: int) -> tuple[int, int]:
    """SH degrees at ``step``: spatial 0→max one per interval, then temporal 0→max (rt4dgs §2)."""
    k = step // max(interval, 1)
    return min(k, max_deg), min(max(k - max_deg, 0), max_deg_t)


def initial_model(scene: Scene, cfg: TrainConfig, points: PointCloud | None = None) -> Gaussians4D:
    """Gaussians from ``points``, the scene's ``points3d.ply``, or random points in the common view volume.

    The backbone's density control chooses the points (:meth:`~omg4.train.strategies.base.DensityStrategy.initial_points`:
    at most ``cfg.strategy.max_gaussians``, a random subset; a FreeTimeGS model starts at its budget exactly) and its
    ``initialize`` makes the Gaussians. Built on the CPU (so the random draws do not depend on the device); the
    caller moves it.
    """
    if points is None:
        points = scene.initial_points
    if points is None:
        points = random_initial_points(scene, cfg.num_random_points, seed=cfg.seed)
    if len(points.xyz) == 0:
        raise OMG4Error("the initial point cloud is empty")
    backbone = backbone_named(cfg.backbone)
    config = GaussianConfig(time_range=tuple(scene.time_range), backbone=backbone.name,
                            **({} if backbone.sh_degree_t is None else {"sh_degree_t": backbone.sh_degree_t}))
    gen = torch.Generator().manual_seed(cfg.seed)
    xyz = torch.as_tensor(points.xyz, dtype=torch.float32, device="cpu")
    rgb = torch.as_tensor(points.rgb, dtype=torch.float32, device="cpu")
    xyz, rgb = strategy_for(backbone, cfg).initial_points(xyz, rgb, gen)
    return Gaussians4D.from_points(xyz, rgb, config, generator=gen)


def evaluate_psnr(model, views: list[View], background: torch.Tensor, backend: str,
                  device: torch.device | str = "cpu") -> float:
    """Mean PSNR of ``model`` (living on ``device``) over ``views`` (renders clamped to [0, 1]); in a distributed
    job each rank renders its share of the views and every rank gets the mean over all of them."""
    world = distributed.world()
    mine = [psnr(render_image(model, v, background, backend, device), view_image(v, device))
            for v in world.shard(views)]
    values = distributed.interleave(distributed.gather_objects(mine, "gathering the test PSNR"))
    return float(np.mean(values)) if values else float("nan")


class Trainer:
    """Trains a :class:`Gaussians4D` on a :class:`Scene` and writes checkpoints into ``run_dir``.

    In a distributed job (:mod:`omg4.distributed`) every rank trains a replica on its share of each batch;
    rank 0 alone logs, shows progress and writes files. It starts from ``model`` when given (on the CPU),
    else from :func:`initial_model` of ``points``. ``check_replicas`` > 0 compares the replicas' parameters
    every that many steps and stops with a one-line error when they differ. ``preset``, the name of the preset
    ``cfg`` started from, is recorded beside it (``config.json``), so a resumed run can check a preset named again.
    Raises :class:`OMG4Error` at once when ``cfg.device`` is unusable or does not suit ``cfg.backend``.
    """

    def __init__(self, scene: Scene, cfg: TrainConfig, run_dir: str | Path, *, points: PointCloud | None = None,
                 model: Gaussians4D | None = None, resume: bool = False, log: Callable[[str], None] | None = None,
                 progress: bool = True, check_replicas: int = 0, preset: str | None = None):
        if not scene.train_views:
            raise OMG4Error("the scene has no training views")
        self.world = distributed.world()
        self.scene, self.cfg, self.run_dir = scene, cfg, Path(run_dir)
        self.log = (log or logger.info) if self.world.main else (lambda *_: None)
        self.progress = progress and self.world.main
        self.check_replicas = check_replicas
        self.extent = scene.extent
        self.device = resolve_device(cfg.device)
        resolve_backend(cfg.backend, self.device)
        self.background = torch.tensor(cfg.background, dtype=torch.float32, device=self.device)
        self.metadata = {
            "scene": scene.name,
            "time_range": list(scene.time_range),
            "normalization": scene.normalization.to_json(),
            "train_config": cfg.to_dict(),
            "world_size": self.world.size,
            **({"preset": preset} if preset else {}),
        }
        self.start = 0
        start_it = latest_iteration(self.run_dir) if resume else None
        if start_it is not None:
            self.model, saved, state = load_run_checkpoint(self.run_dir, start_it, self.device)
            if "held_training" in saved:
                raise OMG4Error(f"{self.run_dir}: its checkpoint trains Gaussians held from the segment before "
                                f"(--hold-lasting, {HOLD_LASTING_REMOVED}): use --force to start afresh")
            self.optimizer = self._make_optimizer()
            self.optimizer.load_state_dict(state["optimizer"])
            self.stats = DensifyStats(self.model.num_gaussians, self.device)
            if self.world.main:  # the checkpoint holds every rank's statistics combined: rank 0 carries them on
                for k, v in state["stats"].items():
                    setattr(self.stats, k, v)
            self.start = int(state["iteration"])
            self.log(f"resuming from iteration {self.start} ({self.model.num_gaussians} Gaussians)")
        else:
            self.model = (model if model is not None else initial_model(scene, cfg, points)).to(self.device)
            self.optimizer = self._make_optimizer()
            self.stats = DensifyStats(self.model.num_gaussians, self.device)
        distributed.broadcast_(list(self.model.params.values()))  # every replica starts from rank 0's model
        self.strategy = strategy_for(self.model.config.schema, cfg)
        self.history: list[dict] = []

    def _make_optimizer(self) -> torch.optim.Adam:
        for p in self.model.params.values():
            p.requires_grad_(True)
        return make_adam(self.model.params, baseline_lrs(self.cfg, self.extent, self.model.config.schema))

    def train_step(self, step: int) -> tuple[float, float]:
        """One optimizer step (1-based ``step``), with the kernels of ``cfg.kernels``; returns (mean loss, mean PSNR)
        of the batch."""
        with using_kernels(self.cfg.kernels):
            return self._train_step(step)

    def _train_step(self, step: int) -> tuple[float, float]:
        cfg, model = self.cfg, self.model
        set_position_lr(self.optimizer, step, init=cfg.position_lr_init, final=cfg.position_lr_final,
                        extent=self.extent, max_steps=cfg.position_lr_max_steps)
        model.active_sh_degree, model.active_sh_degree_t = active_sh_degrees(
            step, cfg.sh_increase_interval, model.config.sh_degree, model.config.sh_degree_t)
        views = self.scene.train_views
        batch = torch.randint(len(views), (cfg.batch_size,), generator=step_generator(cfg.seed, step), device="cpu")
        collecting = self.strategy.collects_statistics(step)

        def on_views(rendered, sl):
            if collecting and rendered.means2d.grad is not None:
                height, width = rendered.image.shape[1:3]
                self.stats.add_view(sl.index, rendered.means2d.grad, rendered.radii, width, height, cfg.batch_size)

        def regularizer(times):
            return self.strategy.regularizer(model.params, times, step)

        loss, batch_psnr = backward_batch(model, views, batch, background=self.background, backend=cfg.backend,
                                          lambda_dssim=cfg.lambda_dssim, what="training", step=step,
                                          device=self.device, on_views=on_views, regularizer=regularizer)
        step_optimizers([self.optimizer], self.device)
        self.strategy.after_step(model, self.optimizer, self.stats, step, self.extent)
        return loss, batch_psnr

    def save_checkpoint(self, step: int) -> Path:
        """Write the checkpoint of ``step`` (rank 0; the statistics of every rank combined)."""
        stats = self.stats.combined()
        if self.world.main:
            save_run_checkpoint(self.run_dir, step, self.model, self.optimizer, stats, self.metadata)
        distributed.barrier("writing a checkpoint")
        return self.run_dir

    def run(self, stop_at: int | None = None) -> TrainResult:
        """Train until ``cfg.iterations`` (or ``stop_at``, for tests of resuming), with the kernels of ``cfg.kernels``.

        Ctrl-C lets the step in progress finish, writes a checkpoint of it and raises ``KeyboardInterrupt``, so
        ``--resume`` loses no step (a second Ctrl-C stops at once; a distributed job stops at once)."""
        with using_kernels(self.cfg.kernels):
            return self._run(stop_at)

    def _run(self, stop_at: int | None) -> TrainResult:
        cfg = self.cfg
        end = min(cfg.iterations, stop_at) if stop_at else cfg.iterations
        if self.world.main:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            write_text_atomic(self.run_dir / "config.json", json.dumps(self.metadata, indent=2))
        t0 = time.perf_counter()
        bar = tqdm(range(self.start + 1, end + 1), initial=self.start, total=cfg.iterations, desc="train",
                   disable=not self.progress, dynamic_ncols=True)
        ema_loss, ema_psnr, done = None, None, self.start
        record_every = max(1, cfg.iterations // HISTORY_POINTS)
        with interrupt_between_steps(enabled=not self.world.parallel) as interrupted:
            for step in bar:
                loss, p = self.train_step(step)
                done = step
                ema_loss = loss if ema_loss is None else 0.9 * ema_loss + 0.1 * loss
                ema_psnr = p if ema_psnr is None else 0.9 * ema_psnr + 0.1 * p
                if step % 10 == 0 or step == end:
                    bar.set_postfix(loss=f"{ema_loss:.4f}", psnr=f"{ema_psnr:.2f}", N=self.model.num_gaussians)
                if step == self.start + ESTIMATE_AFTER and step < end:
                    self._log_estimate(time.perf_counter() - t0, step, end)
                entry = {}
                if step % record_every == 0 or step == end:
                    entry = {"loss": ema_loss, "train_psnr": ema_psnr}
                if cfg.test_interval and step % cfg.test_interval == 0 and self.scene.test_views:
                    entry["test_psnr"] = evaluate_psnr(self.model, self.scene.test_views, self.background,
                                                       cfg.backend, self.device)
                    self.log(f"[{step}] test PSNR {entry['test_psnr']:.2f} dB, {self.model.num_gaussians} Gaussians")
                if entry:
                    self.history.append({"iteration": step, **entry, "num_gaussians": self.model.num_gaussians})
                if cfg.checkpoint_interval and step % cfg.checkpoint_interval == 0 and step != end:
                    self.save_checkpoint(step)
                if self.check_replicas and step % self.check_replicas == 0:
                    distributed.check_replicas(list(self.model.params.values()), step)
                if interrupted():
                    break
        bar.close()
        if done < end:  # stopped by Ctrl-C: keep every finished step
            if done > self.start:
                self.save_checkpoint(done)
            self.log(f"interrupted after iteration {done}: checkpoint written to {self.run_dir}; continue with "
                     "--resume")
            raise KeyboardInterrupt
        wall = time.perf_counter() - t0
        self.save_checkpoint(end)
        model_path = self.run_dir / "model.safetensors"
        if end == cfg.iterations and self.world.main:
            save_gaussians(model_path, self.model, {**self.metadata, "iteration": end})
        return TrainResult(self.model, model_path, end, wall, self.history)

    def _log_estimate(self, seconds: float, step: int, end: int) -> None:
        """The time the rest of the run will take at the rate of its first steps (the first step's one-off work
        included); a run that still densifies grows, so it says so."""
        remaining = seconds / (step - self.start) * (end - step)
        growing = self.strategy.grows_until() > step
        self.log(f"about {_duration(remaining)} for the remaining {end - step:,} iterations at the rate of the first "
                 f"{step - self.start}" + (f"; the Gaussian count grows until iteration {self.strategy.grows_until():,}, "
                                            "so expect longer" if growing else ""))


HISTORY_POINTS = 100
"""How many points of the training curve (loss, PSNR and Gaussian count) a run's history keeps."""

ESTIMATE_AFTER = 20
"""Steps after which a run logs its estimated remaining time."""


def _duration(seconds: float) -> str:
    """``"40 s"``, ``"12 min"`` or ``"3.2 h"``."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min" if seconds < 5400 else f"{seconds / 3600:.1f} h"


@contextlib.contextmanager
def interrupt_between_steps(enabled: bool = True) -> Iterator[Callable[[], bool]]:
    """Inside, Ctrl-C (SIGINT) only sets a flag that the yielded function reads, so a loop can finish its step and
    stop cleanly; a second Ctrl-C raises ``KeyboardInterrupt`` at once. Off the main thread, or not ``enabled``,
    Ctrl-C raises as usual."""
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield lambda: False
        return
    pressed = []

    def handler(signum, frame):
        if pressed:
            raise KeyboardInterrupt
        pressed.append(signum)

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield lambda: bool(pressed)
    finally:
        signal.signal(signal.SIGINT, previous)


def train(scene: Scene, cfg: TrainConfig, run_dir: str | Path, **kwargs) -> TrainResult:
    """Train the baseline of ``cfg.backbone`` (Real-Time4DGS or FreeTimeGS) on ``scene`` (see :class:`Trainer`)."""
    return Trainer(scene, cfg, run_dir, **kwargs).run()


__all__ = ["TrainResult", "Trainer", "train", "initial_model", "evaluate_psnr", "active_sh_degrees"]
