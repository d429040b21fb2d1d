"""The 4D Gaussian model container of every backbone (:mod:`omg4.gaussians.backbone`).

Raw (pre-activation) parameters live in ``params``, named and shaped by the backbone's
attribute table. Real-Time4DGS (rt4dgs §1–2, §3.5), for example:

| name | shape | activation |
| --- | --- | --- |
| xyz | [N, 3] | — |
| t | [N, 1] | — |
| scaling | [N, 3] | exp |
| scaling_t | [N, 1] | exp |
| rotation | [N, 4] | left quaternion (w, x, y, z), normalized at use |
| rotation_r | [N, 4] | right quaternion, normalized at use |
| opacity | [N, 1] | sigmoid |
| features_dc | [N, 1, 3] | SH coefficient 0 |
| features_rest | [N, K−1, 3] | SH coefficients 1..K−1 (K = 48 for degrees 3 × 2) |

FreeTimeGS replaces ``scaling_t`` and ``rotation_r`` by ``duration`` [N, 1] (exp) and
``velocity`` [N, 3], with 3D SH only (K = 16).

The trainer replaces entries of ``params`` (densification) and owns ``requires_grad``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import TYPE_CHECKING

import numpy as np
import torch

from omg4.errors import DataError
from omg4.gaussians import fused_slice
from omg4.gaussians.backbone import BACKBONES, Backbone, activated_scales, backbone_named
from omg4.gaussians.covariance import SliceGeometry, covariance_4d
from omg4.gaussians.rotation import ROTATION_CONVENTIONS
from omg4.gaussians.sh import colors_from_sh, fold_time_sh, num_sh_coeffs, sh_to_rgb, view_directions
from omg4.render.view import TimeSlice, ViewSlicer

if TYPE_CHECKING:
    from omg4.gaussians.appearance import AppearanceMLP

SH_DIRECTIONS = ("conditioned", "canonical")


@dataclass
class GaussianConfig:
    """Fixed settings of a model (not learned).

    Attributes:
        time_range: (t0, t1); T = t1 − t0 is the SH time period (rt4dgs §2).
        sh_degree, sh_degree_t: maximum spatial / temporal SH degrees.
        rotation_convention: ``"flip"`` (official current) or ``"legacy"`` (pre-900c592).
        time_cull: cull Gaussians whose temporal marginal p_t ≤ this (rt4dgs §1.4).
        sh_direction: SH view direction from the ``"conditioned"`` mean μ_3D(τ) (default,
            paper-consistent) or the ``"canonical"`` μ_xyz (official CUDA forward, rt4dgs §1.6-1).
        backbone: the representation (:data:`omg4.gaussians.backbone.BACKBONES`); files that do
            not name one are Real-Time4DGS. FreeTimeGS needs ``sh_degree_t = 0``.
    """

    time_range: tuple[float, float]
    sh_degree: int = 3
    sh_degree_t: int = 2
    rotation_convention: str = "flip"
    time_cull: float = 0.05
    sh_direction: str = "conditioned"
    backbone: str = "rt4dgs"

    def __post_init__(self):
        t0, t1 = _finite_pair(self.time_range, "time_range")
        self.time_range = (t0, t1)
        if not t1 > t0:
            raise ValueError(f"time_range must be increasing, got {self.time_range}")
        if not (_is_int(self.sh_degree, 0, 3) and _is_int(self.sh_degree_t, 0, 2)):
            raise ValueError(f"SH degrees must be integers in 0..3 × 0..2, got {self.sh_degree!r} × "
                             f"{self.sh_degree_t!r}")
        if self.rotation_convention not in ROTATION_CONVENTIONS:
            raise ValueError(f"rotation_convention must be one of {ROTATION_CONVENTIONS}")
        if not (_is_real(self.time_cull) and 0.0 <= self.time_cull < 1.0):
            raise ValueError(f"time_cull must be a number in [0, 1), got {self.time_cull!r}")
        self.time_cull = float(self.time_cull)
        if self.sh_direction not in SH_DIRECTIONS:
            raise ValueError(f"sh_direction must be one of {SH_DIRECTIONS}")
        required_t = backbone_named(self.backbone).sh_degree_t
        if required_t is not None and self.sh_degree_t != required_t:
            raise ValueError(f"the {self.backbone} backbone needs sh_degree_t = {required_t}, got {self.sh_degree_t}")

    @property
    def schema(self) -> Backbone:
        """The backbone's attribute table and time slice."""
        return BACKBONES[self.backbone]

    @property
    def period(self) -> float:
        """T = t1 − t0."""
        return self.time_range[1] - self.time_range[0]

    @property
    def band_size(self) -> int:
        """SH coefficients per temporal band, (sh_degree + 1)²."""
        return num_sh_coeffs(self.sh_degree)

    @property
    def num_coeffs(self) -> int:
        """K = (sh_degree + 1)² · (sh_degree_t + 1) coefficients per channel."""
        return self.band_size * (self.sh_degree_t + 1)

    def to_json(self) -> dict:
        d = asdict(self)
        d["time_range"] = list(self.time_range)
        return d

    @staticmethod
    def from_json(d: dict) -> "GaussianConfig":
        """Inverse of :meth:`to_json`; anything but a dict of known, valid fields raises ``ValueError``."""
        if not isinstance(d, dict):
            raise ValueError(f"a model config must be a JSON object, got {type(d).__name__}")
        unknown = sorted(set(d) - {f.name for f in fields(GaussianConfig)})
        if unknown or "time_range" not in d:
            raise ValueError(f"model config has unknown fields {unknown} or no time_range")
        return GaussianConfig(**d)


