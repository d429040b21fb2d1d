"""Which density control trains which backbone: the names in the table, a class given directly, none; the training
config holds the backbone's own, typed."""

from __future__ import annotations

import dataclasses
import typing

import pytest

from omg4.errors import OMG4Error
from omg4.gaussians.backbone import FREETIMEGS, RT4DGS
from omg4.train.config import TrainConfig
from omg4.train.strategies import STRATEGIES, Strategy, strategy_for
from omg4.train.strategies.base import DensityStrategy
from omg4.train.strategies.densification import Densification
from omg4.train.strategies.relocation import Relocation

DENSIFY = Densification(densify_from=123, densify_until=4567, densify_interval=89, max_gaussians=321,
                        prune_screen_size=17.0)
CFG = TrainConfig(seed=7, strategy=DENSIFY)
RELOCATE = TrainConfig(seed=7, backbone="freetimegs", strategy=Relocation(
    densify_from=123, densify_until=4567, densify_interval=89, max_gaussians=321, lambda_reg=0.25,
    relocate_opacity=0.004))


def test_each_backbone_trains_with_its_named_density_control():
    assert type(strategy_for(RT4DGS, CFG)) is Densification
    assert type(strategy_for(FREETIMEGS, RELOCATE)) is Relocation
    assert strategy_for(RT4DGS, CFG) is not strategy_for(RT4DGS, CFG)  # a new instance each time: state is per run
    assert strategy_for(RT4DGS, CFG) is not CFG.strategy


def test_a_strategy_owns_the_settings_of_the_run_by_their_names_and_the_seed_is_the_runs():
    densify = strategy_for(RT4DGS, CFG)
    assert (densify.densify_from, densify.densify_until, densify.densify_interval, densify.max_gaussians,
            densify.seed, densify.prune_screen_size) == (123, 4567, 89, 321, 7, 17.0)
    assert densify.grows_until() == 4567 and densify.collects_statistics(4566) and not densify.collects_statistics(4567)
    relocation = strategy_for(FREETIMEGS, RELOCATE)
    assert (relocation.lambda_reg, relocation.relocate_opacity, relocation.max_gaussians, relocation.seed) == (
        0.25, 0.004, 321, 7)
    assert "seed" not in {f.name for f in dataclasses.fields(Densification)}  # not a setting of the strategy
    assert "seed" not in CFG.to_dict()["strategy"]


def test_the_config_holds_the_backbones_strategy_typed_and_replace_changes_it():
    assert typing.get_type_hints(TrainConfig)["strategy"] == Strategy
    assert set(typing.get_args(Strategy)) == {DensityStrategy, *STRATEGIES.values()}
    assert type(TrainConfig().strategy) is Densification
    assert type(TrainConfig(backbone="freetimegs").strategy) is Relocation
    moved = dataclasses.replace(CFG, backbone="freetimegs")  # the shared schedule and budget stay
    assert moved.strategy == Relocation(densify_from=123, densify_until=4567, densify_interval=89, max_gaussians=321)
    assert dataclasses.replace(moved, backbone="rt4dgs").strategy.densify_until == 4567
    assert dataclasses.replace(CFG, seed=8).seed == 8 and dataclasses.replace(CFG, seed=8).strategy == DENSIFY
    with pytest.raises(OMG4Error, match="unknown backbone 'nope'"):
        TrainConfig(backbone="nope")


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
