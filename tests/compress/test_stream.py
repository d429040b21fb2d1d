"""Which Gaussians a predicted segment carries: the time distance in the backbone's own terms (√Σtt of the 4D
covariance, checked against the covariance built here from its rotation and scales), which Gaussians last through a
segment, the base layer of lasting ones and what it covers, and ``auto``'s decision from the share it covers."""

from __future__ import annotations

import dataclasses

import pytest
import torch

import numpy as np

from omg4.compress.stream import (AUTO_MIN_COVERED, COVER, LASTING_MARGINAL, STILL, base_layer, carry_matches,
                                  chosen_carry, lasting, valid_setting)
from omg4.gaussians import GaussianConfig, Gaussians4D
from omg4.gaussians.rotation import build_rotation_4d


def model(backbone: str, n: int = 40, seed: int = 0) -> Gaussians4D:
    g = torch.Generator().manual_seed(seed)
    config = GaussianConfig(time_range=(0.0, 2.0), backbone=backbone, sh_degree_t=2 if backbone == "rt4dgs" else 0)
    m = Gaussians4D.from_points(torch.rand(n, 3, generator=g) * 4 - 2, torch.rand(n, 3, generator=g), config,
                                generator=g)
    for name in ("rotation", "rotation_r"):
        if name in m.params:
            m.params[name] = m.params[name] + 0.4 * torch.randn(m.params[name].shape, generator=g)
    return m


def values_of(m: Gaussians4D) -> dict[str, torch.Tensor]:
    """The per-Gaussian values a compressing model holds at the carry (the SH base colour as its static
    appearance features)."""
    values = {k: v.detach().clone() for k, v in m.params.items()}
    values["f_static"] = values.pop("features_dc").reshape(len(values["xyz"]), -1)
    return values


def covariance_4d(values: dict, convention: str) -> torch.Tensor:
    """rt4dgs's 4D covariance R diag(s²) Rᵀ [N, 4, 4], from the rotation and the log scales (spatial, then time)."""
    rotation = build_rotation_4d(torch.nn.functional.normalize(values["rotation"], dim=-1),
                                 torch.nn.functional.normalize(values["rotation_r"], dim=-1), convention).double()
    scales = torch.cat([values["scaling"], values["scaling_t"]], dim=1).double().exp()
    return rotation @ torch.diag_embed(scales ** 2) @ rotation.transpose(1, 2)


def sigma_tt(values: dict, convention: str) -> torch.Tensor:
    """Σtt of rt4dgs's 4D covariance."""
    return covariance_4d(values, convention)[:, 3, 3]


def test_the_time_distance_is_in_units_of_the_4d_covariances_time_deviation():
    m = model("rt4dgs")
    own = values_of(m)
    std = sigma_tt(own, m.config.rotation_convention).sqrt()
    assert not torch.allclose(std, own["scaling_t"].double().exp().reshape(-1), rtol=0.05)  # the rotation mixes in
    reference = {k: v.clone() for k, v in own.items()}
    reference["t"] = reference["t"] + (0.3 * std).float().reshape(reference["t"].shape)  # 0.3 deviations later
    matched, _ = carry_matches(own, reference, m.config, 0.31)
    assert len(matched) == len(own["xyz"])
    matched, _ = carry_matches(own, reference, m.config, 0.29)
    assert len(matched) == 0


def lasting_row(m: Gaussians4D) -> dict[str, torch.Tensor]:
    """``m``'s values made Gaussians that last through its whole time range, in a row 10 of their largest scale
    (1) apart."""
    own = values_of(m)
    for name in ("scaling_t", "duration"):
        if name in own:
            own[name][:] = 4.0
    own["t"][:] = 1.0
    own["xyz"] = torch.zeros(len(own["t"]), 3)
    own["xyz"][:, 0] = 10.0 * torch.arange(len(own["t"])) * COVER
    own["scaling"][:] = torch.tensor([-1.0, 0.0, -2.0])
    for name in ("rotation", "rotation_r", "velocity"):  # axis-aligned: standing still
        if name in own:
            own[name][:] = torch.tensor([1.0, 0.0, 0.0, 0.0]) if name.startswith("rotation") else 0.0
    return own


def test_a_gaussian_lasts_through_a_segment_where_its_marginal_holds_at_both_ends_and_it_stays_put():
    m = model("rt4dgs")
    own = values_of(m)
    own["scaling_t"] = own["scaling_t"] + 1.0  # time scales of about 3 s: some last through a second, some not
    cov = covariance_4d(own, m.config.rotation_convention)
    std = cov[:, 3, 3].sqrt()
    velocity = cov[:, :3, 3] / cov[:, 3, 3:]  # Σxt / Σtt: how the conditional mean moves
    a, b = 0.5, 1.5
    mu = own["t"].double().reshape(-1)
    marginal = torch.minimum(torch.exp(-0.5 * ((mu - a) / std) ** 2), torch.exp(-0.5 * ((mu - b) / std) ** 2))
    moved = velocity.norm(dim=1) * torch.maximum((mu - a).abs(), (mu - b).abs())
    size = own["scaling"].double().exp().max(dim=1).values
    expected = (marginal >= LASTING_MARGINAL) & (moved <= STILL * size)
    assert 0 < int(expected.sum()) < len(expected)  # the example has both
    assert 0 < int(((marginal >= LASTING_MARGINAL) & ~expected).sum())  # and some that last but move away
    assert np.array_equal(lasting(own, m.config, (a, b)), expected.numpy())
    long = lasting_row(m)
    assert lasting(long, m.config, (a, b)).all()
    long["scaling_t"][:] = -6.0
    long["scaling"][:] = -6.0  # a few ms at most: none lasts half a second
    assert not lasting(long, m.config, (a, b)).any()