def _is_int(v: object, lo: int, hi: int) -> bool:
    """``v`` is an integer (not a bool) in ``[lo, hi]``."""
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool) and lo <= v <= hi


def _is_real(v: object) -> bool:
    """``v`` is a finite real number (not a bool)."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and bool(np.isfinite(v))


def _finite_pair(v: object, what: str) -> tuple[float, float]:
    """Two finite numbers ``(a, b)`` from a 2-sequence, else ``ValueError``."""
    if not (isinstance(v, (list, tuple)) and len(v) == 2 and all(_is_real(x) for x in v)):
        raise ValueError(f"{what} must be two finite numbers, got {v!r}")
    return float(v[0]), float(v[1])


def param_shapes(n: int, config: GaussianConfig) -> dict[str, tuple[int, ...]]:
    """Expected raw parameter shapes for ``n`` Gaussians of ``config``'s backbone."""
    return config.schema.param_shapes(n, config.num_coeffs)


class Gaussians4D(ViewSlicer):
    """A baseline 4D Gaussian model of any backbone: raw parameters, fixed config and active SH degrees."""

    def __init__(self, params: dict[str, torch.Tensor], config: GaussianConfig,
                 active_sh_degree: int | None = None, active_sh_degree_t: int | None = None):
        names = config.schema.param_names
        missing = [k for k in names if k not in params]
        if missing:
            raise ValueError(f"missing parameters {missing}")
        n = int(params["xyz"].shape[0])
        expected = param_shapes(n, config)
        for k in names:
            if tuple(params[k].shape) != expected[k]:
                raise ValueError(f"parameter '{k}' has shape {tuple(params[k].shape)}, expected {expected[k]}")
        self.params = params
        self.config = config
        self.active_sh_degree = config.sh_degree if active_sh_degree is None else int(active_sh_degree)
        self.active_sh_degree_t = config.sh_degree_t if active_sh_degree_t is None else int(active_sh_degree_t)
        if not (0 <= self.active_sh_degree <= config.sh_degree and 0 <= self.active_sh_degree_t <= config.sh_degree_t):
            raise ValueError(f"active SH degrees ({self.active_sh_degree}, {self.active_sh_degree_t}) exceed the "
                             f"maximum ({config.sh_degree}, {config.sh_degree_t})")

    @property
    def num_gaussians(self) -> int:
        return int(self.params["xyz"].shape[0])

    @classmethod
    def from_points(cls, xyz: torch.Tensor, rgb: torch.Tensor, config: GaussianConfig, *,
                    generator: torch.Generator | None = None) -> "Gaussians4D":
        """Initial model from a point cloud (rt4dgs §3.5), one Gaussian per point, by the backbone's
        ``initialize`` (:mod:`omg4.gaussians.initial`: isotropic scales from the 3 nearest neighbours, identity
        rotations, opacity 0.1, the points' colours; Real-Time4DGS and FreeTimeGS add their time attributes).
        The model is built on the CPU (``generator`` is a CPU one); move it with :meth:`to`.

        Args:
            xyz: [M, 3] positions; rgb: [M, 3] colours in [0, 1].
        """
        cpu = torch.device("cpu")
        xyz = torch.as_tensor(xyz, dtype=torch.float32, device=cpu)
        rgb = torch.as_tensor(rgb, dtype=torch.float32, device=cpu)
        m = xyz.shape[0]
        if m == 0:
            raise DataError("cannot initialize Gaussians from an empty point cloud")
        if xyz.shape != (m, 3) or rgb.shape != (m, 3):
            raise DataError(f"point cloud shapes {tuple(xyz.shape)} / {tuple(rgb.shape)}, expected [M, 3] both")
        if not (torch.isfinite(xyz).all() and torch.isfinite(rgb).all()):
            raise DataError("the point cloud contains NaN or Inf values")
        params = config.schema.initialize(xyz, rgb, config, generator)
        params = {k: params[k] for k in config.schema.param_names}
        return cls(params, config, active_sh_degree=0, active_sh_degree_t=0)

    # activations -----------------------------------------------------------------------
    def opacity(self) -> torch.Tensor:
        """[N] sigmoid(opacity)."""
        return torch.sigmoid(self.params["opacity"][:, 0])

    def scales(self) -> torch.Tensor:
        """[N, 4] exp of a Real-Time4DGS model's log scales, (x, y, z, t)."""
        return activated_scales(self.params)

    def features(self) -> torch.Tensor:
        """[N, K, 3] all SH coefficients (DC first)."""
        return torch.cat([self.params["features_dc"], self.params["features_rest"]], dim=1)

    def covariance_4d(self) -> torch.Tensor:
        """[N, 4, 4] Σ4 of a Real-Time4DGS model (rt4dgs §1.3)."""
        p = self.params
        return covariance_4d(self.scales(), p["rotation"], p["rotation_r"], self.config.rotation_convention)

    # rendering -------------------------------------------------------------------------
    def slice_views(self, timestamps: torch.Tensor, camera_centers: torch.Tensor) -> TimeSlice:
        """The 3D Gaussians of ``V`` views at once: ``timestamps`` [V], ``camera_centers`` [V, 3]."""
        return slice_values(self.params, self.config, self.active_sh_degree, self.active_sh_degree_t, timestamps,
                            camera_centers)

    def to(self, device: torch.device | str) -> "Gaussians4D":
        """This model with its parameters on ``device`` (tensors already there are shared, not copied).

        Moved tensors are new leaves with the same ``requires_grad`` (a plain ``.to`` of a
        leaf that requires grad would be a non-leaf, whose flags cannot be changed later).
        """
        params = {k: _moved_leaf(v, device) for k, v in self.params.items()}
        return Gaussians4D(params, self.config, self.active_sh_degree, self.active_sh_degree_t)

    def detach_copy(self) -> "Gaussians4D":
        """An independent copy with detached, cloned parameters."""
        params = {k: v.detach().clone() for k, v in self.params.items()}
        return Gaussians4D(params, self.config, self.active_sh_degree, self.active_sh_degree_t)


