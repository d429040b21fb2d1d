"""Result tables and rate–distortion figures shared by ``omg4 demo`` and ``omg4 bench``.

Tables carry the paper's columns (PSNR, SSIM, LPIPS, FPS, #Gaussians, MB; paper Tab. 1)
plus PSNR and SSIM over the moving pixels (:mod:`omg4.metrics.dynamic`). The figure puts a
run's points (PSNR against storage, log axis) beside the paper's N3DV points at 1352×1014
(paper Tab. 1: Real-Time4DGS and OMG4-L/M/S/T), drawn on a separate panel: different data,
shown only for orientation.
"""

from __future__ import annotations

import itertools
from pathlib import Path

TABLE_COLUMNS = (("PSNR", "psnr", "{:.2f}"), ("SSIM", "ssim", "{:.4f}"), ("LPIPS", "lpips_alex", "{:.4f}"),
                 ("PSNR dyn", "psnr_dynamic", "{:.2f}"), ("SSIM dyn", "ssim_dynamic", "{:.4f}"),
                 ("FPS", "fps", "{:.1f}"), ("#Gaussians", "num_gaussians", "{:,}"), ("MB", "storage_mb", "{:.3f}"))

#: paper Tab. 1, N3DV at 1352×1014: name → (storage MB, PSNR dB)
PAPER_N3DV_POINTS: dict[str, tuple[float, float]] = {
    "Real-Time4DGS": (2087.0, 31.96),
    "OMG4-L": (5.75, 31.99),
    "OMG4-M": (3.61, 31.80),
    "OMG4-S": (2.54, 31.60),
    "OMG4-T": (2.09, 31.47),
}


def equal_training_row(title: str) -> str:
    """The results row of the equal-training control of a ``title`` baseline: one trained for as many steps as
    the baseline and the compression's fine-tuning together."""
    return f"{title}, equal training"


def format_table(rows: dict[str, dict]) -> str:
    """A markdown table with the paper's columns and the dynamic-region ones, one row per method."""
    head = "| method | " + " | ".join(c for c, _, _ in TABLE_COLUMNS) + " |"
    sep = "|---" * (len(TABLE_COLUMNS) + 1) + "|"
    lines = [head, sep]
    for name, r in rows.items():
        cells = [fmt.format(r[key]) if r.get(key) is not None else "-" for _, key, fmt in TABLE_COLUMNS]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


Curves = dict[str, dict[str, tuple[float, float]]]
"""Named rate–distortion curves: curve name → {point label → (storage MB, PSNR dB)}."""


def _panel(ax, points: dict[str, tuple[float, float]], title: str, curves: Curves | None = None) -> None:
    """Stand-alone ``points`` (grey squares) and ``curves`` (one colour and legend entry each); None: the points
    whose name starts with "OMG4" form one curve, as in the paper's figure."""
    if curves is None:
        curves = {"OMG4": {n: p for n, p in points.items() if n.startswith("OMG4")}}
        points = {n: p for n, p in points.items() if not n.startswith("OMG4")}
    curves = {name: members for name, members in curves.items() if members}
    if points:
        ax.scatter([p[0] for p in points.values()], [p[1] for p in points.values()], marker="s", s=36,
                   color="tab:gray", zorder=3)
    colours = itertools.cycle(("tab:red", "tab:blue", "tab:green", "tab:purple", "tab:orange", "tab:brown"))
    for (name, members), colour in zip(curves.items(), colours):
        line = sorted(members.values())
        ax.plot([p[0] for p in line], [p[1] for p in line], color=colour, alpha=0.6, marker="o", markersize=5,
                zorder=2, label=name if len(curves) > 1 else None)
    labelled = [*points.items(), *(item for members in curves.values() for item in members.items())]
    for i, (name, (mb, db)) in enumerate(sorted(labelled, key=lambda item: item[1][0])):
        # alternate above/below so points at similar sizes keep readable labels
        ax.annotate(name, (mb, db), textcoords="offset points", xytext=(5, 5 if i % 2 == 0 else -11), fontsize=7)
    if len(curves) > 1:
        ax.legend(fontsize=6, loc="lower right")
    sizes = [mb for _, (mb, _) in labelled]
    ax.set_xlim(min(sizes) / 2.5, max(sizes) * 8)
    ax.margins(y=0.15)
    ax.set_xscale("log")
    ax.set_xlabel("storage (MB, log scale)")
    ax.set_ylabel("PSNR (dB)")
    ax.set_title(title, fontsize=8)
    ax.grid(True, which="both", alpha=0.3)


