"""make_config: scaling a preset's schedule with --iterations (densification must not run more often than every 100 steps, or the count explodes)."""

from __future__ import annotations

import pytest

from omg4.train import make_config
from omg4.train.config import MIN_DENSIFY_INTERVAL


def test_shorter_run_scales_the_window_but_not_the_interval_below_100():
    cfg = make_config("official", iterations=5000)  # factor 1/6: the interval would become 17
    assert cfg.densify_interval == MIN_DENSIFY_INTERVAL == 100
    assert cfg.densify_until == 2500 and cfg.densify_from == 83
    assert cfg.opacity_reset_interval == 500 and cfg.sh_increase_interval == 167


def test_longer_run_scales_the_interval_up():
    cfg = make_config("cpu-small", iterations=6000)  # cpu-small: 3000 iterations, interval 100
    assert cfg.densify_interval == 200
    assert cfg.densify_until == 4000


@pytest.mark.parametrize("interval", [3, 40])
def test_an_explicit_interval_is_taken_as_given(interval):
    assert make_config("official", iterations=5000, densify_interval=interval).densify_interval == interval