def _moved_leaf(value: torch.Tensor, device: torch.device | str) -> torch.Tensor:
    moved = value.to(device)
    return moved if moved is value else moved.detach().requires_grad_(value.requires_grad)


def slice_values(values: dict[str, torch.Tensor], config: GaussianConfig, sh_degree: int, sh_degree_t: int,
                 timestamps: torch.Tensor, camera_centers: torch.Tensor, *,
                 appearance: "AppearanceMLP | None" = None, position_term: torch.Tensor | None = None,
                 geometry: SliceGeometry | None = None, rows: torch.Tensor | None = None) -> TimeSlice:
    """The 3D Gaussians that raw per-Gaussian ``values`` show to ``V`` views (rt4dgs §1.4 + §2).

    Positions, covariances, opacity · p_t and the cull p_t ≤ ``time_cull`` for all views
    in one pass, by the backbone's time slice (``config.schema.geometry``: the Real-Time4DGS
    conditioning or the FreeTimeGS motion) unless the caller gives that ``geometry``; colours
    max(SH + 0.5, 0) with the active degrees only and Δt = μ_t − τ. The appearance (opacity, SH) is either explicit in ``values`` or,
    with ``appearance`` (paper §4.4), predicted by the MLPs from ``f_static``/``f_view`` —
    only for the rows that passed the cull, in one pass for every view. Differentiable
    w.r.t. every value.

    Args:
        values: the backbone's geometry attributes and either ``opacity, features_dc,
            features_rest`` or ``f_static, f_view``.
        timestamps: [V] view times; camera_centers: [V, 3] viewer positions.
        position_term: for a frozen model with time-conditioned MLPs, each row's
            :meth:`~omg4.gaussians.appearance.AppearanceMLP.position_term` (a renderer's cache).
        geometry: the slice's geometry at ``timestamps`` when the caller has it (a render-only model conditions
            from terms it computed at load, :func:`~omg4.gaussians.covariance.condition_and_cull`); else the
            backbone's time slice computes it from ``values``.
        rows: int64 [K] ascending: only these Gaussians take part (a merge round's rendered rows, paper §4.3); the
            slice's ``index`` still refers to the rows of ``values``.
    """
    if geometry is None and position_term is None and fused_slice.runs(values, appearance):
        return fused_slice.fused_slice(values, config, sh_degree, sh_degree_t, timestamps, camera_centers,
                                       appearance=appearance, rows=rows)
    if rows is not None:  # the torch form: slice the gathered rows, then refer the index back
        if geometry is not None:
            raise ValueError("a slice of some rows computes its own geometry")
        sl = slice_values({k: v[rows] for k, v in values.items()}, config, sh_degree, sh_degree_t, timestamps,
                          camera_centers, appearance=appearance,
                          position_term=None if position_term is None else position_term[rows])
        sl.index, sl.num_total = rows[sl.index], int(values["xyz"].shape[0])
        return sl
    xyz = values["xyz"]
    times64 = torch.as_tensor(timestamps, dtype=torch.float64, device=xyz.device).reshape(-1)
    centers = torch.as_tensor(camera_centers, dtype=xyz.dtype, device=xyz.device).reshape(-1, 3)
    geom = config.schema.geometry(values, config, times64.to(xyz.dtype)) if geometry is None else geometry
    coeffs, coeff_rows, logit = _appearance(values, config, geom, times64, appearance, position_term)
    origin = geom.means if config.sh_direction == "conditioned" else values["xyz"].index_select(0, geom.index)
    dirs = view_directions(origin, centers.index_select(0, geom.views))
    colors = colors_from_sh(coeffs, dirs, geom.dt, config.period, sh_degree, sh_degree_t, band_size=config.band_size,
                            rows=coeff_rows)
    return TimeSlice(means=geom.means, covars=geom.covars, colors=colors, opacities=torch.sigmoid(logit) * geom.marginal,
                     index=geom.index, num_total=int(xyz.shape[0]), views=geom.views)


