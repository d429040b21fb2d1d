"""The command line offers exactly what the library's tables hold, with the library's defaults.

Every option with a fixed set of values takes it from a library table; these tests fail
when a table gains (or loses) an entry the CLI does not offer, or when an option with
choices appears that no table backs.
"""

from __future__ import annotations

import argparse

import pytest

from omg4.compress.modes import choice_value
from omg4.kernels import KERNEL_MODES

from omg4.app.cli import COMMANDS, _build_parser
from omg4.codec.coders import CODERS
from omg4.compress.appearance_stage import PREDICTED_MLPS
from omg4.compress.pipeline import FULL_STAGES, CompressConfig
from omg4.compress.schedule import MINIMIZING_STAGES, SCHEDULES
from omg4.compress.score import SCORE_WEIGHTINGS
from omg4.compress.time_balance import TIME_SAMPLINGS
from omg4.data.readers import READERS
from omg4.data.scene import SPLITS
from omg4.gaussians.backbone import BACKBONES
from omg4.gaussians.model import SH_DIRECTIONS
from omg4.io import EXPORT_FOLDERS, EXPORT_FORMATS
from omg4.render.paths import PATHS
from omg4.render.rendered import BACKENDS
from omg4.train.config import PRESETS
from omg4.train.init import INIT_MODES
from omg4.train.segmented import PARALLEL_MODES

SCENE = {"--format": READERS}
DEVICE = {"--backend": BACKENDS, "--kernels": KERNEL_MODES}
TABLES: dict[str, dict[str, object]] = {
    "demo": {"--codec": CODERS, "--kernels": KERNEL_MODES},
    "synth": {},
    "prepare": {},
    "info": {**SCENE},
    "train": {**SCENE, **DEVICE, "--backbone": BACKBONES, "--preset": PRESETS, "--init": INIT_MODES,
              "--parallel": PARALLEL_MODES},
    "import-rt4dgs": {"--sh-direction": SH_DIRECTIONS},
    "compress": {**SCENE, **DEVICE, "--schedule": SCHEDULES, "--stop-after": MINIMIZING_STAGES, "--codec": CODERS,
                 "--score-weighting": SCORE_WEIGHTINGS, "--time-sampling": TIME_SAMPLINGS,
                 "--predicted-mlp": PREDICTED_MLPS,
                 "--preset": {name for b in BACKBONES.values() for name in b.size_presets}},
    "eval": {**SCENE, **DEVICE, "--split": SPLITS},
    "render": {**SCENE, **DEVICE},  # --path: a name of PATHS or a camera path file (test_render_path_names)
    "export": {"--format": set(EXPORT_FORMATS.values()) | set(EXPORT_FOLDERS)},
    "view": {**SCENE, **DEVICE},
    "bench": {**SCENE, **DEVICE, "--schedule": SCHEDULES, "--codec": CODERS},
}


def _subparser(command: str) -> argparse.ArgumentParser:
    parser, _ = _build_parser(command)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[command]


def _options_with_choices(command: str) -> dict[str, argparse.Action]:
    return {a.option_strings[-1]: a for a in _subparser(command)._actions if a.choices is not None and a.option_strings}


def test_every_command_is_covered():
    assert set(TABLES) == set(COMMANDS)


@pytest.mark.parametrize("command", sorted(TABLES))
def test_choices_are_the_library_tables(command):
    offered = _options_with_choices(command)
    assert set(offered) == set(TABLES[command]), "an option with choices that no library table backs, or one missing"
    for flag, table in TABLES[command].items():
        assert set(offered[flag].choices) == set(table), f"omg4 {command} {flag}"


@pytest.mark.parametrize("command", ["compress", "bench"])
def test_fine_tuning_defaults_are_the_library_defaults(command):
    actions = {a.option_strings[-1]: a for a in _subparser(command)._actions if a.option_strings}
    assert actions["--schedule"].default is None  # omg4.compress.schedule.default_schedule decides, per device
    if command == "bench":
        assert actions["--batch-size"].default == CompressConfig.batch_size
        assert actions["--baseline-iterations"].default is None  # the checkpoint's, else the library's
        # unset, the mode's coder: omg4's default, or the paper's with --paper (omg4.compress.modes)
        assert actions["--codec"].default is None and choice_value("codec", False) == next(iter(CODERS))
        assert actions["--rate-weights"].default == (CompressConfig.rate_weight,)
        return
    # compress leaves its flags unset so that a config file can set them; unset, the run takes the library's
    assert all(actions[f].default is None for f in ("--batch-size", "--baseline-iterations", "--codec", "--seed",
                                                    "--num-merge", "--stages", "--device", "--backend", "--rate-weight"))
    assert _compress_config([]) == CompressConfig(schedule="cpu", device="cpu")
    assert _compress_config(["--stages", "sample,appearance", "--seed", "3"]) == CompressConfig(
        schedule="cpu", device="cpu", stages=("sample", "appearance"), seed=3)


