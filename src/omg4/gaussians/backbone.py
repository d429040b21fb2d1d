"""The backbones omg4 trains and compresses, each described once.

A :class:`Backbone` lists its per-Gaussian attributes — name, shape, activation, learning
rate and what each OMG4 stage does with it (merged by a proxy, §4.3; replaced by the
appearance MLPs, §4.4; sub-vector quantized in stage 3D or 4D, §4.4; else kept explicit,
positions and time centres in fp16) — and says how a time slice is formed, how a model
starts from a point cloud, which density control trains it (a strategy of
:mod:`omg4.train.strategies`, named here and looked up only by training) and its OMG4 size presets.
Training, every OMG4 stage, the codec, the decoder and the commands read these tables; nothing
else names attributes or backbones. Every backbone has positions ``xyz`` and time centres ``t``
(the codec stores both explicitly). A new backbone is one :class:`Backbone` passed to
:func:`register_backbone`. The ``.omg4`` header and checkpoints name their backbone
(``GaussianConfig.backbone``); files without the name are Real-Time4DGS.

* ``rt4dgs`` — Real-Time4DGS (Yang et al., ICLR 2024): 4D Gaussians conditioned on time,
  4D SH; the paper's main backbone.
* ``freetimegs`` — FreeTimeGS (Wang et al., CVPR 2025): moving 3D Gaussians with a duration,
  3D SH; the paper's Table 3. Its MLPs see the time-shifted position and no time input.

Part of the render-only decoder: imports only Gaussian math.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Mapping

import torch

from omg4.gaussians.covariance import SliceGeometry, conditioning_terms, slice_geometry
from omg4.gaussians.freetime import covariance_3d, duration_variance, initialize_ftgs, slice_geometry_ftgs
from omg4.gaussians.initial import identity_quaternions, log_time_scale, neighbour_log_scales, spatial_params

SH_REST = "sh_rest"
"""Shape placeholder: the number of SH coefficients after the DC term, K − 1 (from the model config)."""


@dataclass(frozen=True)
class Attribute:
    """One per-Gaussian tensor of a backbone.

    Attributes:
        name: key in a model's ``params``.
        shape: per-Gaussian shape (:data:`SH_REST` stands for K − 1).
        activation: ``none``, ``exp``, ``sigmoid`` or ``quaternion`` (normalized at use).
        lr: the :class:`omg4.optimize.parameters.LearningRates` field (and training knob) holding its learning rate.
        extent_lr: the learning rate is multiplied by the scene extent.
        merge_logit: name of its merge-proxy logit vector when Gaussian Merging averages it (§4.3).
        by_mlp: replaced by the appearance MLPs at attribute compression (§4.4).
        svq: the sub-vector-quantized attribute it becomes part of (§4.4), or None.
    """

    name: str
    shape: tuple[int | str, ...]
    activation: str
    lr: str
    extent_lr: bool = False
    merge_logit: str | None = None
    by_mlp: bool = False
    svq: str | None = None

    def full_shape(self, n: int, num_coeffs: int) -> tuple[int, ...]:
        """``(n, *shape)`` with :data:`SH_REST` resolved for ``num_coeffs`` SH coefficients per channel."""
        return (n, *(num_coeffs - 1 if d == SH_REST else d for d in self.shape))


@dataclass(frozen=True)
class SVQGroup:
    """A sub-vector-quantized attribute (§4.4): the parameters it concatenates (those whose
    :attr:`Attribute.svq` names it, in table order), its sub-vector length, its stage."""

    name: str
    params: tuple[str, ...]
    sub_length: int
    stage: str  # "svq3d" or "svq4d"


def _svq_groups(attributes: tuple[Attribute, ...], layout: tuple[tuple[str, int, str], ...]) -> tuple[SVQGroup, ...]:
    """The SVQ groups of ``layout`` — (name, sub-vector length, stage) in stage order — with the parameters each
    concatenates read from the attributes' ``svq`` fields."""
    return tuple(SVQGroup(name, tuple(a.name for a in attributes if a.svq == name), sub_length, stage)
                 for name, sub_length, stage in layout)


