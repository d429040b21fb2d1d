"""Which Gaussians of the segment before a predicted segment takes in place of its own (beyond the paper;
docs/file-format.md §8b).

A segment trained on from the one before still holds most of that segment's content — the static set, whatever
moves slowly — but training lets all of it drift a little, so none of it is the same value for value and every
Gaussian would be coded again. At the appearance stage (paper §4.4), when a predicted segment switches to the
segment before's MLPs, each of its Gaussians that lies close to one of the segment before's decoded Gaussians
is replaced by that one, as it decoded (a snap to the reference): from then on it is fixed, so the file names it
with about a bit (:mod:`omg4.codec.carry`), and the fine-tuning that follows lets the segment's own Gaussians
and MLPs make up the difference.

``omg4 compress --carry TOLERANCE`` turns it on. The default 0 carries none: in ``docs/results.md``, "Carried
Gaussians", a tolerance of 0.5 saves 5 % of a real capture whose background stays put at the same PSNR, but costs
PSNR where the content moves on, and larger tolerances cost more than they save.
Close means within ``tolerance`` on each of: the distance of the centres in units of the Gaussian's largest
scale, of the time centres in units of its time scale, the largest difference of their sorted log-scales, and
the largest difference of their static appearance features (an SH base colour at this point). One-to-one: the
closest pairs first.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from omg4.errors import OMG4Error

CANDIDATES = 8
"""Nearest reference centres tried per Gaussian."""


def _time_scale_name(schema) -> str:
    """The backbone's log time scale: the one log-scaled attribute that is not the spatial scale."""
    names = [p for g in schema.log_scaled_groups() if g != "scale" for p in schema.svq_group(g).params]
    if len(names) != 1:
        raise OMG4Error(f"carrying Gaussians needs one log time scale in the {schema.name} backbone, found {names}")
    return names[0]


def carry_matches(own: dict[str, torch.Tensor], reference: dict[str, torch.Tensor], schema,
                  tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (own row, reference row), one to one, of Gaussians that differ by at most ``tolerance`` (module
    docstring); ``own`` and ``reference`` are per-Gaussian parameters by the backbone ``schema``'s names."""
    time_scale = _time_scale_name(schema)

    def arrays(values):
        return {k: values[k].detach().cpu().double().numpy().reshape(len(values["xyz"]), -1)
                for k in ("xyz", "t", "scaling", time_scale, "f_static")}

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
        np.abs(a["t"][rows, 0] - b["t"][cols, 0]) / np.exp(a[time_scale][rows, 0]),
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


__all__ = ["CANDIDATES", "carry_matches"]