def _appearance(values: dict[str, torch.Tensor], config: GaussianConfig, geom, times64: torch.Tensor,
                appearance: "AppearanceMLP | None", position_term: torch.Tensor | None = None
                ) -> tuple[tuple[torch.Tensor, torch.Tensor], torch.Tensor | None, torch.Tensor]:
    """(4D SH coefficients as (DC [·, 1, 3], the others [·, K − 1, 3]), the coefficient row of each slice row
    or None, opacity logits [M]) of the slice's rows ``geom.index``: explicit in ``values`` (one
    coefficient row per Gaussian, gathered by the colour kernel), or predicted by the appearance MLPs
    (paper §4.4) in one pass for every view (one per slice row); a time-conditioned network's first
    layer is split into its position part (``position_term`` where a renderer cached it, else computed
    on the rows when they are fewer than the Gaussians, or once per Gaussian) and a per-view time part."""
    idx = geom.index

    def rows(name: str) -> torch.Tensor:
        return values[name].index_select(0, idx)

    if appearance is None:
        return (values["features_dc"], values["features_rest"]), idx, rows("opacity")[:, 0]
    if config.schema.mlp_time_input:  # canonical position and normalized view time (Real-Time4DGS)
        t0, t1 = config.time_range
        t_norm = ((times64 - t0) / (t1 - t0)).to(values["xyz"].dtype)  # normalized in float64, as training did
        if position_term is not None:
            term = position_term.index_select(0, idx)
        elif idx.numel() < values["xyz"].shape[0]:  # fewer rows than Gaussians: encode the rows
            term = appearance.position_term(rows("xyz"))
        else:  # each Gaussian once, however many views' rows it serves
            term = appearance.position_term(values["xyz"]).index_select(0, idx)
        dc, rest, logit = appearance.predict_from_position_term(term, t_norm, geom.views, rows("f_static"),
                                                                rows("f_view"))
    else:  # the position at the view's time carries the time (FreeTimeGS)
        dc, rest, logit = appearance.predict(geom.means, None, rows("f_static"), rows("f_view"))
    return (dc, rest), None, logit


