"""Sub-vector quantization: fitting, reconstruction error vs. codebook size, gradients, payload export."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from omg4.codec.payload import CompressedPayload, decode_payload, encode_payload
from omg4.compress.presets import size_preset
from omg4.compress.svq import SubVectorQuantizer


def _values(n: int = 3000, d: int = 4, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(n, d, generator=gen) * torch.linspace(0.5, 2.0, d) + torch.randn(n, 1, generator=gen)


def test_fit_splits_into_contiguous_sub_vectors():
    x = _values(d=6)
    q = SubVectorQuantizer.fit(x, sub_len=2, codebook_size=32, seed=0)
    assert len(q.codebooks) == 3 and q.indices.shape == (3000, 3)
    assert all(cb.shape == (32, 2) for cb in q.codebooks)
    recon = q.values()
    assert recon.shape == (3000, 6)
    for j in range(3):  # slot j is reconstructed from codebook j only, in columns 2j:2j+2
        torch.testing.assert_close(recon[:, 2 * j:2 * j + 2], q.codebooks[j][q.indices[:, j]], rtol=0, atol=0)
        # and each index is the nearest codeword of the original sub-vector (k-means assignment)
        dist = ((x[:, None, 2 * j:2 * j + 2] - q.codebooks[j].detach()[None]) ** 2).sum(-1)
        picked = dist.gather(1, q.indices[:, j:j + 1]).squeeze(1)
        torch.testing.assert_close(picked, dist.min(1).values, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("sub_len", [1, 2])
def test_reconstruction_error_falls_as_codebooks_grow(sub_len):
    x = _values()
    errors = [float((SubVectorQuantizer.fit(x, sub_len, k).values().detach() - x).square().mean())
              for k in (4, 16, 64, 256)]
    assert all(b < 0.6 * a for a, b in zip(errors, errors[1:]))


def test_lossless_when_codebook_covers_all_values():
    x = torch.randint(0, 5, (1000, 4)).float()  # 25 distinct pairs per slot
    q = SubVectorQuantizer.fit(x, 2, 64)
    torch.testing.assert_close(q.values(), x, rtol=0, atol=0)


def test_gradients_reach_codebooks_only():
    x = _values(500).requires_grad_(True)
    q = SubVectorQuantizer.fit(x, 2, 16)
    assert [p for p in q.parameters()] == list(q.codebooks)  # indices are a buffer, not a parameter
    q.values().square().sum().backward()
    assert x.grad is None
    for j, cb in enumerate(q.codebooks):
        counts = torch.bincount(q.indices[:, j], minlength=cb.shape[0]).float()
        # d/dc Σ_i c[idx_i]² = 2 · count(c) · c  (closed form)
        torch.testing.assert_close(cb.grad, 2 * counts[:, None] * cb.detach())
    assert not q.indices.requires_grad


def test_slots_of_mixed_lengths_reconstruct_and_backpropagate():
    """A decoded file may hold slots of different sub-vector lengths: column blocks follow the slots' widths."""
    gen = torch.Generator().manual_seed(1)
    codebooks = [torch.randn(5, 1, generator=gen), torch.randn(7, 2, generator=gen), torch.randn(3, 1, generator=gen)]
    indices = torch.stack([torch.randint(0, k.shape[0], (40,), generator=gen) for k in codebooks], dim=1)
    q = SubVectorQuantizer(codebooks, indices)
    expected = np.concatenate([cb.numpy()[ix] for cb, ix in zip(codebooks, indices.T.numpy())], axis=1)
    np.testing.assert_array_equal(q.values().detach().numpy(), expected)
    q.values().square().sum().backward()
    for j, cb in enumerate(q.codebooks):
        counts = torch.bincount(indices[:, j], minlength=cb.shape[0]).float()
        torch.testing.assert_close(cb.grad, 2 * counts[:, None] * cb.detach())


def test_select_keeps_rows_and_codebook_objects():
    q = SubVectorQuantizer.fit(_values(200), 2, 8)
    codebook_ids = [id(cb) for cb in q.codebooks]
    before = q.values().detach()
    keep = torch.arange(200) % 3 != 0
    q.select(keep)
    assert q.num_gaussians == int(keep.sum())
    torch.testing.assert_close(q.values().detach(), before[keep], rtol=0, atol=0)
    assert [id(cb) for cb in q.codebooks] == codebook_ids  # the codebook optimizer keeps working