#: The per-Gaussian appearance features that replace opacity and SH at attribute compression (§4.4):
#: a 3-d static feature (from the base colour) and a 3-d view feature, quantized together as ``app``.
APPEARANCE_FEATURES = (
    Attribute("f_static", (3,), "none", lr="feature_lr", svq="app"),
    Attribute("f_view", (3,), "none", lr="feature_lr", svq="app"),
)

_POSITION = Attribute("xyz", (3,), "none", lr="position_lr_init", extent_lr=True, merge_logit="merge_xyz_logits")
_TIME = Attribute("t", (1,), "none", lr="time_lr", extent_lr=True)
_OPACITY = Attribute("opacity", (1,), "sigmoid", lr="opacity_lr", by_mlp=True)
_SH_DC = Attribute("features_dc", (1, 3), "none", lr="feature_lr", merge_logit="merge_dc_logits", by_mlp=True)
_SH_REST = Attribute("features_rest", (SH_REST, 3), "none", lr="feature_rest_lr", merge_logit="merge_rest_logits",
                     by_mlp=True)
_SCALE = Attribute("scaling", (3,), "exp", lr="scaling_lr", svq="scale")
_ROTATION = Attribute("rotation", (4,), "quaternion", lr="rotation_lr", svq="rotation")
#: stage 3D of both backbones: scale (s = 1), rotation (s = 2), appearance features (s = 2) (omg4 §7)
_SVQ_3D = (("scale", 1, "svq3d"), ("rotation", 2, "svq3d"), ("app", 2, "svq3d"))


@dataclass(frozen=True)
class SizePreset:
    """Rate knobs of one OMG4 size (paper appendix): sampling ratio τ_GS, pruning quantile p, codebook size per
    SVQ attribute of ``backbone``."""

    name: str
    tau_gs: float
    prune_quantile: float
    codebook_sizes: Mapping[str, int] = field(default_factory=dict)
    backbone: str = "rt4dgs"

    def codebook(self, attribute: str) -> tuple[int, int]:
        """(sub-vector length, codebook size) of an SVQ attribute."""
        return backbone_named(self.backbone).svq_group(attribute).sub_length, self.codebook_sizes[attribute]