def test_the_base_layer_studys_knobs_set_the_constants_the_lasting_rule_reads(monkeypatch):
    import runpy
    from pathlib import Path

    import omg4.compress.stream as stream

    study = runpy.run_path(str(Path(__file__).parents[2] / "benchmarks" / "studies" / "base_layer.py"))
    m = model("rt4dgs")
    own = values_of(m)
    own["scaling_t"] = own["scaling_t"] + 1.0
    before = lasting(own, m.config, (0.5, 1.5))
    for name in ("STILL", "LASTING_MARGINAL", "COVER"):
        monkeypatch.setattr(stream, name, getattr(stream, name))  # each restored after the test
    study["set_knobs"]({"STILL": 1e9})  # no limit on motion: the Gaussians that last but move away count too
    after = lasting(own, m.config, (0.5, 1.5))
    assert (after >= before).all() and after.sum() > before.sum()
    with pytest.raises(SystemExit, match="no constant NOPE"):
        study["set_knobs"]({"NOPE": 1.0})


@pytest.mark.parametrize("backbone", ["rt4dgs", "freetimegs"])
def test_the_base_layer_carries_every_lasting_gaussian_and_covers_the_own_ones_near_them(backbone):
    m = model(backbone)
    own = lasting_row(m)
    time_range = m.config.time_range
    n = len(own["xyz"])
    reference = {k: v.clone() for k, v in own.items()}
    reference["xyz"][n // 2:, 1] += 100.0  # the second half of the reference lies far from every own Gaussian
    reference["xyz"][0, 0] += 1.5 * COVER  # the first own one is half its size beyond cover
    reference["xyz"][1, 0] += 0.9 * COVER  # the second one just within
    covered, carried = base_layer(own, reference, m.config, time_range)
    assert carried.tolist() == list(range(n))  # the far ones last too: carried, for segments that show them
    assert covered.tolist() == list(range(1, n // 2))
    brief = {k: v.clone() for k, v in reference.items()}
    brief["t"][: n // 4] = -1e4  # a quarter of the reference ended long before: not carried
    assert base_layer(own, brief, m.config, time_range)[1].tolist() == list(range(n // 4, n))


@pytest.mark.parametrize("backbone", ["rt4dgs", "freetimegs"])
def test_auto_carries_the_base_layer_where_it_covers_enough_and_a_number_is_taken_as_given(backbone):
    m = model(backbone)
    own = lasting_row(m)
    n = len(own["xyz"])
    time_range = m.config.time_range
    decision = chosen_carry(own, own, m.config, "auto", time_range)
    assert (decision.kind, decision.covered, decision.ref_rows.size, decision.own_rows.size) == ("lasting", 1.0, n, n)
    assert decision.meta() == {"setting": "auto", "carried": "lasting", "gaussians": n, "covered_share": 1.0}
    few = max(1, int(AUTO_MIN_COVERED * n) - 1)  # just under the share: every other Gaussian far away
    moved = {k: v.clone() for k, v in own.items()}
    moved["xyz"][few:] += 100.0
    decision = chosen_carry(own, moved, m.config, "auto", time_range)
    assert decision.covered == pytest.approx(few / n) and decision.kind == "none" and decision.ref_rows.size == 0
    assert chosen_carry(own, moved, m.config, "lasting", time_range).kind == "lasting"  # told: carried anyway
    enough = {k: v.clone() for k, v in own.items()}
    enough["xyz"][few + 2:] += 100.0
    decision = chosen_carry(own, enough, m.config, "auto", time_range)
    assert decision.covered >= AUTO_MIN_COVERED and decision.kind == "lasting" and decision.own_rows.size == few + 2
    decision = chosen_carry(own, moved, m.config, 0.7, time_range)
    assert (decision.kind, decision.tolerance, decision.covered, decision.own_rows.size) == ("matched", 0.7, None, few)
    assert decision.meta() == {"setting": 0.7, "carried": "matched", "gaussians": few, "tolerance": 0.7}
    decision = chosen_carry(own, own, m.config, 0, time_range)
    assert (decision.kind, decision.own_rows.size, decision.ref_rows.size) == ("none", 0, 0)


def test_only_auto_or_a_finite_tolerance_is_a_setting():
    assert valid_setting("auto") and valid_setting("lasting") and valid_setting(0) and valid_setting(0.5)
    assert not any(valid_setting(v) for v in ("often", -0.1, float("nan"), float("inf"), True, None))


def test_the_config_carries_by_default_but_not_the_papers_way_and_takes_any_setting():
    from omg4.compress.pipeline import CompressConfig

    assert CompressConfig().choice("carry") == "auto" and CompressConfig(paper=True).choice("carry") == 0.0
    assert CompressConfig(carry="lasting").choice("carry") == "lasting"
    assert CompressConfig(carry="auto").choice("carry") == "auto"
    assert dataclasses.replace(CompressConfig(carry=0.25), seed=3).choice("carry") == 0.25
