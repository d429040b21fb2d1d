"""Every frame, not only the mean: per-frame statistics of a clip's metrics, and of the difference of two models.

A mean over a clip hides the frames that fall: :func:`frame_summary` gives, from :func:`omg4.evaluate.evaluate`'s
per-view rows, the worst frame, the spread and the 5th percentile of PSNR and SSIM; :func:`frame_differences`
pairs two models' rows by (camera, frame) and summarizes model − reference the same way.
"""

from __future__ import annotations

import numpy as np


def frame_summary(rows: list[dict], key: str = "psnr") -> dict:
    """``{"mean", "std", "min", "p5", "max", "worst": {"camera", "frame", "time", key}}`` of ``key`` over the
    per-view ``rows`` (each with ``camera``, ``frame``, ``time`` and ``key``)."""
    values = np.array([r[key] for r in rows], dtype=np.float64)
    worst = rows[int(np.argmin(values))]
    return {"mean": float(values.mean()), "std": float(values.std()), "min": float(values.min()),
            "p5": float(np.percentile(values, 5)), "max": float(values.max()),
            "worst": {"camera": worst["camera"], "frame": worst["frame"], "time": worst["time"], key: worst[key]}}


def frame_differences(rows: list[dict], reference: list[dict], keys: tuple[str, ...] = ("psnr", "ssim")
                      ) -> list[dict]:
    """Per view seen by both (matched by camera and frame, in ``rows``' order): ``{"camera", "frame", "time"}``
    and ``key`` = this model's value − the reference's, for each of ``keys``."""
    by_view = {(r["camera"], r["frame"]): r for r in reference}
    out = []
    for r in rows:
        other = by_view.get((r["camera"], r["frame"]))
        if other is not None:
            out.append({"camera": r["camera"], "frame": r["frame"], "time": r["time"],
                        **{k: r[k] - other[k] for k in keys}})
    return out


def per_frame(rows: list[dict]) -> dict:
    """The per-frame record of one model: its PSNR and SSIM summaries (:func:`frame_summary`)."""
    return {"psnr": frame_summary(rows, "psnr"), "ssim": frame_summary(rows, "ssim")}


__all__ = ["frame_differences", "frame_summary", "per_frame"]
