"""The backbone schema: every attribute of each backbone survives encode → decode with its declared
width and treatment (explicit fp16, sub-vector quantized, or replaced by the appearance MLPs)."""

import numpy as np
import pytest
import torch

from omg4.codec.grids import position_order
from omg4.codec.payload import CompressedPayload, QuantizedAttribute, encode_payload
from omg4.gaussians import GaussianConfig
from omg4.gaussians.appearance import AppearanceMLP
from omg4.gaussians.backbone import APPEARANCE_FEATURES, BACKBONES
from omg4.models.compact import load_omg4

WIDTH = {"xyz": 3, "t": 1}


def _config(name: str) -> GaussianConfig:
    required_t = BACKBONES[name].sh_degree_t
    return GaussianConfig(time_range=(0.0, 1.0), backbone=name,
                          **({} if required_t is None else {"sh_degree_t": required_t}))


def _payload(name: str, n: int, seed: int) -> CompressedPayload:
    rng = np.random.default_rng(seed)
    schema, config = BACKBONES[name], _config(name)
    attributes = {}
    for group in schema.svq_groups:
        width = sum(w for _, w in schema.svq_widths(group.name))
        slots = width // group.sub_length
        codebooks = [(rng.normal(size=(int(rng.integers(2, 40)), group.sub_length)) * 0.3 - 0.5).astype(np.float16)
                     for _ in range(slots)]
        attributes[group.name] = QuantizedAttribute(codebooks, [rng.integers(0, len(cb), n) for cb in codebooks])
    with torch.device("cpu"):
        mlp = AppearanceMLP(num_rest=config.num_coeffs - 1, num_inputs=schema.mlp_inputs)
    meta = {"gaussian_config": config.to_json(), "active_sh_degree": config.sh_degree,
            "active_sh_degree_t": config.sh_degree_t}
    return CompressedPayload(xyz=rng.normal(size=(n, 3)).astype(np.float32),
                             t=rng.uniform(0, 1, n).astype(np.float32), attributes=attributes,
                             mlp=mlp.to_fp16_state(), meta=meta)


@pytest.mark.parametrize("codec", ["compact", "ans", "paper"])
@pytest.mark.parametrize("name", sorted(BACKBONES))
@pytest.mark.parametrize("seed", range(3))
def test_every_attribute_survives_encode_decode_with_its_width_and_treatment(name, codec, seed, tmp_path):
    schema = BACKBONES[name]
    payload = _payload(name, 300 + 50 * seed, seed)
    encode_payload(payload, tmp_path / "m.omg4", codec=codec)
    model = load_omg4(tmp_path / "m.omg4")
    decoded = model.values
    # the file keeps Gaussians in its own order: match rows by position (compact: its grid's Z-order, since it
    # moves positions and time centres onto grids by at most half a step, plus fp16 rounding)
    xyz16 = payload.xyz.astype(np.float16)
    if codec == "compact":
        order, back = position_order(xyz16), np.arange(xyz16.shape[0])
        half_step = {"xyz": np.ptp(xyz16.astype(np.float64), axis=0).max() / (2 ** 15 - 1) / 2, "t": 1 / 1024 / 2}
    else:
        order, back = np.lexsort(xyz16.T[::-1]), np.lexsort(decoded["xyz"].numpy().T[::-1])
        half_step = {"xyz": 0.0, "t": 0.0}
    treated = set()
    for attribute in (*schema.attributes, *APPEARANCE_FEATURES):
        if attribute.by_mlp:
            assert attribute.name not in decoded  # replaced by the MLPs
            treated.add(attribute.name)
            continue
        value = decoded[attribute.name].numpy()[back]
        if attribute.svq is None:  # explicit, fp16 in the file
            expected = getattr(payload, attribute.name).reshape(-1, WIDTH[attribute.name]).astype(np.float16)
            expected = expected[order].astype(np.float64)
            tolerance = half_step[attribute.name] * (1 + 1e-9) + np.abs(expected) * 2.0 ** -11
            assert (np.abs(value - expected) <= tolerance).all()
        else:
            group = schema.svq_group(attribute.svq)
            recon = payload.attributes[group.name].reconstruct()
            start = 0
            for param, width in schema.svq_widths(group.name):
                if param == attribute.name:
                    break
                start += width
            assert value.shape[1] == width == int(np.prod(attribute.shape))
            np.testing.assert_array_equal(value, recon[order, start:start + width])
        treated.add(attribute.name)
    assert treated == {a.name for a in (*schema.attributes, *APPEARANCE_FEATURES)}
    assert model.appearance.num_inputs == schema.mlp_inputs
    sl = model.slice_at(0.5, torch.tensor([0.0, 0.0, -4.0]))
    assert torch.isfinite(sl.colors).all() and torch.isfinite(sl.means).all()


@pytest.mark.parametrize("name", sorted(BACKBONES))
def test_a_compressed_model_stores_only_positions_and_time_centres_unquantized(name):
    """The payload has explicit sections for xyz and t only; every other attribute must be quantized or MLP-made."""
    assert BACKBONES[name].explicit_after_compression() == ("xyz", "t")


def test_a_file_that_names_no_backbone_decodes_as_real_time_4dgs(tmp_path):
    payload = _payload("rt4dgs", 200, 0)
    del payload.meta["gaussian_config"]["backbone"]
    encode_payload(payload, tmp_path / "old.omg4")
    model = load_omg4(tmp_path / "old.omg4")
    assert model.config.backbone == "rt4dgs" and "rotation_r" in model.values
