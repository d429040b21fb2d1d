"""The OMG4 compression pipeline: a trained baseline (any backbone) → a minimal, quantized model.

Runs the events of :mod:`omg4.compress.schedule` and fine-tunes in between with the
baseline loss (paper §5.1): each iteration renders ``batch_size`` random training views,
back-propagates ``loss_v / B`` and steps every optimizer (main Adam over per-Gaussian
tensors and merge logits; MLP Adam with its schedule; codebook Adam). The model, its MLPs,
codebooks and optimizer states live on ``CompressConfig.device``; random draws come from CPU
generators, and merge clustering and k-means run on the CPU and hand their results back.
Which attributes each stage merges, replaces or quantizes is the baseline's backbone table
(:mod:`omg4.gaussians.backbone`); steps and parameter groups go through the layer the
trainer uses (:mod:`omg4.optimize.step`, :mod:`omg4.optimize.parameters`). Each stage's work is its own module;
this one
holds the order of events and the state they share (model, optimizers, scores), which is why it is about 400
lines.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from tqdm.auto import tqdm

from omg4 import distributed
from omg4.compress import appearance_stage, merging, modes
from omg4.compress.stream import AUTO_MIN_COVERED, SegmentBefore, chosen_carry, valid_setting
from omg4.compress.model import CompressibleModel
from omg4.compress.presets import SizePreset, size_preset
from omg4.compress.pruning import check_frame_floor, pruning_mask
from omg4.compress.sampling import sampling_mask
from omg4.compress.schedule import SCHEDULES, StageLengths, build_events
from omg4.compress.score import SCORE_WEIGHTINGS, SDScores, compute_sd_scores, lifetime_weights
from omg4.compress.svq import SubVectorQuantizer
from omg4.compress.time_balance import REFRESH, TIME_SAMPLINGS, DeficitSampler
from omg4.data.scene import Scene
from omg4.device import resolve_device
from omg4.errors import OMG4Error
from omg4.gaussians import Gaussians4D
from omg4.gaussians.appearance import AppearanceMLP
from omg4.gaussians.backbone import Backbone
from omg4.kernels import KERNELS_HELP, check_kernels, using_kernels
from omg4.metrics import psnr
from omg4.optimize.parameters import (LEARNING_RATES, baseline_lrs, keep_rows, make_adam, rebuilt_adam, replace_param,
                                      set_position_lr, step_optimizers)
from omg4.optimize.step import backward_batch, step_generator
from omg4.render.api import resolve_backend
from omg4.render.view import render_views, view_image, views_by_size
from omg4.settings import knob

logger = logging.getLogger(__name__)

FULL_STAGES = ("sample", "prune", "merge", "appearance", "svq3d", "svq4d")


@dataclass
class CompressConfig:
    """Everything that decides an OMG4 run; ``preset`` sets τ_GS, p and the codebook sizes (None: the
    backbone's default, :attr:`~omg4.gaussians.backbone.Backbone.default_preset`).

    ``rate_weight`` β > 0 (beyond the paper) fits the SVQ codebooks by entropy-constrained k-means
    (:func:`omg4.compress.kmeans.kmeans`: an index bit costs β times the mean k-means distortion), so index
    usage becomes skewed and the entropy-coded indices shrink; 0 keeps the paper's k-means.

    ``paper=True`` (:mod:`omg4.compress.modes`) gives every choice left unset (None) the paper's value; a choice is
    read through :meth:`choice`, which resolves it then, so ``dataclasses.replace(cfg, paper=True)`` switches every
    unset choice as ``CompressConfig(paper=True)`` does.
    """

    preset: str | None = knob(None, "size preset (L, M, S, T; None: the backbone's default)")
    stages: tuple[str, ...] = knob(FULL_STAGES, "the stages in order (ablations drop some)")
    schedule: str = knob("official", "fine-tuning lengths: official, cpu, short or tiny")
    lengths: StageLengths | None = None
    num_merge: int = knob(2, "merge rounds M")
    batch_size: int = knob(4, "views per fine-tuning step")
    seed: int = knob(6666, "random seed (batches, MLP initialization, k-means)")
    merge: merging.MergeConfig = field(default_factory=merging.MergeConfig)
    paper: bool = knob(False, "the paper's way: every choice of omg4.compress.modes.CHOICES that is not set itself "
                              "takes the paper's value (selection, view sampling, coder, segments coded alone)")
    official_score_quirk: bool = knob(False, "accumulate the time gradient without zeroing, as the official code")
    score_weighting: str | None = knob(None, "sampling and pruning rank by lifetime-weighted SD scores (lifetime, "
                                             "beyond the paper) or by the paper's (paper); unset: lifetime, or "
                                             "paper with paper=true")
    time_sampling: str | None = knob(None, "fine-tuning draws its views more often in the spans of the clip that "
                                           "fell further below the baseline (deficit, beyond the paper) or uniformly "
                                           "(uniform, the paper); unset: deficit, or uniform with paper=true")
    frame_floor: float | None = knob(None, "pruning also keeps what a single frame's static score ranks among its "
                                           "largest (this share of the Gaussians; beyond the paper), at an equal "
                                           "count; unset: 0.02, or 0 with paper=true")
    baseline_iterations: int = knob(30_000, "the baseline's steps: the position learning rate continues its decay")
    position_lr_init: float = knob(1.6e-4, "the baseline's initial position learning rate (× extent)")
    position_lr_final: float = knob(1.6e-6, "the baseline's final position learning rate (× extent)")
    codebook_lr: float = knob(1e-4, "learning rate of the SVQ codebooks")
    backend: str = knob("auto", "rasterizer: auto, cpu or gsplat")
    device: str = knob("cpu", "where tensors live: cpu, cuda, cuda:N or auto")
    kernels: str | None = knob(None, KERNELS_HELP)
    background: tuple[float, float, float] = knob((0.0, 0.0, 0.0), "background colour, RGB in [0, 1]")
    tau_gs: float | None = knob(None, "sampling ratio τ_GS, overriding the preset's")
    prune_quantile: float | None = knob(None, "pruning quantile p, overriding the preset's")
    rate_weight: float = knob(0.0, "β of entropy-constrained codebooks (beyond the paper; 0: its k-means)")
    predicted_mlp: str = knob("tune", "a predicted segment fine-tunes the segment before's appearance MLPs and "
                                      "stores the change (tune) or keeps them as they are (keep)")
    carry: float | str | None = knob(None, "what a predicted segment takes of the segment before's decoded Gaussians "
                                           "in place of its own, a bit each: auto (the lasting ones where they cover "
                                           "enough of its own), lasting (always), a tolerance (those within it, in "
                                           "units of their size) or 0 (none); unset: auto, or 0 with paper=true")
    codec: str | None = knob(None, "the .omg4 file's coder: compact (beyond the paper: codewords without their "
                                   "order, 8-bit MLP weights), ans, or paper (the paper's Huffman + LZMA); unset: "
                                   "compact, or paper with paper=true")
    key_interval: int | None = knob(None, "a segmented run: every N-th segment coded alone and the others predicted "
                                          "from the segment before (beyond the paper); unset: 8, or 1 with "
                                          "paper=true")

    def choice(self, name: str):
        """The value of the choice ``name`` (:data:`omg4.compress.modes.CHOICES`) in this run: its setting, else the
        paper's value with ``paper``, else omg4's default — the one place that resolves it."""
        value = getattr(self, name)
        return modes.choice_value(name, self.paper) if value is None else value

    def resolved(self) -> "CompressConfig":
        """A copy with every unset choice set to its value in this run (what a record of the run holds)."""
        return replace(self, **{c.setting: self.choice(c.setting) for c in modes.CHOICES if hasattr(self, c.setting)})

    def mode(self, *, sequence: bool = False) -> str:
        """The mode these settings amount to (:func:`omg4.compress.modes.mode_of`); the key interval counts for a
        ``sequence`` only."""
        values = modes.choices_of(self)
        if not sequence:
            del values["key_interval"]
        return modes.mode_of(values)

    def size(self, backbone: str = "rt4dgs") -> SizePreset:
        p = size_preset(self.preset, backbone)
        return replace(p, tau_gs=self.tau_gs if self.tau_gs is not None else p.tau_gs,
                       prune_quantile=self.prune_quantile if self.prune_quantile is not None else p.prune_quantile)

    def stage_lengths(self) -> StageLengths:
        if self.lengths is not None:
            return self.lengths
        if self.schedule not in SCHEDULES:
            raise OMG4Error(f"unknown schedule '{self.schedule}' (choose from {', '.join(SCHEDULES)})")
        return SCHEDULES[self.schedule]

    def fine_tuning_iterations(self) -> int:
        """How many fine-tuning steps the whole pipeline takes (every stage's, each merge round's)."""
        return build_events(self.stages, self.stage_lengths(), self.num_merge)[1]


@dataclass
class StageRecord:
    """One row of the pipeline's log: the stage, when it ran, the Gaussian count after it, and the training views'
    PSNR in each fifth of the clip (:data:`TIME_BUCKETS`) just before the stage and just after it (before its
    fine-tuning), so a stage that hurts some times shows where it happens; then the fine-tuning steps that followed
    it and their wall time (the steps alone, not the stage log's renders or the view sampler's refreshes)."""

    stage: str
    iteration: int
    num_gaussians: int
    seconds: float
    psnr_by_time_before: list[float] | None = None
    psnr_by_time_after: list[float] | None = None
    finetune_steps: int = 0
    finetune_seconds: float = 0.0

    @property
    def steps_per_second(self) -> float | None:
        """The stage's fine-tuning speed (None before its first step)."""
        return self.finetune_steps / self.finetune_seconds if self.finetune_steps else None


TIME_BUCKETS = 5
"""Spans of the clip the stage log reports quality for."""

VIEWS_PER_BUCKET = 2
"""Training views rendered per span for the stage log."""


class CompressionPipeline:
    """Runs OMG4 on ``baseline`` for ``scene``; see :func:`omg4.compress.api.compress_to_file`.

    The pipeline works on a copy of ``baseline`` on ``cfg.device`` (``baseline`` is left alone);
    an unusable device, or one that does not suit ``cfg.backend``, is an :class:`OMG4Error` here.
    In a distributed job (:mod:`omg4.distributed`) every rank runs the same stages on a replica, scores and
    fine-tunes on its share of the views, and rank 0 alone logs; ``check_replicas`` > 0 compares the replicas
    every that many iterations. ``before``: a predicted segment's segment before (:mod:`omg4.compress.stream`), whose
    MLPs it starts from, whose codebooks it keeps and whose Gaussians it may carry; None: a segment coded alone.
    """

    def __init__(self, baseline: Gaussians4D, scene: Scene, cfg: CompressConfig, *, scores: SDScores | None = None,
                 progress: bool = True, log=None, check_replicas: int = 0,
                 before: SegmentBefore | None = None):
        if not scene.train_views:
            raise OMG4Error("the scene has no training views")
        cfg = cfg.resolved()
        if cfg.score_weighting not in SCORE_WEIGHTINGS:
            raise OMG4Error(f"unknown score weighting '{cfg.score_weighting}' (choose from {', '.join(SCORE_WEIGHTINGS)})")
        if cfg.time_sampling not in TIME_SAMPLINGS:
            raise OMG4Error(f"unknown time sampling '{cfg.time_sampling}' (choose from {', '.join(TIME_SAMPLINGS)})")
        if cfg.predicted_mlp not in appearance_stage.PREDICTED_MLPS:
            raise OMG4Error(f"unknown predicted MLP mode '{cfg.predicted_mlp}' (choose from "
                            f"{', '.join(appearance_stage.PREDICTED_MLPS)})")
        if not valid_setting(cfg.carry):
            raise OMG4Error(f"the carry setting must be auto, lasting or a finite number >= 0, got {cfg.carry!r}")
        if not (math.isfinite(cfg.rate_weight) and cfg.rate_weight >= 0):
            raise OMG4Error(f"the rate weight must be a finite number >= 0, got {cfg.rate_weight}")
        check_frame_floor(cfg.frame_floor)
        try:
            check_kernels(cfg.kernels)
        except ValueError as exc:
            raise OMG4Error(str(exc)) from None
        prunes = any(stage in cfg.stages for stage in ("prune", "sample+prune"))
        if prunes and cfg.frame_floor > 0 and scores is not None and scores.frame_rank is None:
            raise OMG4Error("the SD scores given have no frame ranks (written by an older omg4): compute them again, "
                            "or prune without the frame floor (frame_floor = 0)")
        self.world = distributed.world()
        self.scene, self.cfg = scene, cfg
        self.progress, self.log = progress and self.world.main, (log or logger.info) if self.world.main else (lambda *_: None)
        self.check_replicas = check_replicas
        self.before = before
        self.schema: Backbone = baseline.config.schema
        self.size = cfg.size(baseline.config.backbone)
        self.device = resolve_device(cfg.device)
        resolve_backend(cfg.backend, self.device)
        self.model = CompressibleModel.from_gaussians(baseline.to(self.device))
        self.background = torch.tensor(cfg.background, dtype=torch.float32, device=self.device)
        self.extent = scene.extent
        self.scores = scores
        self.score_weights: torch.Tensor | None = None  # lifetime weights of the scored Gaussians, on first use
        self.records: list[StageRecord] = []
        for p in self.model.params.values():
            p.requires_grad_(True)
        self.optimizer = make_adam(self.model.params, self._lrs())
        self.mlp_optimizer = None
        self.mlp_scheduler = None
        self.codebook_optimizer = None
        self.time_balance = (DeficitSampler(scene.train_views, self._views_psnr) if cfg.time_sampling == "deficit"
                             else None)
        self.events, self.total_iterations = build_events(cfg.stages, cfg.stage_lengths(), cfg.num_merge)
        if cfg.stage_lengths() == SCHEDULES["tiny"] and self.world.main:
            logger.warning("the tiny schedule is a smoke test: a few fine-tuning steps per stage leave the model far "
                           "below its baseline, so its quality means nothing (schedule short, cpu or official for "
                           "figures)")

    # ----------------------------------------------------------------- optimizers
    def _lrs(self) -> dict[str, float]:
        """Learning rates of the current per-Gaussian tensors (omg4 §9)."""
        return baseline_lrs_for(self.model.params, self.extent, self.schema)

    def _rebuild_main_optimizer(self) -> None:
        """New main Adam over the current params (+ merge logits), keeping moments of surviving tensors."""
        merge = self.model.merge
        extra = merge.param_groups(self.cfg.merge.logit_lr) if merge is not None else []
        self.optimizer = rebuilt_adam(self.optimizer, self.model.params, self._lrs(), extra)

    # ---------------------------------------------------------------------- stages
    def _remove(self, keep: torch.Tensor) -> None:
        """Keep the Gaussians ``keep`` (bool [N], any device) in the params, quantizers and scores."""
        keep_rows(self.model.params, self.optimizer, keep.to(self.device))
        for q in self.model.quantizers.values():
            q.select(keep)
        if self.scores is not None:
            self.scores = self.scores.select(keep.cpu())
        if self.score_weights is not None:
            self.score_weights = self.score_weights[keep.cpu()]

    def ensure_scores(self) -> SDScores:
        """The SD scores of the current Gaussians, computed on first use (paper §4.1)."""
        if self.scores is None:
            self.scores = compute_sd_scores(self.model, self.scene.train_views, background=self.background,
                                            backend=self.cfg.backend, official_quirk=self.cfg.official_score_quirk,
                                            progress=self.progress, device=self.device)
        return self.scores

    def selection_scores(self) -> SDScores:
        """The scores sampling and pruning rank by: the SD scores, lifetime-weighted where ``cfg.score_weighting`` is
        "lifetime" (:func:`~omg4.compress.score.lifetime_weights`, from the Gaussians the scores were computed on)."""
        scores = self.ensure_scores()
        if self.cfg.score_weighting == "paper":
            return scores
        if self.score_weights is None:
            self.score_weights = lifetime_weights(self.model, sorted({v.timestamp for v in self.scene.train_views}))
        return scores.weighted(self.score_weights)

    def stage_sample(self) -> None:
        """Gaussian Sampling (paper §4.1)."""
        self._remove(sampling_mask(self.selection_scores(), self.size.tau_gs))

    def stage_prune(self) -> None:
        """Gaussian Pruning (paper §4.2) on the stored scores of the sampled set."""
        self._remove(pruning_mask(self.selection_scores(), self.size.prune_quantile, self.cfg.choice("frame_floor")))

    def stage_sample_prune(self) -> None:
        """Sampling and pruning applied at once (the paper's GS+GP ablation row)."""
        scores = self.selection_scores()
        keep = sampling_mask(scores, self.size.tau_gs)
        keep[keep.clone()] = pruning_mask(scores.select(keep), self.size.prune_quantile, self.cfg.choice("frame_floor"))
        self._remove(keep)

    def _bake_merge(self) -> None:
        proxy = self.model.merge
        if proxy is None:
            return
        baked, keep = proxy.bake(self.model.params)
        for name in proxy.merged:
            replace_param(self.model.params, self.optimizer, name, baked[name], reset_state=False)
        self.model.merge = None
        self._rebuild_main_optimizer()
        self._remove(keep)

    def stage_merge(self, round_index: int) -> None:
        """One Gaussian Merging round (paper §4.3): bake the previous round, build new groups and proxies."""
        self._bake_merge()
        mc = self.cfg.merge
        grid = mc.grid_size * mc.grid_growth ** round_index
        p = self.model.params
        groups = merging.build_merge_groups(p["xyz"].detach(), p["t"].detach(), p["features_dc"].detach(),
                                            self.model.config.time_range, grid, mc)
        self.model.merge = merging.MergeProxy(groups, self.model.num_gaussians, self.schema.merged)
        self._rebuild_main_optimizer()

    def stage_appearance(self) -> None:
        """Replace opacity and SH by the time-conditioned MLPs and per-Gaussian features (paper §4.4)."""
        self._bake_merge()
        features = appearance_stage.init_appearance_features(self.model.params)
        for name in self.schema.by_mlp:
            self.model.params.pop(name)
        for name, value in features.items():
            self.model.params[name] = value.detach().clone().requires_grad_(True)
        taken = self.before.mlp(self.schema.mlp_inputs) if self.before is not None else None
        trained = taken is None or self.cfg.predicted_mlp == "tune"
        if taken is not None:  # a predicted segment: the segment before's decoded MLPs, tuned or kept as they are
            self.model.appearance = taken.to(self.device).requires_grad_(trained)
        else:
            torch.manual_seed(self.cfg.seed)
            with torch.device("cpu"):  # initialized by the seeded CPU generator whatever the device
                self.model.appearance = AppearanceMLP(num_inputs=self.schema.mlp_inputs).to(self.device)
        if trained:
            remaining = self._remaining_after("appearance")
            self.mlp_optimizer, self.mlp_scheduler = appearance_stage.make_mlp_optimizer(
                self.model.appearance, total_iterations=remaining)
        self._rebuild_main_optimizer()
        if taken is not None and self.cfg.carry != 0:
            self._carry()

    def _carry(self) -> None:
        """A predicted segment takes the segment before's decoded Gaussians in place of its own as ``cfg.carry`` says
        (:mod:`omg4.compress.stream`: the lasting base layer, ``auto`` where it covers enough, or a tolerance);
        they render from now on, fixed. The decision is kept on the model for the file's metadata."""
        reference = self.before.gaussians(self.schema)
        if set(reference) != set(self.model.params):
            raise OMG4Error(f"the segment before has the attributes {sorted(reference)}, this one "
                            f"{sorted(self.model.params)}: no Gaussian can be carried")
        decision = chosen_carry(self.model.params, reference, self.model.config, self.cfg.carry,
                                tuple(self.scene.time_range))
        self.model.carry_decision = decision.meta()
        if decision.covered is not None:
            self.log(f"carry {self.cfg.carry}: the segment before's lasting Gaussians cover "
                     f"{100 * decision.covered:.1f} % of this segment's"
                     + ("" if decision.kind == "lasting" else ": none lasts and stays put" if decision.covered
                        >= AUTO_MIN_COVERED else f" (under {100 * AUTO_MIN_COVERED:.0f} %): none carried"))
        if decision.kind == "none":
            return
        dropped = decision.own_rows
        keep = torch.ones(self.model.num_gaussians, dtype=torch.bool)
        keep[torch.from_numpy(dropped[:self.model.num_gaussians - 1])] = False
        self._remove(keep)
        order = np.sort(decision.ref_rows)
        self.model.carried_rows = order
        self.model.carried = {k: v[torch.from_numpy(order)].to(self.device) for k, v in reference.items()}
        self.log(f"carry: {order.size:,} of the segment before's {self.before.num_gaussians:,} Gaussians, in "
                 f"place of {int((~keep).sum()):,} of this segment's")

    def _remaining_after(self, name: str) -> int:
        """Fine-tuning iterations from the event ``name`` to the end of the pipeline."""
        start = next(e.iteration for e in self.events if e.name == name)
        return self.total_iterations - start

    def _quantize(self, attributes: tuple[str, ...]) -> None:
        self._bake_merge()
        for attr in attributes:
            names = self.schema.svq_group(attr).params
            if not all(n in self.model.params for n in names):
                raise OMG4Error(f"SVQ of '{attr}' needs {names}: run the appearance stage first")
            values = torch.cat([self.model.params[n].detach().reshape(self.model.num_gaussians, -1) for n in names], 1)
            sub_len, k = self.size.codebook(attr)
            taken = self.before.codebooks(attr, sub_len, values.shape[1]) if self.before is not None else None
            if taken is not None:  # a predicted segment: the segment before's decoded codebooks, kept as they are
                self.model.quantizers[attr] = SubVectorQuantizer.assign(values, taken).requires_grad_(False)
            else:
                self.model.quantizers[attr] = SubVectorQuantizer.fit(values, sub_len, k, seed=self.cfg.seed,
                                                                     rate_weight=self.cfg.rate_weight)
            for n in names:
                self.model.params.pop(n)
        self._rebuild_main_optimizer()
        codebooks = [cb for q in self.model.quantizers.values() for cb in q.parameters() if cb.requires_grad]
        self.codebook_optimizer = (torch.optim.Adam(codebooks, lr=self.cfg.codebook_lr, eps=1e-8, fused=True)
                                   if codebooks else None)

    def stage_svq3d(self) -> None:
        """SVQ of scale, rotation and appearance features (paper §4.4, stage 3D)."""
        self._quantize(self.schema.svq_stage("svq3d"))

    def stage_svq4d(self) -> None:
        """SVQ of the 4D attributes (paper §4.4, stage 4D): Real-Time4DGS's time scale and right quaternion,
        FreeTimeGS's duration and velocity."""
        self._quantize(self.schema.svq_stage("svq4d"))

    def apply_event(self, name: str, round_index: int, iteration: int) -> None:
        before = self.quality_by_time()
        t0 = time.perf_counter()
        {"sample": self.stage_sample, "prune": self.stage_prune, "sample+prune": self.stage_sample_prune,
         "appearance": self.stage_appearance, "svq3d": self.stage_svq3d, "svq4d": self.stage_svq4d,
         }.get(name, lambda: self.stage_merge(round_index))()
        seconds = time.perf_counter() - t0
        after = self.quality_by_time()
        label = f"merge{round_index + 1}" if name == "merge" else name
        self.records.append(StageRecord(label, iteration, self.model.num_gaussians, seconds, before, after))
        spans = "" if after is None else (f"; training views' PSNR by fifth of the clip "
                                          f"{' '.join(f'{p:.2f}' for p in before)} → {' '.join(f'{p:.2f}' for p in after)}")
        self.log(f"{label} (iteration {iteration}): {self.model.num_gaussians:,} Gaussians{spans}")

    def quality_by_time(self) -> list[float] | None:
        """Mean PSNR of :data:`VIEWS_PER_BUCKET` training views in each of :data:`TIME_BUCKETS` equal spans of the
        clip (views in time order, evenly spread within a span; None off the main rank)."""
        if not self.world.main:
            return None
        views = sorted(self.scene.train_views, key=lambda v: (v.timestamp, v.camera.name))
        edges = np.linspace(0, len(views), TIME_BUCKETS + 1).astype(int)
        buckets = [np.linspace(start, stop - 1, min(VIEWS_PER_BUCKET, stop - start)).round().astype(int)
                   if stop > start else [] for start, stop in zip(edges[:-1], edges[1:])]
        values = iter(self._views_psnr([views[i] for picks in buckets for i in picks]))
        return [float(np.mean([next(values) for _ in picks])) if len(picks) else float("nan") for picks in buckets]

    def _views_psnr(self, views: list) -> list[float]:
        """PSNRs of the current model's renders of training ``views``, rendered together (a pass per image size and
        batch of ``batch_size`` views, so the memory stays a training step's)."""
        out = [0.0] * len(views)
        size = self.cfg.batch_size
        with torch.no_grad():
            for same_size in views_by_size([v.camera for v in views]):
                for start in range(0, len(same_size), size):
                    group = same_size[start:start + size]
                    rendered, _ = render_views(self.model, [views[i].camera for i in group],
                                               [views[i].timestamp for i in group], background=self.background,
                                               backend=self.cfg.backend, device=self.device)
                    for image, i in zip(rendered.image, group):
                        out[i] = float(psnr(image.clamp(0.0, 1.0), view_image(views[i], self.device)))
        return out

    def rebalance(self, log: bool) -> None:
        """Re-weight the fine-tuning's draw over the clip (``time_sampling="deficit"``); ``log``: say how."""
        deficit = self.time_balance.update()
        if log:
            self.log(self.time_balance.describe(deficit))

    # -------------------------------------------------------------------- training
    def finetune_step(self, step: int) -> float:
        """One fine-tuning iteration (1-based ``step``), with the kernels of ``cfg.kernels``; returns the mean batch
        loss."""
        with using_kernels(self.cfg.kernels):
            return self._finetune_step(step)

    def _finetune_step(self, step: int) -> float:
        # the baseline's position decay, continued over the fine-tuning iterations
        set_position_lr(self.optimizer, self.cfg.baseline_iterations + step, init=self.cfg.position_lr_init,
                        final=self.cfg.position_lr_final, extent=self.extent,
                        max_steps=self.cfg.baseline_iterations + self.total_iterations)
        views = self.scene.train_views
        generator = step_generator(self.cfg.seed, step, 2)
        if self.time_balance is None:
            batch = torch.randint(len(views), (self.cfg.batch_size,), generator=generator, device="cpu")
        else:
            batch = self.time_balance.draw(self.cfg.batch_size, generator)
        loss, _ = backward_batch(self.model, views, batch, background=self.background, backend=self.cfg.backend,
                                 lambda_dssim=0.2, what="compression", step=step, device=self.device)
        step_optimizers((self.optimizer, self.mlp_optimizer, self.codebook_optimizer), self.device)
        if self.mlp_scheduler is not None:
            self.mlp_scheduler.step()
        return loss

    def replicated_tensors(self) -> list[torch.Tensor]:
        """Everything every rank must hold alike: the per-Gaussian tensors, merge weights, codebooks and MLPs."""
        modules = [m for m in (self.model.merge, self.model.appearance, *self.model.quantizers.values()) if m is not None]
        return [*self.model.params.values(), *(p for m in modules for p in m.parameters())]

    def run(self, stop_after: str | None = None) -> CompressibleModel:
        """Run every event and the fine-tuning between them, with the kernels of ``cfg.kernels``; stop after the stage
        ``stop_after`` if given."""
        with using_kernels(self.cfg.kernels):
            return self._run(stop_after)

    def _run(self, stop_after: str | None) -> CompressibleModel:
        events = list(self.events)
        stop_iteration = None
        if stop_after is not None:
            matching = [i for i, e in enumerate(events) if e.name == stop_after]
            if not matching:
                raise OMG4Error(f"--stop-after {stop_after}: that stage is not part of this pipeline")
            last = matching[-1]
            stop_iteration = events[last + 1].iteration if last + 1 < len(events) else self.total_iterations
        end = self.total_iterations if stop_iteration is None else stop_iteration
        bar = tqdm(total=end, desc="compress", disable=not self.progress, dynamic_ncols=True)
        loss_ema = None
        if self.time_balance is not None:
            self.time_balance.start()
        for step in range(1, end + 1):
            applied = False
            while events and events[0].iteration == step - 1:
                e = events.pop(0)
                self.apply_event(e.name, e.round, step - 1)
                bar.set_description(f"compress [{self.records[-1].stage}]")
                applied = True
            if self.time_balance is not None and (applied or (step - 1) % REFRESH == 0):
                self.rebalance(log=applied)
            t0 = time.perf_counter()
            loss = self.finetune_step(step)
            if self.records:
                self.records[-1].finetune_steps += 1
                self.records[-1].finetune_seconds += time.perf_counter() - t0
            loss_ema = loss if loss_ema is None else 0.9 * loss_ema + 0.1 * loss
            bar.update(1)
            if self.check_replicas and step % self.check_replicas == 0:
                distributed.check_replicas(self.replicated_tensors(), step)
            if step % 10 == 0:
                bar.set_postfix(loss=f"{loss_ema:.4f}", N=self.model.num_gaussians)
        bar.close()
        self._bake_merge()
        return self.model


def baseline_lrs_for(params: dict[str, torch.Tensor], extent: float, schema: Backbone) -> dict[str, float]:
    """Learning rates of the per-Gaussian tensors (omg4 §9), in ``params``' order."""
    lrs = baseline_lrs(LEARNING_RATES, extent, schema)
    return {k: lrs[k] for k in params}