def rate_distortion_plot(path: Path, rows: dict[str, dict], title: str, curves: Curves | None = None) -> None:
    """PSNR against MB for every row of a run, beside the paper's N3DV points; written as PNG.

    Without ``curves``, rows whose name starts with "OMG4" are drawn as the compressed curve and the
    others (baselines, ablations) as separate points; with them, ``rows`` are the separate points and
    each curve gets its colour and a legend entry.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from omg4.atomic import atomic_path

    fig, (ours, paper) = plt.subplots(1, 2, figsize=(9, 3.6), dpi=120)
    _panel(ours, {name: (r["storage_mb"], r["psnr"]) for name, r in rows.items()}, title, curves)
    _panel(paper, PAPER_N3DV_POINTS, "paper Tab. 1, N3DV 1352×1014 (different data, for orientation)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def per_frame_plot(path: Path, models: dict[str, list[dict]], title: str = "") -> dict[str, tuple[list, list]]:
    """PSNR of every evaluated frame, one line per model and test camera (``models``: label → per-view rows of
    :func:`omg4.evaluate.evaluate`); with two models a second panel shows the second − the first, frame by frame,
    its worst frame marked. Written as PNG; returns the lines drawn (name → (frames, values))."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from omg4.atomic import atomic_path
    from omg4.metrics.frames import frame_differences

    labels = list(models)
    pair = len(labels) == 2
    fig, axes = plt.subplots(2 if pair else 1, 1, figsize=(8, 5.6 if pair else 3.2), dpi=120, squeeze=False,
                             sharex=True)
    lines: dict[str, tuple[list, list]] = {}
    for label in labels:
        for camera, rows in _by_camera(models[label]).items():
            lines[f"{label} {camera}"] = ([r["frame"] for r in rows], [r["psnr"] for r in rows])
            axes[0, 0].plot(*lines[f"{label} {camera}"], marker=".", label=f"{label} {camera}")
    axes[0, 0].set_ylabel("PSNR (dB)")
    axes[0, 0].legend(fontsize=7)
    axes[0, 0].set_title(title or "PSNR of every frame")
    if pair:
        difference = frame_differences(models[labels[1]], models[labels[0]])
        ax = axes[1, 0]
        for camera, rows in _by_camera(difference).items():
            lines[f"difference {camera}"] = ([r["frame"] for r in rows], [r["psnr"] for r in rows])
            ax.plot(*lines[f"difference {camera}"], marker=".", label=camera)
        worst = min(difference, key=lambda r: r["psnr"])
        ax.annotate(f"{worst['psnr']:+.2f} dB", (worst["frame"], worst["psnr"]), fontsize=8, color="red")
        ax.axhline(0.0, color="grey", linewidth=0.8)
        ax.set_ylabel(f"{labels[1]} − {labels[0]} (dB)")
    axes[-1, 0].set_xlabel("frame")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return lines


def _by_camera(rows: list[dict]) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for r in sorted(rows, key=lambda r: (r["camera"], r["frame"])):
        out.setdefault(r["camera"], []).append(r)
    return out


__all__ = ["TABLE_COLUMNS", "PAPER_N3DV_POINTS", "Curves", "format_table", "per_frame_plot", "rate_distortion_plot"]
