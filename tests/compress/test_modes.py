"""The paper's way is one switch away (omg4.compress.modes): README's table and the table of choices agree, the
switch restores each paper value in the config, the commands and the file, and a flag naming one choice still wins."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import pytest

from omg4.app.cli import _build_parser, main
from omg4.app.commands.compress import pipeline_config
from omg4.codec.payload import CODECS
from omg4.codec.sequence import DEFAULT_KEY_INTERVAL
from omg4.compress.modes import BY_SETTING, CHOICES, choice_value, mode_of
from omg4.compress.pipeline import CompressConfig
from omg4.settings import check_settings, settings_of

README = (Path(__file__).resolve().parents[2] / "README.md").read_text()


def readme_rows() -> dict[str, tuple[str, str]]:
    """The "Paper-faithful and beyond" table: topic → (default, the --paper column)."""
    section = README.split("## Paper-faithful and beyond", 1)[1].split("\n## ", 1)[0]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 3 and cells[0] not in ("topic", "---"):
            rows[cells[0]] = (cells[1], cells[2])
    return rows


def flags_in(text: str) -> dict[str, str]:
    """``--flag value`` pairs written in backticks."""
    return {m.group(1).replace("-", "_"): m.group(2) for m in re.finditer(r"`--([a-z-]+) ([^`\s]+)`", text)}


def test_every_row_of_readme_is_a_choice_or_a_fixed_bug_and_every_choice_has_a_row():
    rows = readme_rows()
    assert rows, "README lost its table"
    topics = {c.topic for c in CHOICES}
    for topic, (_, paper) in rows.items():
        if topic not in topics:
            assert paper.startswith("—") and "bug" in paper, f"README row '{topic}' has no entry in modes.CHOICES"
    assert topics <= set(rows), f"choices without a README row: {topics - set(rows)}"


def test_the_paper_values_readme_names_are_the_switchs():
    named = {}
    for topic, (_, paper) in readme_rows().items():
        named.update(flags_in(paper))
    assert {"codec", "score_weighting", "time_sampling", "key_interval"} <= set(named)
    for setting, text in named.items():
        assert setting in BY_SETTING, f"README names --{setting} for the paper, but it is not a choice"
        assert str(BY_SETTING[setting].paper) in (text, text + ".0"), setting


def test_the_defaults_of_the_table_are_the_code_defaults():
    cfg = CompressConfig()
    for c in CHOICES:
        if hasattr(cfg, c.setting):
            assert cfg.choice(c.setting) == c.default, c.setting
    assert BY_SETTING["codec"].default == CODECS[0]
    assert BY_SETTING["key_interval"].default == DEFAULT_KEY_INTERVAL


def test_a_knob_beyond_the_paper_has_a_paper_value():
    """A new deviation without its entry fails here: its help says it goes beyond the paper."""
    for name, s in settings_of(CompressConfig).items():
        if "beyond the paper" in s.help and name != "paper":
            assert name in BY_SETTING, f"CompressConfig.{name} goes beyond the paper but has no entry in modes.CHOICES"


def test_the_switch_sets_every_choice_of_the_config_and_explicit_values_win():
    cfg = CompressConfig(paper=True)
    for c in CHOICES:
        if hasattr(cfg, c.setting):
            assert cfg.choice(c.setting) == c.paper, c.setting
            assert getattr(cfg.resolved(), c.setting) == c.paper, c.setting
    assert cfg.mode() == "paper" and CompressConfig().mode() == "omg4" and CompressConfig(codec="compact").mode() == "omg4"
    mixed = CompressConfig(paper=True, time_sampling="deficit")
    assert mixed.choice("time_sampling") == "deficit" and mixed.choice("score_weighting") == "paper"
    assert mixed.mode() == "mixed (codec=paper, score_weighting=paper, frame_floor=0.0, carry=0.0)"
    assert mixed.mode(sequence=True) == "mixed (codec=paper, score_weighting=paper, frame_floor=0.0, key_interval=1, carry=0.0)"
    # a copy keeps what it holds, and the switch works on a copy as on a new config
    assert dataclasses.replace(cfg, seed=1).choice("time_sampling") == "uniform"
    switched = dataclasses.replace(CompressConfig(), paper=True)
    assert switched.resolved() == CompressConfig(paper=True).resolved() and switched.mode() == "paper"
    assert dataclasses.replace(mixed, paper=False).choice("time_sampling") == "deficit"  # what it set, it keeps
    assert dataclasses.replace(mixed, paper=False).choice("score_weighting") == "lifetime"
    # the coder and a sequence's key interval are settings like the others, resolved by the same method
    assert (cfg.choice("codec"), cfg.choice("key_interval")) == ("paper", 1)
    assert (CompressConfig().choice("codec"), CompressConfig().choice("key_interval")) == (CODECS[0], DEFAULT_KEY_INTERVAL)
    assert dataclasses.replace(cfg, codec="ans").mode() == "mixed (codec=ans, score_weighting=paper, frame_floor=0.0, " \
                                                        "time_sampling=uniform, carry=0.0)"
    assert check_settings(CompressConfig, {"codec": "ans", "key_interval": 4}) == {"codec": "ans", "key_interval": 4}


def test_mode_of_judges_only_the_settings_given():
    assert mode_of({"codec": "paper"}) == "paper"
    assert mode_of({"codec": "compact", "rate_weight": 0.0}) == "omg4"
    assert mode_of({"rate_weight": 0.0}) == "omg4"  # a choice whose values agree says nothing of the paper
    assert mode_of({"codec": "paper", "rate_weight": 10.0}).startswith("mixed (")


def parse(argv: list[str]):
    return _build_parser(argv[0])[0].parse_args(argv)


def _compress_args(*extra: str):
    return parse(["compress", "data", "--model", "m.safetensors", "--out", "o.omg4", *extra])


@pytest.mark.parametrize("extra,expected", [
    ((), {"score_weighting": "lifetime", "time_sampling": "deficit", "paper": False}),
    (("--paper",), {"score_weighting": "paper", "time_sampling": "uniform", "paper": True}),
    (("--paper", "--time-sampling", "deficit"), {"score_weighting": "paper", "time_sampling": "deficit"}),
    (("--set", "paper=true"), {"score_weighting": "paper", "time_sampling": "uniform"}),
])
def test_the_compress_command_takes_the_switch(extra, expected):
    from omg4.app.commands.common import settings_from_args
    from omg4.app.commands.compress import COMMAND_KEYS

    args = _compress_args(*extra)
    settings = settings_from_args(args, CompressConfig, section="compress_config", extra=COMMAND_KEYS)
    cfg = pipeline_config(args, settings, "cpu")
    for key, value in expected.items():
        assert getattr(cfg.resolved(), key) == value, key


@pytest.mark.parametrize("command", ["demo", "bench"])
def test_demo_and_bench_take_the_switch(command):
    argv = {"demo": ["demo", "--paper"], "bench": ["bench", "data", "--model", "m.safetensors", "--paper"]}[command]
    assert parse(argv).paper is True


def test_a_paper_run_writes_the_papers_file_and_says_so(tiny_scene_dir, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", str(tiny_scene_dir), "--out", str(run), "--iterations", "6", "--backend", "cpu",
                 "--preset", "cpu-small"]) == 0
    out = tmp_path / "p.omg4"
    assert main(["compress", str(tiny_scene_dir), "--model", str(run / "model.safetensors"), "--backend", "cpu",
                 "--out", str(out), "--schedule", "tiny", "--batch-size", "1", "--paper"]) == 0
    record = json.loads(out.with_name("p.omg4.config.json").read_text())
    assert record["codec"] == choice_value("codec", True) == "paper" and record["mode"] == "paper"
    assert record["compress_config"]["time_sampling"] == "uniform"
    capsys.readouterr()
    info = tmp_path / "info.json"
    assert main(["info", str(out), "--json", str(info)]) == 0
    assert "mode: paper" in capsys.readouterr().out
    assert json.loads(info.read_text())["mode"] == "paper" and json.loads(info.read_text())["codec"] == "paper"


def test_the_switch_outranks_a_records_choices_and_a_recorded_codec_can_be_overridden(tiny_scene_dir, tmp_path):
    """``--config <an omg4-mode record> --paper`` is the paper's way (the record's resolved choices give way), a flag
    naming a choice still wins, and ``--config <record> --codec X`` takes X."""
    from omg4.app.commands.common import settings_from_args
    from omg4.app.commands.compress import COMMAND_KEYS, write_record
    from omg4.codec.payload import CompactGrids

    record = tmp_path / "run.omg4.config.json"
    write_record(record, CompressConfig(), "compact", CompactGrids())
    for extra, expected in ((("--paper",), ("paper", "uniform")),
                            (("--paper", "--carry", "0.5"), ("paper", "uniform")),
                            (("--paper", "--time-sampling", "deficit"), ("paper", "deficit")),
                            ((), ("lifetime", "deficit"))):
        args = _compress_args("--config", str(record), *extra)
        settings = settings_from_args(args, CompressConfig, section="compress_config", extra=COMMAND_KEYS)
        settings.pop("codec"), settings.pop("grid_bits")
        cfg = pipeline_config(args, settings, "cpu")
        assert (cfg.choice("score_weighting"), cfg.choice("time_sampling")) == expected, extra
        if "--carry" in extra:
            assert cfg.choice("carry") == 0.5
    run = tmp_path / "r"
    assert main(["train", str(tiny_scene_dir), "--out", str(run), "--iterations", "4", "--backend", "cpu",
                 "--preset", "cpu-small"]) == 0
    out = tmp_path / "x.omg4"
    assert main(["compress", str(tiny_scene_dir), "--model", str(run / "model.safetensors"), "--backend", "cpu",
                 "--out", str(out), "--schedule", "tiny", "--batch-size", "1", "--config", str(record),
                 "--codec", "ans"]) == 0
    assert json.loads(out.with_name("x.omg4.config.json").read_text())["codec"] == "ans"
