"""The OMG4 stage schedule (paper §5.1 "Implementation Details"; omg4 §2).

Stages run at fixed iterations and the model is fine-tuned with the baseline loss in
between: sampling at 0, pruning at T_GS, M merge rounds every T_GM, MLP appearance, then
SVQ of the 3D attributes and, T_3D later, of the 4D attributes. Ablations drop stages or
apply sampling and pruning at once (paper Tab. 4).
"""

from __future__ import annotations

from dataclasses import dataclass

from omg4.errors import OMG4Error
from omg4.settings import knob

STAGE_NAMES = ("sample", "prune", "sample+prune", "merge", "appearance", "svq3d", "svq4d")
MINIMIZING_STAGES = ("sample", "prune", "sample+prune", "merge")
"""The stages that only remove or merge Gaussians: after them the model is still a baseline
model, written as a checkpoint by ``omg4 compress --stop-after``."""


@dataclass(frozen=True)
class StageLengths:
    """Fine-tuning iterations after each stage (official: 1000 each, 5000 for the MLPs)."""

    sample: int = knob(1000, "fine-tuning iterations after sampling")
    prune: int = knob(1000, "fine-tuning iterations after pruning")
    merge: int = knob(1000, "fine-tuning iterations after each merge round")
    appearance: int = knob(5000, "fine-tuning iterations after the switch to MLP appearance")
    svq3d: int = knob(1000, "fine-tuning iterations after SVQ of the 3D attributes")
    svq4d: int = knob(1000, "fine-tuning iterations after SVQ of the 4D attributes")

    def scaled(self, factor: float, minimum: int = 10) -> "StageLengths":
        return StageLengths(**{k: max(minimum, int(round(v * factor))) for k, v in self.__dict__.items()})


SCHEDULES: dict[str, StageLengths] = {
    "official": StageLengths(),
    # a 2-core laptop on a small scene: a fifth of every stage
    "cpu": StageLengths().scaled(0.2),
    # the demo and quick benchmarks: a tenth of each stage, 600 MLP iterations
    "short": StageLengths(sample=100, prune=100, merge=100, appearance=600, svq3d=100, svq4d=100),
    # smoke tests
    "tiny": StageLengths(sample=4, prune=4, merge=4, appearance=8, svq3d=4, svq4d=4),
}


def default_schedule(device: object) -> str:
    """The fine-tuning lengths a command uses when none is named: the paper's (``official``) on a
    CUDA device, a fifth of them (``cpu``) anywhere else."""
    return "official" if str(device).startswith("cuda") else "cpu"


@dataclass(frozen=True)
class Event:
    """Stage ``name`` applied before iteration ``iteration`` + 1 (``round`` counts merge rounds)."""

    iteration: int
    name: str
    round: int = 0


def build_events(stages: tuple[str, ...], lengths: StageLengths, num_merge: int = 2) -> tuple[list[Event], int]:
    """The ordered events of a pipeline and its total fine-tuning iterations.

    ``stages`` lists stage names in order; ``"merge"`` expands to ``num_merge`` rounds.
    """
    events: list[Event] = []
    it = 0
    for name in stages:
        if name not in STAGE_NAMES:
            raise OMG4Error(f"unknown stage '{name}' (known: {', '.join(STAGE_NAMES)})")
        if name == "merge":
            for r in range(num_merge):
                events.append(Event(it, "merge", r))
                it += lengths.merge
            continue
        events.append(Event(it, name))
        it += getattr(lengths, "prune" if name == "sample+prune" else name)
    return events, it
