"""The density controls' settings nested in the training config (``strategy``): the backbone's strategy's own
fields, reachable by config files, ``--set strategy.<field>=…`` and flags; another strategy's setting is a one-line
error; the earlier flat names still read, each with one deprecation line; records of every earlier form still
resume."""

from __future__ import annotations

import dataclasses
import json
import logging

import pytest

from omg4.app.cli import main
from omg4.errors import OMG4Error
from omg4.settings import check_settings, settings_of
from omg4.train.config import TrainConfig, make_config
from omg4.train.resume import recorded_config
from omg4.train.strategies import STRATEGIES, DensityStrategy
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
            setting = table[f"strategy.{f.name}"]
            assert setting.default == f.default and setting.help == f.metadata["help"] != ""
    assert table["strategy.lambda_reg"].default == Relocation().lambda_reg == 0.01
    assert table["strategy.prune_opacity"].default == Densification().prune_opacity == 0.005
    assert not any(name in table for name in ("densify_until", "max_gaussians", "lambda_reg", "strategy.seed"))


def test_a_setting_of_another_backbones_strategy_is_a_one_line_error(tiny_scene_dir, tmp_path, capsys):
    with pytest.raises(OMG4Error, match="strategy is Densification, which has no setting strategy.lambda_reg"):
        make_config("cpu-small", {"strategy.lambda_reg": 0.3})
    assert make_config("cpu-small", {"strategy.lambda_reg": 0.3, "backbone": "freetimegs"}).strategy.lambda_reg == 0.3
    assert main(["train", str(tiny_scene_dir), "--out", str(tmp_path / "run"), "--set", "strategy.lambda_reg=0.3"]) == 2
    err = capsys.readouterr().err
    assert "has no setting strategy.lambda_reg" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "run" / "config.json").exists()


def test_flat_names_read_from_settings_with_one_deprecation_line_and_the_config_is_a_plain_dataclass(told):
    assert check_settings(TrainConfig, {"densify_until": 4, "iterations": 3}) == {"strategy.densify_until": 4,
                                                                                  "iterations": 3}
    assert told() == ["the setting 'densify_until' is now 'strategy.densify_until'; the old name is deprecated"]
    with pytest.raises(TypeError):  # the dataclass's own constructor: the nested settings are a field
        TrainConfig(densify_until=5)
    with pytest.raises(AttributeError):
        TrainConfig().densify_until
    nested = TrainConfig(strategy=Densification(densify_until=5, max_gaussians=9))
    assert dataclasses.replace(TrainConfig(), strategy=nested.strategy) == nested
    assert TrainConfig.__init__.__qualname__ == "TrainConfig.__init__"


def test_make_config_takes_the_strategy_settings_by_name_nested_or_dotted(told):
    by_name = make_config("cpu-small", iterations=300, densify_until=77)
    assert by_name == make_config("cpu-small", iterations=300, strategy={"densify_until": 77})
    assert by_name == make_config("cpu-small", {"iterations": 300, "strategy.densify_until": 77})
    assert by_name.strategy.densify_until == 77 and by_name.strategy.densify_from == 15  # the rest scaled
    assert told() == []


def test_records_of_every_earlier_form_resume_as_the_typed_config(tmp_path, told):
    cfg = make_config("cpu-small", iterations=30, densify_until=20, lambda_reg=0.5, backbone="freetimegs")
    flat = {k: v for k, v in cfg.to_dict().items() if k != "strategy"} | cfg.to_dict()["strategy"]
    (tmp_path / "config.json").write_text(json.dumps({"train_config": flat, "preset": "cpu-small"}))
    assert recorded_config(tmp_path) == cfg
    (tmp_path / "config.json").write_text(json.dumps({"train_config": cfg.to_dict(), "preset": "cpu-small"}))
    assert recorded_config(tmp_path) == cfg
    union = {"max_gaussians": 900, "densify_from": 15, "densify_until": 20, "densify_interval": 100,  # every strategy's
             "densify_grad_threshold": 0.0002, "percent_dense": 0.01, "prune_opacity": 0.005, "prune_world_size": 0.1,
             "prune_screen_size": 20.0, "opacity_reset_interval": 10, "lambda_reg": 0.5, "relocate_opacity": 0.05}
    schedule = dict(max_gaussians=900, densify_from=15, densify_until=20, densify_interval=100)
    for backbone, kept in (("freetimegs", Relocation(**schedule, lambda_reg=0.5, relocate_opacity=0.05)),
                           ("rt4dgs", Densification(**schedule, opacity_reset_interval=10))):
        record = {**cfg.to_dict(), "backbone": backbone, "strategy": union}
        (tmp_path / "config.json").write_text(json.dumps({"train_config": record, "preset": "cpu-small"}))
        assert recorded_config(tmp_path).strategy == kept
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
    assert trained("old-flag", "--lambda-reg", "0.5", "--backbone", "freetimegs")["lambda_reg"] == 0.5
    assert [m.split("'")[1] for m in told()] == ["prune_opacity", "lambda_reg"]
    config = tmp_path / "settings.toml"
    config.write_text('iterations = 2\nbackbone = "freetimegs"\n[strategy]\nrelocate_opacity = 0.2\n')
    assert trained("file", "--config", str(config))["relocate_opacity"] == 0.2
    capsys.readouterr()
    assert main(["train", str(tiny_scene_dir), "--out", str(tmp_path / "bad"), "--set", "strategy.prune=1"]) == 2
    assert "did you mean strategy.prune_opacity" in capsys.readouterr().err
