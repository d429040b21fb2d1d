"""Which Gaussians of the segment before a predicted segment takes in place of its own (beyond the paper;
docs/file-format.md §8b).

A segment trained on from the one before still holds most of that segment's content — the static set, whatever
moves slowly — but training lets all of it drift a little, so none of it is the same value for value and every
Gaussian would be coded again. At the appearance stage (paper §4.4), when a predicted segment switches to the
segment before's MLPs, each of its Gaussians that lies close to one of the segment before's decoded Gaussians
is replaced by that one, as it decoded (a snap to the reference): from then on it is fixed, so the file names it
with about a bit (:mod:`omg4.codec.carry`), and the fine-tuning that follows lets the segment's own Gaussians
and MLPs make up the difference.

``omg4 compress --carry TOLERANCE`` carries within that tolerance; ``--carry auto`` decides per predicted segment
from its match rate (:func:`chosen_carry`). The default 0 carries none: in ``docs/results.md``, "Carried
Gaussians", a tolerance of 0.5 saves about 5 % of a real capture whose background stays put, where 11–12 % of the
Gaussians match, at −0.14 to +0.08 dB over two trainings, and costs PSNR where the content moves on and few match;
larger tolerances cost more than they save.
Close means within ``tolerance`` on each of: the distance of the centres in units of the Gaussian's largest
scale, of the time centres in units of its temporal standard deviation in the backbone's own terms (√Σtt of
Real-Time4DGS's 4D covariance, rt4dgs §1.4; FreeTimeGS's duration), the largest difference of their sorted
log-scales, and the largest difference of their static appearance features (an SH base colour at this point).
One-to-one: the closest pairs first.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree


CANDIDATES = 8
"""Nearest reference centres tried per Gaussian."""

AUTO = "auto"
"""The ``carry`` setting that decides per predicted segment (:func:`chosen_carry`)."""

AUTO_TOLERANCE = 0.5
"""The tolerance ``auto`` carries with, where it carries."""

AUTO_MIN_SHARE = 0.08
"""``auto`` carries where at least this share of a segment's Gaussians match one of the segment before's within
:data:`AUTO_TOLERANCE`: on basketball 11–12 % matched and carrying saved 5 % of the bytes, on the synthetic capture
2–5 % matched and carrying cost 0.13 dB for 1 % (``docs/results.md``, "Carried Gaussians")."""


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
    size = np.exp(a["scaling"].max(axis=1))[rows]
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


def chosen_carry(own: dict[str, torch.Tensor], reference: dict[str, torch.Tensor], config,
                 setting: float | str) -> tuple[float, float | None, tuple[np.ndarray, np.ndarray]]:
    """What a predicted segment carries for the ``carry`` setting: the tolerance, the share of its Gaussians that
    match within :data:`AUTO_TOLERANCE` (None where the setting is a number: nothing was measured), and the pairs
    (own rows, reference rows) it carries (:func:`carry_matches` at that tolerance; none at 0)."""
    none = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if setting != AUTO:
        tolerance = float(setting)
        return tolerance, None, carry_matches(own, reference, config, tolerance) if tolerance else none
    pairs = carry_matches(own, reference, config, AUTO_TOLERANCE)
    share = len(pairs[0]) / max(1, len(own["xyz"]))
    return (AUTO_TOLERANCE, share, pairs) if share >= AUTO_MIN_SHARE else (0.0, share, none)


def valid_setting(setting) -> bool:
    """Whether ``setting`` is a carry setting: :data:`AUTO` or a finite tolerance ≥ 0."""
    if setting == AUTO:
        return True
    return isinstance(setting, (int, float)) and not isinstance(setting, bool) and math.isfinite(setting) \
        and setting >= 0


__all__ = ["AUTO", "AUTO_MIN_SHARE", "AUTO_TOLERANCE", "CANDIDATES", "carry_matches", "chosen_carry",
           "valid_setting"]
