"""Which density control trains which backbone: the names in the table, a class given directly, none."""

from __future__ import annotations

import dataclasses

import pytest

from omg4.errors import OMG4Error
from omg4.gaussians.backbone import FREETIMEGS, RT4DGS
from omg4.train.config import TrainConfig
from omg4.train.strategies.densification import Densification
from omg4.train.strategies.relocation import Relocation
from omg4.train.strategies import StrategySettings, strategy_for
from omg4.train.strategies.base import DensityStrategy


CFG = TrainConfig(seed=7, strategy=StrategySettings(densify_from=123, densify_until=4567, densify_interval=89,
                                                    max_gaussians=321, lambda_reg=0.25, relocate_opacity=0.004,
                                                    prune_screen_size=17.0))


def test_each_backbone_trains_with_its_named_density_control():
    assert type(strategy_for(RT4DGS, CFG)) is Densification
    assert type(strategy_for(FREETIMEGS, CFG)) is Relocation
    assert strategy_for(RT4DGS, CFG) is not strategy_for(RT4DGS, CFG)  # a new instance each time: state is per run


def test_a_strategy_owns_the_settings_of_the_run_by_their_names():
    densify = strategy_for(RT4DGS, CFG)
    assert (densify.densify_from, densify.densify_until, densify.densify_interval, densify.max_gaussians,
            densify.seed, densify.prune_screen_size) == (123, 4567, 89, 321, 7, 17.0)
    assert densify.grows_until() == 4567 and densify.collects_statistics(4566) and not densify.collects_statistics(4567)
    relocation = strategy_for(FREETIMEGS, CFG)
    assert (relocation.lambda_reg, relocation.relocate_opacity, relocation.max_gaussians) == (0.25, 0.004, 321)
    defaults = StrategySettings()  # the config's defaults are the strategies' own; the seed is the run's
    assert dataclasses.asdict(Densification()) == {f.name: TrainConfig().seed if f.name == "seed" else getattr(defaults, f.name)
                                                   for f in dataclasses.fields(Densification)}


def test_a_class_is_taken_as_it_is_and_none_trains_a_fixed_set():
    @dataclasses.dataclass
    class Mine(DensityStrategy):
        every: int = 3  # a setting the run's config does not have keeps its default

    mine = strategy_for(dataclasses.replace(RT4DGS, training=Mine), CFG)
    assert type(mine) is Mine and (mine.every, mine.max_gaussians) == (3, 321)
    fixed = strategy_for(dataclasses.replace(RT4DGS, training=None), CFG)
    assert type(fixed) is DensityStrategy and fixed.max_gaussians == 321


def test_hooks_that_still_take_the_config_are_a_one_line_error():
    class Old(DensityStrategy):
        def collects_statistics(self, cfg, step):  # the form before strategies owned their settings
            return True

    with pytest.raises(OMG4Error, match="Old: density-control hooks no longer take the TrainConfig") as caught:
        strategy_for(dataclasses.replace(RT4DGS, training=Old), CFG)
    assert "\n" not in str(caught.value)


def test_an_unknown_name_is_a_one_line_error():
    with pytest.raises(OMG4Error, match="names the density control 'densify'"):
        strategy_for(dataclasses.replace(RT4DGS, training="densify"), CFG)