@dataclass(frozen=True)
class Backbone:
    """A 4D Gaussian representation: its attributes, SVQ groups, MLP input and time slice.

    Attributes:
        name: the name files carry (``GaussianConfig.backbone``).
        title: for tables and messages.
        attributes: the baseline's per-Gaussian tensors, in optimizer-group order (a resumed run's
            Adam state is matched to groups by position).
        svq_groups: the quantized attributes of a compressed model, in stage order.
        mlp_time_input: the appearance MLPs see (canonical position, time) — else the position at the
            view's time, with no time input.
        geometry: ``(values, config, timestamps [V]) →`` :class:`SliceGeometry` (conditioning and cull).
        motion: ``(values, config) → (velocity [N, 3], covariance [N, 3, 3], temporal variance [N])``: every
            backbone's Gaussian shows a 3D Gaussian moving linearly through ``xyz`` at time ``t`` with a
            constant covariance and opacity × exp(−½ (τ − t)² / variance) (the conditional mean, Schur
            complement and Σtt of rt4dgs §1.4; FreeTimeGS's motion and duration), which the ``.splatv``
            export writes exactly and a render-only model computes once at load
            (:class:`~omg4.models.windowed.WindowedModel`).
        initialize: ``(xyz [M, 3], rgb [M, 3], config, generator) → params``: a model's raw values from a point
            cloud (CPU tensors, one Gaussian per point; :mod:`omg4.gaussians.initial` holds the shared part).
        size_presets: its OMG4 sizes by name (paper appendix), and ``default_preset`` the one used unless named.
        training: the name of its density control in :data:`omg4.train.strategies.STRATEGIES`, or a
            :class:`omg4.train.strategies.base.DensityStrategy` subclass; None trains a fixed set of Gaussians.
        paper_rows: the rows ``omg4 bench`` measures for it (the paper's table of this backbone): label →
            (size preset, stages).
        sh_degree_t: the temporal SH degree it requires (None: any).
    """

    name: str
    title: str
    attributes: tuple[Attribute, ...]
    svq_groups: tuple[SVQGroup, ...]
    mlp_time_input: bool
    geometry: Callable[..., SliceGeometry]
    motion: Callable[..., tuple[torch.Tensor, torch.Tensor, torch.Tensor]]
    initialize: Callable[..., dict[str, torch.Tensor]]
    size_presets: Mapping[str, SizePreset]
    default_preset: str
    training: str | type | None = None
    paper_rows: Mapping[str, tuple[str, tuple[str, ...]]] = field(default_factory=dict)
    sh_degree_t: int | None = None

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.attributes)

    @property
    def mlp_inputs(self) -> int:
        """Inputs of the shared appearance network: position (3) and, for Real-Time4DGS, time."""
        return 4 if self.mlp_time_input else 3

    def attribute(self, name: str) -> Attribute:
        """The attribute called ``name`` (the appearance features included)."""
        for a in (*self.attributes, *APPEARANCE_FEATURES):
            if a.name == name:
                return a
        raise KeyError(f"{self.name} has no attribute '{name}'")

    def param_shapes(self, n: int, num_coeffs: int) -> dict[str, tuple[int, ...]]:
        """Raw parameter shapes of a baseline with ``n`` Gaussians and ``num_coeffs`` SH coefficients."""
        return {a.name: a.full_shape(n, num_coeffs) for a in self.attributes}

    @property
    def merged(self) -> dict[str, str]:
        """Attribute → merge-proxy logit name, for the attributes Gaussian Merging averages (§4.3)."""
        return {a.name: a.merge_logit for a in self.attributes if a.merge_logit}

    @property
    def by_mlp(self) -> tuple[str, ...]:
        """The attributes the appearance MLPs replace (§4.4)."""
        return tuple(a.name for a in self.attributes if a.by_mlp)

    def svq_group(self, name: str) -> SVQGroup:
        """The SVQ attribute called ``name``."""
        for g in self.svq_groups:
            if g.name == name:
                return g
        raise KeyError(f"{self.name} has no quantized attribute '{name}'")

    def svq_stage(self, stage: str) -> tuple[str, ...]:
        """Names of the SVQ attributes quantized at ``stage`` (``svq3d`` or ``svq4d``)."""
        return tuple(g.name for g in self.svq_groups if g.stage == stage)

    def svq_widths(self, name: str) -> tuple[tuple[str, int], ...]:
        """(parameter, width per Gaussian) of the parameters an SVQ attribute concatenates, in order."""
        widths = []
        for p in self.svq_group(name).params:
            shape = self.attribute(p).shape
            if SH_REST in shape:
                raise ValueError(f"SH coefficients cannot be sub-vector quantized ({p})")
            widths.append((p, math.prod(shape)))
        return tuple(widths)

    def quaternion_groups(self) -> tuple[str, ...]:
        """SVQ attributes that are exactly one rotation quaternion (normalized at use; q and −q alike), which
        the "compact" codec may store as unit quaternions (:mod:`omg4.codec.quaternions`)."""
        return tuple(g.name for g in self.svq_groups
                     if len(g.params) == 1 and self.attribute(g.params[0]).activation == "quaternion"
                     and self.attribute(g.params[0]).shape == (4,))

    def log_scaled_groups(self) -> tuple[str, ...]:
        """SVQ attributes stored as logarithms (every parameter exp-activated: scales, durations), whose codebooks
        the "compact" codec rounds in log space (:class:`omg4.codec.coders.CompactGrids`, ``log_scales``)."""
        return tuple(g.name for g in self.svq_groups if all(self.attribute(p).activation == "exp" for p in g.params))

    def explicit_after_compression(self) -> tuple[str, ...]:
        """The per-Gaussian tensors a fully compressed model stores unquantized (fp16 in the file)."""
        quantized = {p for g in self.svq_groups for p in g.params}
        return tuple(a.name for a in self.attributes if not a.by_mlp and a.name not in quantized)


def activated_scales(values: dict[str, torch.Tensor]) -> torch.Tensor:
    """[N, 4] exp of a Real-Time4DGS model's raw ``scaling`` and ``scaling_t`` values, (x, y, z, t)."""
    return torch.cat([values["scaling"], values["scaling_t"]], dim=1).exp()


def _rt4dgs_geometry(values: dict[str, torch.Tensor], config, timestamps: torch.Tensor) -> SliceGeometry:
    return slice_geometry(values["xyz"], values["t"], activated_scales(values), values["rotation"],
                          values["rotation_r"], timestamps, convention=config.rotation_convention,
                          time_cull=config.time_cull)


