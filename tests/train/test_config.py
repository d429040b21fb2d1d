"""make_config: scaling a preset's schedule with --iterations (densification must not run more often than every 100 steps, or the count explodes)."""

from __future__ import annotations

import pytest

from omg4.train import make_config
from omg4.train.config import MIN_DENSIFY_INTERVAL


def test_shorter_run_scales_the_window_but_not_the_interval_below_100():
    cfg = make_config("official", iterations=5000)  # factor 1/6: the interval would become 17
    assert cfg.strategy.densify_interval == MIN_DENSIFY_INTERVAL == 100
    assert cfg.strategy.densify_until == 2500 and cfg.strategy.densify_from == 83
    assert cfg.strategy.opacity_reset_interval == 500 and cfg.sh_increase_interval == 167


def test_longer_run_scales_the_interval_up():
    cfg = make_config("cpu-small", iterations=6000)  # cpu-small: 3000 iterations, interval 100
    assert cfg.strategy.densify_interval == 200
    assert cfg.strategy.densify_until == 4000


@pytest.mark.parametrize("interval", [3, 40])
def test_an_explicit_interval_is_taken_as_given(interval):
    assert make_config("official", iterations=5000, densify_interval=interval).strategy.densify_interval == interval


def _nearest_half_even(x: float) -> int:
    from fractions import Fraction
    import math

    q = Fraction(x)
    low = math.floor(q)
    rest = q - low
    return low + 1 if rest > Fraction(1, 2) or (rest == Fraction(1, 2) and low % 2) else low


@pytest.mark.parametrize("preset", ["official", "cpu-small"])
def test_every_schedule_field_scales_to_the_nearest_step_with_its_floor(preset):
    from omg4.settings import flatten
    from omg4.train.config import PRESETS, SCHEDULE_FIELDS, TrainConfig, setting_of

    base = {**flatten(TrainConfig().to_dict()), **PRESETS[preset]}
    seen = set()
    for iterations in (1, 7, 45, 75, 150, 225, 333, 1000, 1500, 2250, 2999, 4500, 7500, 12345, 45000):
        cfg = make_config(preset, iterations=iterations)
        factor = iterations / base["iterations"]
        assert cfg.iterations == iterations
        for name in SCHEDULE_FIELDS:
            x = base[name] * factor
            seen.add(round(x % 1, 6))
            floor = 100 if name == "strategy.densify_interval" else 1
            assert setting_of(cfg, name) == max(floor, _nearest_half_even(x)), (iterations, name)
    assert 0.5 in seen and any(0 < f < 0.5 for f in seen) and any(f > 0.5 for f in seen)


def test_fields_named_explicitly_are_not_scaled_and_none_means_unset():
    cfg = make_config("official", iterations=3000, densify_until=777, opacity_reset_interval=None)
    assert cfg.strategy.densify_until == 777 and cfg.strategy.opacity_reset_interval == 300
    assert make_config("official", iterations=None) == make_config("official")


def test_the_cpu_small_preset_is_the_documented_schedule():
    cfg = make_config("cpu-small")
    density = cfg.strategy
    assert (cfg.iterations, cfg.batch_size, cfg.position_lr_max_steps, density.densify_from, density.densify_until,
            density.densify_interval, density.opacity_reset_interval, cfg.sh_increase_interval, cfg.num_random_points,
            density.max_gaussians, cfg.checkpoint_interval) == (3000, 2, 3000, 150, 2000, 100, 1000, 250, 20_000,
                                                            60_000, 500)
    official = make_config("official")  # the official Real-Time4DGS N3DV schedule (rt4dgs §3.3–3.6)
    density = official.strategy
    assert (official.iterations, official.batch_size, density.densify_from, density.densify_until,
            density.densify_interval, density.densify_grad_threshold, density.opacity_reset_interval,
            official.sh_increase_interval, official.position_lr_init, official.position_lr_final) == (
        30_000, 4, 500, 15_000, 100, 2e-4, 3000, 1000, 1.6e-4, 1.6e-6)


def test_an_unknown_preset_is_a_clear_error():
    from omg4.errors import OMG4Error

    with pytest.raises(OMG4Error, match="cpu-small"):
        make_config("fast")
