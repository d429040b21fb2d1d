"""Which density control trains which backbone: the names in the table, a class given directly, none."""

from __future__ import annotations

import dataclasses

import pytest

from omg4.errors import OMG4Error
from omg4.gaussians.backbone import FREETIMEGS, RT4DGS
from omg4.train.densify import Densification
from omg4.train.relocate import Relocation
from omg4.train.strategies import strategy_for
from omg4.train.strategy import DensityStrategy


def test_each_backbone_trains_with_its_named_density_control():
    assert type(strategy_for(RT4DGS)) is Densification
    assert type(strategy_for(FREETIMEGS)) is Relocation
    assert strategy_for(RT4DGS) is not strategy_for(RT4DGS)  # a new instance each time: state is per run


def test_a_class_is_taken_as_it_is_and_none_trains_a_fixed_set():
    class Mine(DensityStrategy):
        pass

    assert type(strategy_for(dataclasses.replace(RT4DGS, training=Mine))) is Mine
    assert type(strategy_for(dataclasses.replace(RT4DGS, training=None))) is DensityStrategy


def test_an_unknown_name_is_a_one_line_error():
    with pytest.raises(OMG4Error, match="names the density control 'densify'"):
        strategy_for(dataclasses.replace(RT4DGS, training="densify"))
