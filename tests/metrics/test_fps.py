"""Render-only FPS measurement: structure, call counts, synchronization placement (rt4dgs §6, omg4 §10)."""

import statistics

import pytest
import torch

from omg4.errors import OMG4Error
from omg4.metrics import measure_fps, measure_fps_together
from omg4.metrics import timing


class FakeRenderer:
    """Records its inputs and whether gradients were enabled; returns a small tensor."""

    def __init__(self):
        self.calls, self.grad_enabled = [], []

    def __call__(self, x):
        self.calls.append(x)
        self.grad_enabled.append(torch.is_grad_enabled())
        return torch.full((4, 4, 3), float(x))


def test_structure_counts_and_consistency():
    render = FakeRenderer()
    result = measure_fps(render, [0, 1, 2, 3, 4], warmup=7, repeats=2)
    assert set(result) == {"frames", "warmup", "median_ms", "mean_ms", "min_ms", "max_ms", "fps", "fps_mean"}
    assert result["frames"] == 10 and result["warmup"] == 7
    assert render.calls == [0, 1, 2, 3, 4, 0, 1] + [0, 1, 2, 3, 4] * 2  # warm-up cycles through the inputs
    assert not any(render.grad_enabled)
    assert 0 < result["min_ms"] <= result["median_ms"] <= result["max_ms"]
    assert result["min_ms"] <= result["mean_ms"] <= result["max_ms"]
    assert result["fps"] == pytest.approx(1000.0 / result["median_ms"])
    assert result["fps_mean"] == pytest.approx(1000.0 / result["mean_ms"])


def test_renderers_timed_together_take_turns_frame_by_frame():
    """Every input is rendered by each renderer in turn, the first one rotating, after each one's own warm-up."""
    order = []

    def renderer(name):
        return lambda x: order.append((name, x))

    results = measure_fps_together([renderer("a"), renderer("b"), renderer("c")], [0, 1, 2, 3], warmup=2, repeats=2)
    warm, timed = order[:6], order[6:]
    assert warm == [("a", 0), ("a", 1), ("b", 0), ("b", 1), ("c", 0), ("c", 1)]
    starts = "abcabcab"  # the renderer that goes first rotates from input to input and across passes
    expected = []
    for turn, x in enumerate([0, 1, 2, 3] * 2):
        first = "abc".index(starts[turn])
        expected += [("abc"[(first + k) % 3], x) for k in range(3)]
    assert timed == expected
    assert [r["frames"] for r in results] == [8, 8, 8] and all(r["warmup"] == 2 for r in results)


def test_renderers_timed_together_each_get_their_own_times(monkeypatch):
    """A fake clock where renderer b always takes 3× as long as a: the medians keep them apart."""
    step = {"a": 0.002, "b": 0.006}
    clock = {"t": 0.0, "next": 0.0}

    def fake_perf_counter():
        clock["t"] += clock["next"]
        clock["next"] = 0.0
        return clock["t"]

    def renderer(name):
        def render(x):
            clock["next"] = step[name]
        return render

    monkeypatch.setattr(timing.time, "perf_counter", fake_perf_counter)
    a, b = measure_fps_together([renderer("a"), renderer("b")], list(range(5)), warmup=0)
    assert a["median_ms"] == pytest.approx(2.0) and b["median_ms"] == pytest.approx(6.0)
    assert a["fps"] / b["fps"] == pytest.approx(3.0)


def test_median_is_robust_to_one_slow_frame(monkeypatch):
    # a fake clock: each timed call takes 2 ms except one of 100 ms
    durations = iter([0.002, 0.002, 0.100, 0.002, 0.002])
    clock = {"t": 0.0, "started": False}

    def fake_perf_counter():
        if clock["started"]:
            clock["t"] += next(durations)
        clock["started"] = not clock["started"]
        return clock["t"]

    monkeypatch.setattr(timing.time, "perf_counter", fake_perf_counter)
    result = measure_fps(lambda x: x, list(range(5)), warmup=0)
    assert result["median_ms"] == pytest.approx(2.0)
    assert result["fps"] == pytest.approx(500.0)
    assert result["mean_ms"] == pytest.approx(statistics.fmean([2, 2, 100, 2, 2]))
    assert result["max_ms"] == pytest.approx(100.0)


def test_cuda_is_synchronized_around_every_timed_call(monkeypatch):
    events = []
    monkeypatch.setattr(torch.cuda, "synchronize", lambda device=None: events.append("sync"))
    measure_fps(lambda x: events.append("render"), [0, 1, 2], warmup=2, device="cuda")
    assert events == ["render"] * 2 + ["sync", "render", "sync"] * 3


def test_cpu_device_never_synchronizes(monkeypatch):
    monkeypatch.setattr(torch.cuda, "synchronize", lambda device=None: pytest.fail("synchronized on CPU"))
    assert measure_fps(lambda x: x, [1], warmup=0, device="cpu")["frames"] == 1


def test_bad_arguments():
    with pytest.raises(OMG4Error, match="at least one input"):
        measure_fps(lambda x: x, [])
    with pytest.raises(ValueError, match="repeats"):
        measure_fps(lambda x: x, [1], repeats=0)
