"""Every frame, not only the mean: per-frame summaries, the difference of two models, the plot, ``omg4 eval``."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from omg4.app.cli import main
from omg4.metrics.frames import frame_differences, frame_summary
from omg4.testing import forge


def rows(values, camera="cam00"):
    return [{"camera": camera, "frame": i, "time": i / 30, "psnr": v, "ssim": v / 40} for i, v in enumerate(values)]


def test_a_summary_names_the_worst_frame_and_the_spread():
    values = [28.0, 27.5, 25.1, 28.3, 27.9, 28.1, 26.0, 28.2, 27.7, 28.4]
    s = frame_summary(rows(values))
    assert s["worst"]["frame"] == 2 and s["min"] == 25.1 and s["max"] == 28.4
    assert s["mean"] == pytest.approx(sum(values) / 10) and s["std"] == pytest.approx(float(np.std(values)))
    assert s["p5"] == pytest.approx(25.1 + 0.45 * (26.0 - 25.1))  # numpy's linear 5th percentile of 10 values


def test_differences_pair_views_by_camera_and_frame():
    a = rows([30.0, 29.0, 31.0]) + rows([20.0], camera="cam05")
    b = list(reversed(rows([29.5, 29.5, 29.0])))  # another order; cam05 missing
    diff = frame_differences(a, b)
    assert [(d["camera"], d["frame"], d["psnr"]) for d in diff] == [("cam00", 0, 0.5), ("cam00", 1, -0.5),
                                                                     ("cam00", 2, 2.0)]


def test_eval_of_two_models_compares_every_frame_and_plots_them(tiny_scene_dir, tmp_path, capsys):
    from omg4.app.report import per_frame_plot

    a, b = tmp_path / "a.omg4", tmp_path / "b.omg4"
    forge.valid_file(a, 300, seed=1, codebook_scale=0.2)
    forge.valid_file(b, 300, seed=2, codebook_scale=0.2)
    out, plot = tmp_path / "e.json", tmp_path / "frames.png"
    assert main(["eval", str(tiny_scene_dir), "--model", str(a), "--model", str(b), "--lpips", "", "--json", str(out),
                 "--plot", str(plot)]) == 0
    record = json.loads(out.read_text())
    first, second = (m["per_view"] for m in record["models"])
    # per-frame values average to the means, and the difference is the second − the first, view by view
    assert np.mean([r["psnr"] for r in first]) == pytest.approx(record["models"][0]["psnr"])
    difference = record["difference"]["per_view"]
    assert len(difference) == len(first) == 6  # the tiny scene's test camera, every frame
    assert all(d["psnr"] == pytest.approx(s["psnr"] - f["psnr"]) for d, f, s in zip(difference, first, second))
    assert record["difference"]["psnr"]["min"] == pytest.approx(min(d["psnr"] for d in difference))
    printed = capsys.readouterr().out
    assert "b.omg4 − a.omg4" in printed and f"{record['difference']['psnr']['min']:+.2f}" in printed
    assert Image.open(plot).size[0] > 500
    lines = per_frame_plot(tmp_path / "again.png", {"a": first, "b": second})
    assert {k: len(v[0]) for k, v in lines.items()} == {"a cam00": 6, "b cam00": 6, "difference cam00": 6}