def _compress_config(flags: list[str]) -> CompressConfig:
    """The CompressConfig ``omg4 compress`` runs with these flags and no config file, on the CPU."""
    import torch

    from omg4.app.commands.common import fill_device_arguments
    from omg4.app.commands.compress import pipeline_config

    parser, _ = _build_parser("compress")
    args = parser.parse_args(["compress", "DATA", "--model", "M", "--out", "F", *flags])
    fill_device_arguments(args, {})
    return pipeline_config(args, {}, torch.device("cpu"))


def test_compress_stages_default_is_the_full_pipeline():
    assert _compress_config([]).stages == FULL_STAGES
    assert CompressConfig().seed == 6666 and CompressConfig().num_merge == 2


@pytest.mark.parametrize("argv", [["train", "DATA", "--out", "RUN"], ["compress", "DATA", "--model", "M", "--out", "F"],
                                  ["eval", "DATA", "--model", "M"], ["render", "--model", "M", "--data", "DATA",
                                                                     "--out", "x.png"]])
def test_white_background_reaches_the_reader(argv, monkeypatch):
    """``--white-background`` composites the data's RGBA images over white, the colour the command renders on."""
    import omg4.data

    from omg4.app.commands.common import background_from_args, load_scene_from_args

    seen = {}
    monkeypatch.setattr(omg4.data, "load_scene", lambda *a, **kw: seen.update(kw))
    parser, _ = _build_parser(argv[0])
    for extra, colour in (([], (0.0, 0.0, 0.0)), (["--white-background"], (1.0, 1.0, 1.0))):
        args = parser.parse_args(argv + extra)
        load_scene_from_args(args)
        assert seen["background"] == colour == background_from_args(args)


def test_render_path_names_are_the_library_table():
    from omg4.app.commands.render import camera_path_source

    assert all(camera_path_source(name) == name for name in PATHS)
    assert camera_path_source("tour.json") == "tour.json"
    with pytest.raises(argparse.ArgumentTypeError, match=", ".join(PATHS)):
        camera_path_source("helix")


def test_info_prints_a_carry_decision_of_this_build_and_of_an_earlier_one_and_ignores_a_forged_one():
    from omg4.app.commands.info import _carry_decision

    assert _carry_decision({"setting": "auto", "carried": "lasting", "gaussians": 991, "covered_share": 0.2121}) == (
        "; carry auto: 21.2 % covered by lasting Gaussians, the lasting ones carried")
    assert _carry_decision({"setting": "auto", "carried": "none", "gaussians": 0, "covered_share": 0.05}) == (
        "; carry auto: 5.0 % covered by lasting Gaussians, none carried")
    assert _carry_decision({"setting": "auto", "tolerance": 0.5, "matched_share": 0.1074}) == (
        "; carry auto: 10.7 % matched, carried within 0.5")
    assert _carry_decision({"setting": "auto", "tolerance": 0.0, "matched_share": 0.024}) == (
        "; carry auto: 2.4 % matched, none carried")
    for forged in (None, [], {"covered_share": "many"}, {"matched_share": True, "tolerance": 1}, {"setting": "auto"}):
        assert _carry_decision(forged) == ""
    assert "\x1b" not in _carry_decision({"setting": "\x1b[2J", "carried": "none", "covered_share": 0.5})


@pytest.mark.parametrize("command", sorted(TABLES))
def test_help_shows_at_most_thirty_options(command):
    shown = [a for a in _subparser(command)._actions
             if a.option_strings and a.help is not argparse.SUPPRESS]
    assert len(shown) <= 30, [a.option_strings[0] for a in shown]


@pytest.mark.parametrize("command, config_class", [("train", "TrainConfig"), ("compress", "CompressConfig")])
def test_settings_lists_every_setting_that_set_takes(command, config_class, capsys):
    import omg4.compress.pipeline
    import omg4.train.config
    from omg4.settings import check_settings, settings_of

    cls = getattr(omg4.train.config, config_class, None) or getattr(omg4.compress.pipeline, config_class)
    with pytest.raises(SystemExit) as done:
        _build_parser(command)[0].parse_args([command, "--settings"])
    assert done.value.code == 0
    listed = [line.split()[0] for line in capsys.readouterr().out.splitlines()[1:]]
    assert listed == list(settings_of(cls))
    for name, setting in settings_of(cls).items():  # each is a name --set takes, with the field's default
        if setting.default is not None:
            assert check_settings(cls, {name: setting.default}) == {name: setting.default}
