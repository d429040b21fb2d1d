"""Which Gaussians a predicted segment carries: the time distance in the backbone's own terms (√Σtt of the 4D
covariance, checked against the covariance built here from its rotation and scales), and ``auto``'s decision from
the share that matches."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from omg4.compress.carry_stage import AUTO_MIN_SHARE, AUTO_TOLERANCE, carry_matches, chosen_carry, valid_setting
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


def sigma_tt(values: dict, convention: str) -> torch.Tensor:
    """Σtt of rt4dgs's 4D covariance R diag(s²) Rᵀ, from the rotation and the log scales (spatial, then time)."""
    rotation = build_rotation_4d(torch.nn.functional.normalize(values["rotation"], dim=-1),
                                 torch.nn.functional.normalize(values["rotation_r"], dim=-1), convention).double()
    scales = torch.cat([values["scaling"], values["scaling_t"]], dim=1).double().exp()
    return (rotation[:, 3, :] ** 2 * scales ** 2).sum(dim=1)


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


@pytest.mark.parametrize("backbone", ["rt4dgs", "freetimegs"])
def test_auto_carries_where_enough_gaussians_match_and_a_number_is_taken_as_given(backbone):
    m = model(backbone)
    own = values_of(m)
    n = len(own["xyz"])
    moved = {k: v.clone() for k, v in own.items()}
    few = max(1, int(AUTO_MIN_SHARE * n) - 1)  # just under the share: every other Gaussian far away
    moved["xyz"][few:] += 100.0
    tolerance, share, (rows, _) = chosen_carry(own, own, m.config, "auto")
    assert (tolerance, share) == (AUTO_TOLERANCE, 1.0) and sorted(rows.tolist()) == list(range(n))
    tolerance, share, (rows, _) = chosen_carry(own, moved, m.config, "auto")
    assert share == pytest.approx(few / n) and share < AUTO_MIN_SHARE and tolerance == 0.0 and len(rows) == 0
    enough = {k: v.clone() for k, v in own.items()}
    enough["xyz"][few + 2:] += 100.0
    tolerance, share, (rows, _) = chosen_carry(own, enough, m.config, "auto")
    assert share >= AUTO_MIN_SHARE and tolerance == AUTO_TOLERANCE and len(rows) == few + 2
    tolerance, share, (rows, _) = chosen_carry(own, moved, m.config, 0.7)
    assert (tolerance, share, len(rows)) == (0.7, None, few)
    tolerance, share, (rows, _) = chosen_carry(own, own, m.config, 0)
    assert (tolerance, share, len(rows)) == (0.0, None, 0)


def test_only_auto_or_a_finite_tolerance_is_a_setting():
    assert valid_setting("auto") and valid_setting(0) and valid_setting(0.5)
    assert not any(valid_setting(v) for v in ("often", -0.1, float("nan"), float("inf"), True, None))


def test_the_config_carries_none_unless_told_and_takes_auto_or_a_tolerance():
    from omg4.compress.pipeline import CompressConfig

    assert CompressConfig().carry == 0.0 and CompressConfig(paper=True).carry == 0.0
    assert CompressConfig(carry="auto").carry == "auto"
    assert dataclasses.replace(CompressConfig(carry=0.25), seed=3).carry == 0.25