def _rt4dgs_motion(values: dict[str, torch.Tensor], config) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    # Σ12 / Σtt is the velocity of the conditional mean
    return conditioning_terms(activated_scales(values), values["rotation"], values["rotation_r"],
                              config.rotation_convention)


def _ftgs_geometry(values: dict[str, torch.Tensor], config, timestamps: torch.Tensor) -> SliceGeometry:
    return slice_geometry_ftgs(values["xyz"], values["t"], values["duration"], values["velocity"], values["scaling"],
                               values["rotation"], timestamps, time_cull=config.time_cull)


def _rt4dgs_initialize(xyz: torch.Tensor, rgb: torch.Tensor, config, generator: torch.Generator | None
                       ) -> dict[str, torch.Tensor]:
    """Real-Time4DGS from points (rt4dgs §3.5): t ~ U(t0 − 0.1 D, t1 + 0.1 D), log time scale log √(D/5), identity
    right quaternion (a static Gaussian)."""
    m, d = xyz.shape[0], config.period
    params = spatial_params(rgb, neighbour_log_scales(xyz.double().numpy()), config.num_coeffs)
    params.update(xyz=xyz.clone(),
                  t=(torch.rand(m, 1, generator=generator, device="cpu") * 1.2 - 0.1) * d + config.time_range[0],
                  scaling_t=torch.full((m, 1), log_time_scale(d), device="cpu"), rotation_r=identity_quaternions(m))
    return params


#: OMG4 sizes (paper appendix): M is the official N3DV config (τ_GS 0.2, p 0.8; codebooks 2^9 scale, 2^13
#: rotation, 2^10 appearance, 2^9 time scale, 2^13 right quaternion — the paper's q^l); L samples 0.4; S and T
#: prune at 0.9 with a 2^8 scale codebook. The appendix gives S and T the same settings, yet its Table 1 has T
#: with 19 % fewer Gaussians than S (111,402 vs 137,414 on N3DV), which codebooks cannot cause: T samples 0.25
#: here (≈ 0.83 × S's count), an inference from the table, not a stated setting.
_M_CODEBOOKS = {"scale": 2**9, "rotation": 2**13, "app": 2**10, "scale_t": 2**9, "rotation_r": 2**13}
_RT4DGS_PRESETS = {p.name: p for p in (
    SizePreset("L", 0.4, 0.8, dict(_M_CODEBOOKS)),
    SizePreset("M", 0.2, 0.8, dict(_M_CODEBOOKS)),
    SizePreset("S", 0.3, 0.9, {**_M_CODEBOOKS, "scale": 2**8}),
    SizePreset("T", 0.25, 0.9, {**_M_CODEBOOKS, "scale": 2**8}),
)}
_AC = ("appearance", "svq3d", "svq4d")
_FULL = ("sample", "prune", "merge", *_AC)
#: paper Tab. 4 (ablations; GS and GP applied at once in the fourth row) and Tab. 1 (sizes)
_RT4DGS_ROWS = {
    "GS+AC": ("M", ("sample", *_AC)),
    "GS+GP+AC": ("M", ("sample", "prune", *_AC)),
    "GS+GP+GM+AC (OMG4-M)": ("M", _FULL),
    "(GS+GP)+GM+AC": ("M", ("sample+prune", "merge", *_AC)),
    "OMG4-L": ("L", _FULL),
    "OMG4-S": ("S", _FULL),
    "OMG4-T": ("T", _FULL),
}

_RT4DGS_ATTRIBUTES = (_POSITION, _TIME, _SH_DC, _SH_REST, _OPACITY, _SCALE,
                      Attribute("scaling_t", (1,), "exp", lr="scaling_lr", svq="scale_t"), _ROTATION,
                      Attribute("rotation_r", (4,), "quaternion", lr="rotation_lr", svq="rotation_r"))
