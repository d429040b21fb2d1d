"""The density controls' settings nested in the training config (``strategy``): made from the strategies' own
fields, reachable by config files, ``--set strategy.<field>=…`` and flags; the earlier flat names still read, each
with one deprecation line; records written with flat names still resume."""

from __future__ import annotations

import dataclasses
import json
import logging

import pytest

from omg4.app.cli import main
from omg4.settings import check_settings, settings_of
from omg4.train.config import TrainConfig, make_config
from omg4.train.resume import recorded_config
from omg4.train.strategies import STRATEGIES, DensityStrategy, StrategySettings, settings_class
from omg4.train.strategies.densification import Densification
from omg4.train.strategies.relocation import Relocation


@pytest.fixture
def told(caplog, monkeypatch):
    """The deprecation lines logged inside the test (each name told afresh)."""
    import omg4.settings

    monkeypatch.setattr(omg4.settings, "_told", set())
    caplog.set_level(logging.WARNING, logger="omg4")
    return lambda: [r.getMessage() for r in caplog.records if "deprecated" in r.getMessage()]


def test_every_field_of_every_strategy_is_one_setting_with_its_own_default_and_help():
    table = settings_of(TrainConfig)
    for cls in (DensityStrategy, *STRATEGIES.values()):
        for f in dataclasses.fields(cls):
            if f.name == "seed":  # the run's own
                assert f"strategy.{f.name}" not in table
                continue
            setting = table[f"strategy.{f.name}"]
            assert setting.default == f.default and setting.help == f.metadata["help"] != ""
    assert table["strategy.lambda_reg"].default == Relocation().lambda_reg == 0.01
    assert table["strategy.prune_opacity"].default == Densification().prune_opacity == 0.005
    assert not any(name in table for name in ("densify_until", "max_gaussians", "lambda_reg"))


def test_a_strategy_brings_its_settings_and_a_clash_of_defaults_is_refused():
    @dataclasses.dataclass
    class Mine(DensityStrategy):
        every: int = dataclasses.field(default=3, metadata={"help": "steps between my events"})

    made = settings_class([DensityStrategy, Mine])
    assert made().every == 3 and made().max_gaussians == 0

    @dataclasses.dataclass
    class Clashing(DensityStrategy):
        max_gaussians: int = 7

    with pytest.raises(TypeError, match="Clashing.max_gaussians"):
        settings_class([DensityStrategy, Clashing])


def test_flat_names_read_from_settings_with_one_deprecation_line_and_the_config_is_a_plain_dataclass(told):
    assert check_settings(TrainConfig, {"densify_until": 4, "iterations": 3}) == {"strategy.densify_until": 4,
                                                                                  "iterations": 3}
    assert told() == ["the setting 'densify_until' is now 'strategy.densify_until'; the old name is deprecated"]
    with pytest.raises(TypeError):  # the dataclass's own constructor: the nested settings are a field
        TrainConfig(densify_until=5)
    with pytest.raises(AttributeError):
        TrainConfig().densify_until
    nested = TrainConfig(strategy=StrategySettings(densify_until=5, max_gaussians=9))
    assert dataclasses.replace(TrainConfig(), strategy=nested.strategy) == nested
    assert TrainConfig.__init__.__qualname__ == "TrainConfig.__init__"


def test_make_config_takes_the_strategy_settings_by_name_nested_or_dotted(told):
    by_name = make_config("cpu-small", iterations=300, densify_until=77)
    assert by_name == make_config("cpu-small", iterations=300, strategy={"densify_until": 77})
    assert by_name == make_config("cpu-small", {"iterations": 300, "strategy.densify_until": 77})
    assert by_name.strategy.densify_until == 77 and by_name.strategy.densify_from == 15  # the rest scaled
    assert told() == []


def test_a_record_with_flat_settings_resumes_as_the_nested_config(tmp_path, told):
    cfg = make_config("cpu-small", iterations=30, densify_until=20, lambda_reg=0.5)
    flat = {k: v for k, v in cfg.to_dict().items() if k != "strategy"} | cfg.to_dict()["strategy"]
    (tmp_path / "config.json").write_text(json.dumps({"train_config": flat, "preset": "cpu-small"}))
    assert recorded_config(tmp_path) == cfg
    (tmp_path / "config.json").write_text(json.dumps({"train_config": cfg.to_dict(), "preset": "cpu-small"}))
    assert recorded_config(tmp_path) == cfg
    assert told() == []  # a record is not the user's writing


def test_the_commands_take_the_nested_the_flat_and_the_earlier_flag_forms(tiny_scene_dir, tmp_path, capsys, told):
    def trained(name, *extra):
        run = tmp_path / name
        assert main(["train", str(tiny_scene_dir), "--out", str(run), "--iterations", "2", "--backend", "cpu",
                     *extra]) == 0
        return json.loads((run / "config.json").read_text())["train_config"]["strategy"]

    assert trained("nested", "--set", "strategy.prune_opacity=0.02")["prune_opacity"] == 0.02
    assert trained("flag", "--strategy-prune-opacity", "0.03")["prune_opacity"] == 0.03
    assert told() == []
    assert trained("flat", "--set", "prune_opacity=0.04")["prune_opacity"] == 0.04
    assert trained("old-flag", "--lambda-reg", "0.5")["lambda_reg"] == 0.5
    assert [m.split("'")[1] for m in told()] == ["prune_opacity", "lambda_reg"]
    config = tmp_path / "settings.toml"
    config.write_text("iterations = 2\n[strategy]\nrelocate_opacity = 0.2\n")
    assert trained("file", "--config", str(config))["relocate_opacity"] == 0.2
    capsys.readouterr()
    assert main(["train", str(tiny_scene_dir), "--out", str(tmp_path / "bad"), "--set", "strategy.prune=1"]) == 2
    assert "did you mean strategy.prune_opacity" in capsys.readouterr().err
