"""The paper's way, one switch away: every choice where omg4's default goes beyond OMG4 (the paper, ICLR 2026).

:data:`CHOICES` is the one table of those choices: the setting that holds each (a
:class:`~omg4.compress.pipeline.CompressConfig` field, or an option of the compression beside it: the coder and a
sequence's key interval), its value in the paper and omg4's default. ``CompressConfig(paper=True)`` — ``--paper``
in ``omg4 compress``, ``demo`` and ``bench``, ``paper = true`` in a config file — takes the paper's value of every
choice not set explicitly; :func:`mode_of` names the mode a run's settings amount to, and the compressed file's
header and every result record carry it. A choice beyond the paper is added here, with a row in README's
"Paper-faithful and beyond" table (``tests/compress/test_modes.py`` holds the two together).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from omg4.codec.payload import CODECS
from omg4.codec.sequence import DEFAULT_KEY_INTERVAL


@dataclass(frozen=True)
class Choice:
    """One algorithmic choice: ``setting`` (a config field or a compression option), the ``paper`` value (the
    paper's equations and the official code's algorithm, without its bugs), omg4's ``default``, and the ``topic``
    (its row in README's table)."""

    setting: str
    paper: Any
    default: Any
    topic: str


CHOICES: tuple[Choice, ...] = (
    Choice("codec", "paper", CODECS[0], "file coding"),
    Choice("rate_weight", 0.0, 0.0, "codebooks"),
    Choice("score_weighting", "paper", "lifetime", "sampling and pruning"),
    Choice("frame_floor", 0.0, 0.02, "sampling and pruning"),
    Choice("time_sampling", "uniform", "deficit", "fine-tuning views"),
    Choice("key_interval", 1, DEFAULT_KEY_INTERVAL, "segments of a long capture"),
    Choice("carry", 0.0, "auto", "segments of a long capture"),
)
"""Every choice with a paper's value; the codebooks' rate weight already defaults to it (the paper's k-means). The dynamic SD score is the paper's Σ_j ∂L_j/∂t in both modes (the official code's
running sum, ``official_score_quirk``, is a bug kept only as a parity flag)."""

BY_SETTING: dict[str, Choice] = {c.setting: c for c in CHOICES}

MODES = ("omg4", "paper")
"""The two modes: omg4's defaults, or the paper's way."""


def choice_value(setting: str, paper: bool) -> Any:
    """The value of ``setting`` in the paper's way (``paper``) or by omg4's default."""
    c = BY_SETTING[setting]
    return c.paper if paper else c.default


def choices_of(config) -> dict[str, Any]:
    """The values of the choices in the run ``config`` (a :class:`~omg4.compress.pipeline.CompressConfig`) makes."""
    return {c.setting: config.choice(c.setting) for c in CHOICES if hasattr(config, c.setting)}


def mode_of(values: dict[str, Any]) -> str:
    """The mode a run's ``values`` (setting → value; settings not given are left out of the judgement) amount to:
    ``"paper"`` when each is the paper's, ``"omg4"`` when each is omg4's default (the choices whose two values
    agree count for both), else ``"mixed (setting=value, …)"`` naming those that differ from omg4's default."""
    given = [c for c in CHOICES if c.setting in values]
    if all(values[c.setting] == c.paper for c in given):
        return "paper" if any(c.paper != c.default for c in given) else "omg4"
    if all(values[c.setting] == c.default for c in given):
        return "omg4"
    changed = ", ".join(f"{c.setting}={values[c.setting]}" for c in given if values[c.setting] != c.default)
    return f"mixed ({changed})"


__all__ = ["Choice", "CHOICES", "BY_SETTING", "MODES", "choice_value", "choices_of", "mode_of"]
