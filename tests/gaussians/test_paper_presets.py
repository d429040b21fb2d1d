"""Every size preset and SVQ layout is the paper's (appendix; docs/file-format.md "Backbones and their SVQ groups"),
written out here from the text rather than read from the code."""

from __future__ import annotations

import pytest

from omg4.gaussians.backbone import backbone_named

# OMG4 appendix: b_s = 2^9, b_r = 2^13, b_f = 2^10; Real-Time4DGS's s_t 2^9 and q^l 2^13; S and T: b_s = 2^8
M = {"scale": 2**9, "rotation": 2**13, "app": 2**10, "scale_t": 2**9, "rotation_r": 2**13}
SMALL = {**M, "scale": 2**8}
# FreeTimeGS: the M codebooks for scale, rotation and appearance, 2^10 for velocity and duration, in both sizes
FTGS = {"scale": 2**9, "rotation": 2**13, "app": 2**10, "velocity": 2**10, "duration": 2**10}

PAPER = {
    ("rt4dgs", "L"): (0.4, 0.8, M), ("rt4dgs", "M"): (0.2, 0.8, M), ("rt4dgs", "S"): (0.3, 0.9, SMALL),
    ("rt4dgs", "T"): (0.25, 0.9, SMALL),  # T's τ_GS is not stated: 0.25 is inferred from Table 1's counts
    ("freetimegs", "L"): (0.7, 0.6, FTGS), ("freetimegs", "S"): (0.3, 0.4, FTGS),
}
SUB_LENGTHS = {"rt4dgs": {"scale": 1, "rotation": 2, "app": 2, "scale_t": 1, "rotation_r": 2},
               "freetimegs": {"scale": 1, "rotation": 2, "app": 2, "duration": 1, "velocity": 1}}


@pytest.mark.parametrize("backbone,size", sorted(PAPER))
def test_size_presets_are_the_papers(backbone, size):
    preset = backbone_named(backbone).size_presets[size]
    tau, quantile, codebooks = PAPER[backbone, size]
    assert (preset.tau_gs, preset.prune_quantile) == (tau, quantile)
    assert dict(preset.codebook_sizes) == codebooks
    for attribute, size_k in codebooks.items():
        assert preset.codebook(attribute) == (SUB_LENGTHS[backbone][attribute], size_k)


def test_every_preset_is_listed():
    assert {(b, s) for b in SUB_LENGTHS for s in backbone_named(b).size_presets} == set(PAPER)