RT4DGS = Backbone(
    name="rt4dgs",
    title="Real-Time4DGS",
    attributes=_RT4DGS_ATTRIBUTES,
    svq_groups=_svq_groups((*_RT4DGS_ATTRIBUTES, *APPEARANCE_FEATURES),
                           (*_SVQ_3D, ("scale_t", 1, "svq4d"), ("rotation_r", 2, "svq4d"))),
    mlp_time_input=True,
    geometry=_rt4dgs_geometry,
    motion=_rt4dgs_motion,
    initialize=_rt4dgs_initialize,
    size_presets=_RT4DGS_PRESETS,
    default_preset="M",
    training="densification",
    paper_rows=_RT4DGS_ROWS,
)

#: FreeTimeGS sizes (paper appendix, Table 3): L samples 0.7 and prunes at the 0.6-quantile, S 0.3 and 0.4; both
#: keep the M codebooks for scale, rotation and appearance and add 2^10 for velocity and duration. No M or T.
_FTGS_CODEBOOKS = {"scale": 2**9, "rotation": 2**13, "app": 2**10, "duration": 2**10, "velocity": 2**10}
_FTGS_PRESETS = {p.name: p for p in (SizePreset("L", 0.7, 0.6, dict(_FTGS_CODEBOOKS), "freetimegs"),
                                     SizePreset("S", 0.3, 0.4, dict(_FTGS_CODEBOOKS), "freetimegs"))}

_FTGS_ATTRIBUTES = (_POSITION, _TIME, _SH_DC, _SH_REST, _OPACITY, _SCALE, _ROTATION,
                    Attribute("duration", (1,), "exp", lr="duration_lr", svq="duration"),
                    Attribute("velocity", (3,), "none", lr="velocity_lr", extent_lr=True, svq="velocity"))
FREETIMEGS = Backbone(
    name="freetimegs",
    title="FreeTimeGS",
    attributes=_FTGS_ATTRIBUTES,
    # duration and velocity (paper appendix): one scalar codebook per component, like the time scale
    svq_groups=_svq_groups((*_FTGS_ATTRIBUTES, *APPEARANCE_FEATURES),
                           (*_SVQ_3D, ("duration", 1, "svq4d"), ("velocity", 1, "svq4d"))),
    mlp_time_input=False,
    geometry=_ftgs_geometry,
    motion=lambda values, config: (values["velocity"], covariance_3d(values["scaling"], values["rotation"]),
                                   duration_variance(values["duration"])),
    initialize=initialize_ftgs,
    size_presets=_FTGS_PRESETS,
    default_preset="L",
    training="relocation",
    paper_rows={"AC only": ("L", _AC), "OMG4-FTGS-L": ("L", _FULL), "OMG4-FTGS-S": ("S", _FULL)},
    sh_degree_t=0,
)

BACKBONES: dict[str, Backbone] = {b.name: b for b in (RT4DGS, FREETIMEGS)}
"""Every backbone by the name files carry; :func:`register_backbone` adds one."""


def register_backbone(backbone: Backbone) -> Backbone:
    """Make ``backbone`` known to training, compression, the codec and the decoder (by its name); returns it.

    Raises ``ValueError`` for a name already taken by another backbone, or presets that name an SVQ attribute the
    backbone does not have.
    """
    if BACKBONES.get(backbone.name, backbone) is not backbone:
        raise ValueError(f"a different backbone is already called {backbone.name!r}")
    groups = {g.name for g in backbone.svq_groups}
    for preset in backbone.size_presets.values():
        if set(preset.codebook_sizes) != groups or preset.backbone != backbone.name:
            raise ValueError(f"preset {preset.name} of {backbone.name} must size exactly its SVQ attributes "
                             f"{sorted(groups)} and name the backbone")
    if backbone.default_preset not in backbone.size_presets:
        raise ValueError(f"{backbone.name}'s default preset {backbone.default_preset!r} is not one of its presets")
    BACKBONES[backbone.name] = backbone
    return backbone


def backbone_named(name: str) -> Backbone:
    """The backbone called ``name`` (``ValueError`` naming the choices otherwise)."""
    try:
        return BACKBONES[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown backbone {name!r} (choose from {', '.join(BACKBONES)})") from None


__all__ = ["APPEARANCE_FEATURES", "Attribute", "SVQGroup", "SizePreset", "Backbone", "RT4DGS", "FREETIMEGS",
           "BACKBONES", "SH_REST", "activated_scales", "backbone_named", "register_backbone"]
