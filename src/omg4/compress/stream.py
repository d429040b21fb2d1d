"""A long capture coded as a stream: what a predicted segment takes of the segment before (beyond the paper;
docs/file-format.md §8a–8b), in one place — the segment before itself (:class:`SegmentBefore`: its decoded
appearance MLPs, codebooks and Gaussians), the lasting rule (:func:`lasting`), the base layer (:func:`base_layer`)
and the carry decision (:func:`chosen_carry`). The compression pipeline and
:func:`omg4.compress.api.compress_to_file` take a predicted segment's link to the stream as one
:class:`SegmentBefore` (None: a key segment, coded alone). What a segment learns where it overlaps the one before
(the crossfade) is :mod:`omg4.optimize.teaching`, below training and compression, which both fit it.

A long capture's lasting content — the static set, the slow background — is in every segment, and every segment
learns it again, each a little differently, so coded segment by segment it is paid for in each. At the appearance
stage (paper §4.4), when a predicted segment switches to the segment before's MLPs, it takes instead the segment
before's decoded Gaussians that last through its own time range and stay put there — temporal marginal at least
``LASTING_MARGINAL`` at both ends, the time scale in the backbone's own terms (√Σtt of Real-Time4DGS's 4D
covariance, rt4dgs §1.4; FreeTimeGS's duration), and a centre that moves at most ``STILL`` of its size
(:func:`lasting`) — as a **base layer**, fixed and exactly as they decoded there, so
the file names each with about a bit (:mod:`omg4.codec.carry`); and it drops its own lasting Gaussians that the base
layer covers (a carried centre within :data:`COVER` of their largest scale). What remains of its own is what it
adds — new and changed content — so its Gaussian budget follows that (:func:`base_layer`); the fine-tuning that
follows fits its own Gaussians and MLPs around the base layer. Carried Gaussians are part of the segment's decoded
model, so the next predicted segment carries them on while they last: lasting content is coded once per key
interval.

``omg4 compress --carry auto`` (the default) carries the base layer where it covers at least
:data:`AUTO_MIN_COVERED` of the segment's own Gaussians (:func:`chosen_carry`), ``lasting`` always, 0 never
(the paper's way: every segment coded whole). A number T > 0 carries one to one instead: each own Gaussian within T
of one of the segment before's — centres in units of its largest scale, time centres in units of its temporal
standard deviation, the largest difference of sorted log-scales and of static appearance features — is replaced by
it, closest pairs first (:func:`carry_matches`; docs/results.md measures both: "Carried Gaussians" and "Lasting
Gaussians as a base layer").
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from omg4.codec.carry import carried_gaussians, reference_count
from omg4.codec.payload import CompressedPayload
from omg4.codec.references import reference_sections
from omg4.gaussians.appearance import AppearanceMLP
from omg4.gaussians.visibility import least_marginal
from omg4.models.compact import payload_values


LASTING_MARGINAL = 0.5
"""A Gaussian lasts through a segment when its temporal marginal is at least this at both ends of the segment's time
range (so everywhere between: the marginal is unimodal)..."""

STILL = 1.0
"""... and stays put: its centre moves (velocity × time from its time centre) at most this many of its largest scale
anywhere in the segment. A Gaussian fitted to one segment's frames and carried on with its motion extrapolated would
otherwise drift from where the video shows its content."""


def lasting(values: dict[str, torch.Tensor], config, time_range: tuple[float, float]) -> np.ndarray:
    """[N] bool: which Gaussians last through ``time_range`` and stay put there (:data:`LASTING_MARGINAL` at both its
    ends, the temporal variance and the velocity in the backbone's own terms, rt4dgs §1.4; :data:`STILL`)."""
    values = {k: v.detach().cpu() for k, v in values.items()}
    velocity, _, var_t = config.schema.motion(values, config)
    mu = values["t"].double().reshape(-1)
    moved = velocity.double().norm(dim=1) * torch.maximum(*[(mu - end).abs() for end in time_range])
    size = torch.from_numpy(largest_scale(values))
    return ((least_marginal(mu, var_t, *time_range) >= LASTING_MARGINAL) & (moved <= STILL * size)).numpy()


def largest_scale(values: dict[str, torch.Tensor]) -> np.ndarray:
    """[N] float64: each Gaussian's largest spatial scale (the size the lasting rule, the base layer's cover and the
    one-to-one match measure distances in)."""
    return np.exp(values["scaling"].detach().cpu().double().numpy().max(axis=1))


CANDIDATES = 8
"""Nearest reference centres tried per Gaussian."""

AUTO = "auto"
"""The ``carry`` setting that decides per predicted segment (:func:`chosen_carry`)."""

LASTING = "lasting"
"""The ``carry`` setting that carries the segment before's lasting Gaussians as a base layer (:func:`base_layer`)."""

COVER = 1.0
"""An own lasting Gaussian is covered by the base layer when a carried centre lies within this many of its largest
scale."""

AUTO_MIN_COVERED = 0.1
"""``auto`` carries the base layer where at least this share of a segment's Gaussians are covered by it."""


def base_layer(own: dict[str, torch.Tensor], reference: dict[str, torch.Tensor], config,
               time_range: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """The base layer a predicted segment carries: (own rows it covers, reference rows it carries) — every reference
    Gaussian that lasts through ``time_range`` (:func:`lasting`), and every own lasting Gaussian with one of their
    centres within :data:`COVER` of its largest scale."""
    ref_rows = np.flatnonzero(lasting(reference, config, time_range))
    own_lasting = np.flatnonzero(lasting(own, config, time_range))
    if not ref_rows.size or not own_lasting.size:
        return np.zeros(0, np.int64), ref_rows.astype(np.int64)
    xyz = own["xyz"].detach().cpu().double().numpy()[own_lasting]
    size = largest_scale(own)[own_lasting]
    distance, _ = cKDTree(reference["xyz"].detach().cpu().double().numpy()[ref_rows]).query(xyz, k=1)
    return own_lasting[distance <= COVER * size].astype(np.int64), ref_rows.astype(np.int64)


def carry_matches(own: dict[str, torch.Tensor], reference: dict[str, torch.Tensor], config,
                  tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (own row, reference row), one to one, of Gaussians that differ by at most ``tolerance`` (module
    docstring); ``own`` and ``reference`` are per-Gaussian parameters by the names of ``config``'s backbone."""

    def arrays(values):
        out = {k: values[k].detach().cpu().double().numpy().reshape(len(values["xyz"]), -1)
               for k in ("xyz", "t", "scaling", "f_static")}
        var_t = config.schema.motion({k: v.detach().cpu() for k, v in values.items()}, config)[2]
        out["time_std"] = var_t.detach().double().clamp_min(0).sqrt().numpy().reshape(-1)
        return out

    a, b = arrays(own), arrays(reference)
    if not len(a["xyz"]) or not len(b["xyz"]) or tolerance <= 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    k = min(CANDIDATES, len(b["xyz"]))
    _, near = cKDTree(b["xyz"]).query(a["xyz"], k=k)
    near = near.reshape(len(a["xyz"]), k)
    rows = np.repeat(np.arange(len(a["xyz"])), k)
    cols = near.ravel()
    size = largest_scale(own)[rows]
    distance = np.max([
        np.linalg.norm(a["xyz"][rows] - b["xyz"][cols], axis=1) / size,
        np.abs(a["t"][rows, 0] - b["t"][cols, 0]) / np.maximum(a["time_std"][rows], 1e-12),
        np.abs(np.sort(a["scaling"][rows], axis=1) - np.sort(b["scaling"][cols], axis=1)).max(axis=1),
        np.abs(a["f_static"][rows] - b["f_static"][cols]).max(axis=1),
    ], axis=0)
    close = np.flatnonzero(distance <= tolerance)
    close = close[np.argsort(distance[close], kind="stable")]
    own_rows, ref_rows = [], []
    taken_own, taken_ref = np.zeros(len(a["xyz"]), bool), np.zeros(len(b["xyz"]), bool)
    for i in close:
        r, c = rows[i], cols[i]
        if not taken_own[r] and not taken_ref[c]:
            taken_own[r] = taken_ref[c] = True
            own_rows.append(r)
            ref_rows.append(c)
    return np.asarray(own_rows, np.int64), np.asarray(ref_rows, np.int64)


@dataclasses.dataclass(frozen=True)
class CarryDecision:
    """What a predicted segment carries: ``kind`` ``"lasting"`` (the base layer, :func:`base_layer`), ``"matched"``
    (one-to-one within ``tolerance``, :func:`carry_matches`) or ``"none"``; its own rows that give way
    (``own_rows``) and the reference rows it carries (``ref_rows``); ``covered``: the share of its Gaussians the base
    layer covers, where the setting is ``auto`` or ``lasting`` (None otherwise: nothing was measured)."""

    setting: float | str
    kind: str
    own_rows: np.ndarray
    ref_rows: np.ndarray
    tolerance: float = 0.0
    covered: float | None = None

    def meta(self) -> dict:
        """The decision as a segment's header records it (docs/file-format.md §8b)."""
        out = {"setting": self.setting, "carried": self.kind, "gaussians": int(self.ref_rows.size)}
        if self.kind == "matched":
            out["tolerance"] = self.tolerance
        if self.covered is not None:
            out["covered_share"] = round(self.covered, 4)
        return out


def chosen_carry(own: dict[str, torch.Tensor], reference: dict[str, torch.Tensor], config, setting: float | str,
                 time_range: tuple[float, float]) -> CarryDecision:
    """What a predicted segment of ``time_range`` carries for the ``carry`` setting: a tolerance (0: none), the base
    layer (:data:`LASTING`), or :data:`AUTO`: the base layer where it covers at least :data:`AUTO_MIN_COVERED` of the
    segment's Gaussians, else none."""
    none = np.zeros(0, np.int64)
    if setting not in (AUTO, LASTING):
        tolerance = float(setting)
        if not tolerance:
            return CarryDecision(setting, "none", none, none)
        own_rows, ref_rows = carry_matches(own, reference, config, tolerance)
        return CarryDecision(setting, "matched", own_rows, ref_rows, tolerance)
    own_rows, ref_rows = base_layer(own, reference, config, time_range)
    covered = own_rows.size / max(1, len(own["xyz"]))
    if not ref_rows.size or (setting == AUTO and covered < AUTO_MIN_COVERED):
        return CarryDecision(setting, "none", none, none, covered=covered)
    return CarryDecision(setting, "lasting", own_rows, ref_rows, covered=covered)


@dataclasses.dataclass(frozen=True)
class SegmentBefore:
    """The segment a predicted segment is coded from: its decoded sections by name
    (:func:`omg4.codec.references.reference_sections`: MLP weights, codebooks, per-Gaussian arrays), which the file
    refers to (the codec takes ``sections``), and what the predicted segment takes of them."""

    sections: dict[str, np.ndarray]

    @classmethod
    def decoded(cls, payload: CompressedPayload) -> "SegmentBefore":
        """The segment before as its decoder gave it (a :class:`~omg4.codec.payload.CompressedPayload`)."""
        return cls(reference_sections(payload))

    def mlp(self, num_inputs: int) -> AppearanceMLP | None:
        """The appearance MLPs the predicted segment starts from: the segment before's decoded weights (``mlp.NAME``);
        None where it has none."""
        state = {name[len("mlp."):]: w for name, w in self.sections.items() if name.startswith("mlp.")}
        return AppearanceMLP.from_fp16_state(state, num_inputs) if state else None

    def codebooks(self, attr: str, sub_len: int, width: int) -> list[torch.Tensor] | None:
        """The codebooks of attribute ``attr`` (``width`` wide in slots of ``sub_len``) the predicted segment keeps as
        they are (``svq.ATTR.codebookJ``), or None where the segment before has none of that layout (then the segment
        fits its own)."""
        slots = [self.sections.get(f"svq.{attr}.codebook{j}") for j in range(width // sub_len)]
        if any(cb is None or cb.ndim != 2 or cb.shape[1] != sub_len for cb in slots):
            return None
        return [torch.from_numpy(np.asarray(cb, np.float32)) for cb in slots]

    @property
    def num_gaussians(self) -> int:
        """How many Gaussians the segment before holds (one-line CorruptFileError where its sections lack them)."""
        return reference_count(self.sections)

    def gaussians(self, schema) -> dict[str, torch.Tensor]:
        """The segment before's decoded Gaussians, per-Gaussian values by the names of ``schema`` (a backbone): what a
        predicted segment may carry."""
        return payload_values(carried_gaussians(self.sections), schema)


def valid_setting(setting) -> bool:
    """Whether ``setting`` is a carry setting: :data:`AUTO`, :data:`LASTING` or a finite tolerance ≥ 0."""
    if setting in (AUTO, LASTING):
        return True
    return isinstance(setting, (int, float)) and not isinstance(setting, bool) and math.isfinite(setting) \
        and setting >= 0


__all__ = ["AUTO", "AUTO_MIN_COVERED", "COVER", "CANDIDATES", "LASTING", "LASTING_MARGINAL", "STILL", "CarryDecision",
           "SegmentBefore",
           "base_layer", "carry_matches", "chosen_carry", "largest_scale", "lasting", "valid_setting"]
