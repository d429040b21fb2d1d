"""Result tables and rate–distortion figures shared by ``omg4 demo`` and ``omg4 bench``.

Tables carry the paper's columns (PSNR, SSIM, LPIPS, FPS, #Gaussians, MB; paper Tab. 1)
plus PSNR and SSIM over the moving pixels (:mod:`omg4.metrics.dynamic`). The figure puts a
run's points (PSNR against storage, log axis) beside the paper's N3DV points at 1352×1014
(paper Tab. 1: Real-Time4DGS and OMG4-L/M/S/T), drawn on a separate panel: different data,
shown only for orientation.
"""

from __future__ import annotations

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


def format_table(rows: dict[str, dict]) -> str:
    """A markdown table with the paper's columns and the dynamic-region ones, one row per method."""
    head = "| method | " + " | ".join(c for c, _, _ in TABLE_COLUMNS) + " |"
    sep = "|---" * (len(TABLE_COLUMNS) + 1) + "|"
    lines = [head, sep]
    for name, r in rows.items():
        cells = [fmt.format(r[key]) if r.get(key) is not None else "-" for _, key, fmt in TABLE_COLUMNS]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _panel(ax, points: dict[str, tuple[float, float]], title: str) -> None:
    baseline = [n for n in points if not n.startswith("OMG4")]
    ours = [n for n in points if n.startswith("OMG4")]
    for names, marker, colour in ((baseline, "s", "tab:gray"), (ours, "o", "tab:red")):
        if names:
            ax.scatter([points[n][0] for n in names], [points[n][1] for n in names], marker=marker, s=36,
                       color=colour, zorder=3)
    if len(ours) > 1:
        line = sorted(points[n] for n in ours)
        ax.plot([p[0] for p in line], [p[1] for p in line], color="tab:red", alpha=0.5, zorder=2)
    for i, (name, (mb, db)) in enumerate(sorted(points.items(), key=lambda item: item[1][0])):
        # alternate above/below so points at similar sizes keep readable labels
        ax.annotate(name, (mb, db), textcoords="offset points", xytext=(5, 5 if i % 2 == 0 else -11), fontsize=7)
    sizes = [mb for mb, _ in points.values()]
    ax.set_xlim(min(sizes) / 2.5, max(sizes) * 8)
    ax.margins(y=0.15)
    ax.set_xscale("log")
    ax.set_xlabel("storage (MB, log scale)")
    ax.set_ylabel("PSNR (dB)")
    ax.set_title(title, fontsize=8)
    ax.grid(True, which="both", alpha=0.3)


def rate_distortion_plot(path: Path, rows: dict[str, dict], title: str) -> None:
    """PSNR against MB for every row of a run, beside the paper's N3DV points; written as PNG.

    Rows whose name starts with "OMG4" are drawn as the compressed curve, the others
    (baselines, ablations) as separate points.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from omg4.atomic import atomic_path

    fig, (ours, paper) = plt.subplots(1, 2, figsize=(9, 3.6), dpi=120)
    _panel(ours, {name: (r["storage_mb"], r["psnr"]) for name, r in rows.items()}, title)
    _panel(paper, PAPER_N3DV_POINTS, "paper Tab. 1, N3DV 1352×1014 (different data, for orientation)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


__all__ = ["TABLE_COLUMNS", "PAPER_N3DV_POINTS", "format_table", "rate_distortion_plot"]