def _row_coefficients(coeffs: tuple[torch.Tensor, torch.Tensor], coeff_rows: torch.Tensor | None) -> torch.Tensor:
    """The coefficients [M, K, 3] of each slice row from :func:`_appearance`'s first two results."""
    joined = torch.cat(coeffs, dim=1)
    return joined if coeff_rows is None else joined.index_select(0, coeff_rows)


@dataclass
class StaticSlice:
    """The plain 3D Gaussians a 4D model shows at one time, view dependence kept as 3D SH.

    Attributes:
        means: [M, 3]; covars: [M, 3, 3]; opacities: [M] opacity × temporal marginal;
        sh: [M, (degree+1)², 3] 3D SH coefficients (the 4D time bands folded at τ, rt4dgs §2);
        index: [M] rows of the model that passed the temporal cull.
    """

    means: torch.Tensor
    covars: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor
    index: torch.Tensor


def static_slice(values: dict[str, torch.Tensor], config: GaussianConfig, sh_degree: int, sh_degree_t: int,
                 timestamp: float, *, appearance: "AppearanceMLP | None" = None) -> StaticSlice:
    """The 3D Gaussians of raw per-Gaussian ``values`` at ``timestamp`` with 3D SH instead of colours.

    Rendering it as plain 3DGS from any camera gives :func:`slice_values`' image for that camera
    (with ``sh_direction="conditioned"``: the view direction starts at the conditional mean, as
    a 3D Gaussian's does). The export formats (``.ply``, ``.splatv``) are written from it.
    """
    xyz = values["xyz"]
    times64 = torch.tensor([float(timestamp)], dtype=torch.float64, device=xyz.device)
    geom = config.schema.geometry(values, config, times64.to(xyz.dtype))
    coeffs, coeff_rows, logit = _appearance(values, config, geom, times64, appearance)
    sh = fold_time_sh(_row_coefficients(coeffs, coeff_rows), geom.dt, config.period, sh_degree, sh_degree_t,
                      band_size=config.band_size)
    return StaticSlice(means=geom.means, covars=geom.covars, opacities=torch.sigmoid(logit) * geom.marginal, sh=sh,
                       index=geom.index)


def centre_appearance(values: dict[str, torch.Tensor], config: GaussianConfig, sh_degree_t: int, *,
                      appearance: "AppearanceMLP | None" = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Each Gaussian's view-averaged colour and opacity at its own time centre τ = μ_t.

    The view average of SH colours is the DC term (the other bands integrate to zero over the
    sphere); its temporal bands are folded at Δt = 0. For formats that store one colour per
    Gaussian (``.splatv``). Returns ``rgb [N, 3]`` clamped to [0, 1] and ``opacity [N]``.
    """
    xyz = values["xyz"]
    rows = torch.arange(xyz.shape[0], device=xyz.device)
    zeros = torch.zeros(xyz.shape[0], dtype=xyz.dtype, device=xyz.device)
    centres = SliceGeometry(index=rows, means=xyz, covars=None, marginal=None, dt=zeros, views=rows)
    coeffs, coeff_rows, logit = _appearance(values, config, centres, values["t"][:, 0].double(), appearance)
    dc = fold_time_sh(_row_coefficients(coeffs, coeff_rows), zeros, config.period, 0, sh_degree_t,
                      band_size=config.band_size)[:, 0]
    return sh_to_rgb(dc).clamp(0.0, 1.0), torch.sigmoid(logit)


__all__ = ["slice_values", "static_slice", "StaticSlice", "centre_appearance", "SH_DIRECTIONS", "GaussianConfig", "Gaussians4D", "param_shapes",
           ]