def test_payload_round_trip(tmp_path):
    x = _values(400, d=4)
    q = SubVectorQuantizer.fit(x, 2, 64)
    exported = q.to_quantized()
    assert [cb.dtype for cb in exported.codebooks] == [np.float16] * 2
    payload = CompressedPayload(np.zeros((400, 3)), np.zeros(400), {"rotation": exported})
    encode_payload(payload, tmp_path / "q.omg4", codec="paper")
    restored = SubVectorQuantizer.from_quantized(decode_payload(tmp_path / "q.omg4").attributes["rotation"])
    torch.testing.assert_close(restored.indices, q.indices, rtol=0, atol=0)
    torch.testing.assert_close(restored.values(), q.values().detach().half().float(), rtol=0, atol=0)


def test_rejects_bad_shapes():
    with pytest.raises(ValueError):
        SubVectorQuantizer.fit(torch.zeros(10, 3), 2, 4)
    with pytest.raises(ValueError):
        SubVectorQuantizer([torch.zeros(4, 1)], torch.zeros(10, 2, dtype=torch.long))


# paper appendix "Additional Implementation Details": b_s, b_r, b_f, and the 4D sizes
PAPER_M = {"scale": (1, 2**9), "rotation": (2, 2**13), "app": (2, 2**10), "scale_t": (1, 2**9),
           "rotation_r": (2, 2**13)}


@pytest.mark.parametrize("preset,expected", [
    ("M", PAPER_M), ("L", PAPER_M),
    ("S", {**PAPER_M, "scale": (1, 2**8)}), ("T", {**PAPER_M, "scale": (1, 2**8)}),
])
def test_preset_codebooks_follow_the_paper(preset, expected):
    for name in (preset, preset.lower()):
        p = size_preset(name)
        assert {a: p.codebook(a) for a in p.codebook_sizes} == expected


@pytest.mark.parametrize("preset,tau,p", [("L", 0.4, 0.8), ("M", 0.2, 0.8), ("S", 0.3, 0.9)])
def test_preset_sampling_and_pruning_follow_the_paper(preset, tau, p):
    s = size_preset(preset)
    assert (s.tau_gs, s.prune_quantile) == (tau, p)


def test_quantized_values_match_each_quantizers_gather_in_values_and_codebook_gradients():
    """The one-function gather of every quantizer (numba, CPU) against each quantizer's torch gather: the same
    reconstructions, and the same gradients in every codebook (rows no Gaussian uses get exact zeros)."""
    from omg4.compress.svq import quantized_values
    from omg4.kernels import using_kernels

    g = torch.Generator().manual_seed(3)
    quantizers = {"scale": SubVectorQuantizer([torch.randn(7, 1, generator=g) for _ in range(3)],
                                              torch.randint(5, (40, 3), generator=g)),  # rows 5, 6 unused
                  "rotation": SubVectorQuantizer([torch.randn(9, 2, generator=g) for _ in range(2)],
                                                 torch.randint(9, (40, 2), generator=g))}
    weights = {name: torch.randn(40, q.indices.shape[1] * q.codebooks[0].shape[1], generator=g)
               for name, q in quantizers.items()}
    results = []
    for mode in ("fused", "reference"):
        for q in quantizers.values():
            for cb in q.codebooks:
                cb.grad = None
        with using_kernels(mode):
            values = quantized_values(quantizers)
        sum((values[name] * weights[name]).sum() for name in quantizers).backward()
        results.append((values, [cb.grad.clone() for q in quantizers.values() for cb in q.codebooks]))
    (fused, fused_grads), (ref, ref_grads) = results
    for name in quantizers:
        assert torch.equal(fused[name], ref[name])
        assert type(fused[name].grad_fn).__name__ == "_QuantizedValuesBackward"  # the one function, not a fallback
    for a, b in zip(fused_grads, ref_grads):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-6)
    assert torch.equal(fused_grads[0][5:], torch.zeros(2, 1))
