"""The stage schedule places events at the paper's iterations."""

import pytest

from omg4.compress.schedule import SCHEDULES, StageLengths, build_events
from omg4.errors import OMG4Error


def test_official_schedule_matches_paper_iterations():
    events, total = build_events(("sample", "prune", "merge", "appearance", "svq3d", "svq4d"), SCHEDULES["official"])
    at = [(e.name, e.iteration) for e in events]
    # paper §5.1: pruning at 1000, merging at 2000 and 3000, MLPs at 4000, SVQ-3D at 9000, SVQ-4D at 10000
    assert at == [("sample", 0), ("prune", 1000), ("merge", 2000), ("merge", 3000), ("appearance", 4000),
                  ("svq3d", 9000), ("svq4d", 10000)]
    assert total == 11000


def test_ablation_without_pruning_and_merging():
    events, total = build_events(("sample", "appearance", "svq3d", "svq4d"), StageLengths())
    assert [(e.name, e.iteration) for e in events] == [("sample", 0), ("appearance", 1000), ("svq3d", 6000),
                                                         ("svq4d", 7000)]
    assert total == 8000


def test_unknown_stage_is_a_clear_error():
    with pytest.raises(OMG4Error, match="unknown stage"):
        build_events(("sample", "magic"), StageLengths())
