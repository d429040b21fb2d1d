"""The README works as written: its Python example runs, every ``omg4`` command it shows parses, it stays short."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def code_blocks(language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", README, flags=re.S)


def test_the_readme_is_short():
    assert len(README.splitlines()) <= 300


def test_the_python_example_runs(tmp_path, monkeypatch, capsys):
    (example,) = [block for block in code_blocks("python") if "import omg4" in block]
    monkeypatch.chdir(tmp_path)
    exec(compile(example, "README.md", "exec"), {})
    psnr = float(capsys.readouterr().out.strip().splitlines()[-1])
    assert 20.0 < psnr < 40.0  # a believable figure: the README says about 23.1 dB
    assert (tmp_path / "scene_M.omg4").stat().st_size < 200_000 and (tmp_path / "run" / "model.safetensors").exists()


def readme_commands() -> list[list[str]]:
    """Every ``omg4 …`` command line of the README's shell blocks (continuations joined, comments dropped)."""
    commands = []
    for block in code_blocks("bash"):
        text = re.sub(r"\\\n\s*", " ", block)
        for line in text.splitlines():
            for part in line.split("  #")[0].split("&&"):
                part = part.strip()
                if part.startswith("omg4 ") or " -m omg4 " in part:  # also what torchrun starts
                    commands.append(shlex.split(part.replace("$DATA", "DATA").split("omg4 ", 1)[1]))
    return commands


def test_there_is_an_example_of_every_command():
    from omg4.app.cli import COMMANDS

    shown = {argv[0] for argv in readme_commands()}
    assert shown == set(COMMANDS)


@pytest.mark.parametrize("argv", readme_commands(), ids=lambda argv: " ".join(argv)[:60])
def test_every_command_in_the_readme_parses(argv):
    from omg4.app.cli import _build_parser

    parser, _ = _build_parser(argv[0])
    args = parser.parse_args(argv)
    assert args.command == argv[0]
