"""OMG4 appearance MLPs (paper §4.4, omg4 §6b): contraction, encoding, wiring, storage, fitting."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from omg4.errors import CorruptFileError
from omg4.gaussians.appearance import AppearanceMLP, contract_to_unisphere, frequency_encoding

# hand count: Linear(in, 64) + Linear(64, out), no biases
EXPECTED_PARAMS = (128 * 64 + 64 * 13) + (16 * 64 + 64 * 3) + (16 * 64 + 64 * 1) + (16 * 64 + 64 * 141)


def _inputs(n: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    xyz = torch.randn(n, 3, generator=g) * 1.5  # mix of points inside and outside the unit ball
    return xyz, torch.randn(n, 3, generator=g) * 0.5, torch.randn(n, 3, generator=g) * 0.5


def _mlp(seed: int = 0) -> AppearanceMLP:
    torch.manual_seed(seed)
    return AppearanceMLP()


def test_output_shapes_and_parameter_count():
    mlp = _mlp()
    xyz, fs, fv = _inputs(37)
    dc, rest, opacity = mlp(xyz, 0.3, fs, fv)
    assert dc.shape == (37, 1, 3) and rest.shape == (37, 47, 3) and opacity.shape == (37,)
    assert bool(((opacity > 0) & (opacity < 1)).all())
    assert EXPECTED_PARAMS == 21376
    assert mlp.num_parameters() == EXPECTED_PARAMS
    assert all(m.bias is None for m in mlp.modules() if isinstance(m, torch.nn.Linear))


def test_contraction_hand_values():
    x = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.2, 0.4], [3.0, 0.0, 0.0], [0.0, -2.0, 0.0], [1.0, 1.0, 1.0]],
                     dtype=torch.float64)
    r3 = math.sqrt(3.0)
    c = (2.0 - 1.0 / r3) / r3  # |(1,1,1)| = sqrt 3 → (2 - 1/sqrt3) * x / sqrt3
    expected = torch.tensor([
        [0.5, 0.5, 0.5],
        [0.5 / 4 + 0.5, -0.2 / 4 + 0.5, 0.4 / 4 + 0.5],
        [(2 - 1 / 3) / 4 + 0.5, 0.5, 0.5],
        [0.5, -(2 - 1 / 2) / 4 + 0.5, 0.5],
        [c / 4 + 0.5] * 3,
    ], dtype=torch.float64)
    torch.testing.assert_close(contract_to_unisphere(x), expected, rtol=0, atol=1e-12)


def test_contraction_range_and_continuity():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(2000, 3, generator=g, dtype=torch.float64) * torch.logspace(-2, 4, 2000, dtype=torch.float64)[:, None]
    y = contract_to_unisphere(x)
    radius = torch.linalg.vector_norm(y - 0.5, dim=1)
    assert bool((radius < 0.5).all()) and bool((y >= 0).all()) and bool((y <= 1).all())
    d = torch.nn.functional.normalize(x, dim=1)
    inside, outside = contract_to_unisphere(d * (1 - 1e-9)), contract_to_unisphere(d * (1 + 1e-9))
    torch.testing.assert_close(inside, outside, rtol=0, atol=1e-8)


def test_frequency_encoding_matches_tcnn_layout():
    x = torch.tensor([[0.1, 0.7], [0.33, -0.25]], dtype=torch.float64)
    num_freqs = 5
    enc = frequency_encoding(x, num_freqs)
    assert enc.shape == (2, 2 * 2 * num_freqs)
    for n in range(2):
        for j in range(enc.shape[1]):
            d, k = j // (2 * num_freqs), (j // 2) % num_freqs
            arg = (2.0 ** k) * math.pi * float(x[n, d])
            want = math.sin(arg) if j % 2 == 0 else math.cos(arg)
            assert abs(float(enc[n, j]) - want) < 1e-9, (n, j)


def _reference_forward(state: dict[str, np.ndarray], xyz, t_norm, fs, fv, num_freqs=16):
    """Independent float64 numpy forward pass from the weight matrices (omg4 §6b)."""
    W = {k: v.astype(np.float64) for k, v in state.items()}
    x = np.asarray(xyz, np.float64)
    mag = np.linalg.norm(x, axis=1, keepdims=True)
    x = np.where(mag > 1, (2 - 1 / np.maximum(mag, 1)) * x / np.maximum(mag, 1), x) / 4 + 0.5
    inp = np.concatenate([x, np.full((len(x), 1), t_norm)], 1)
    cols = []
    for d in range(4):
        for k in range(num_freqs):
            cols += [np.sin(2.0 ** k * np.pi * inp[:, d]), np.cos(2.0 ** k * np.pi * inp[:, d])]
    enc = np.stack(cols, 1)

    def relu(a):
        return np.maximum(a, 0)

    def leaky(a):
        return np.where(a > 0, a, 0.01 * a)

    shared = relu(enc @ W["shared.0.weight"].T) @ W["shared.2.weight"].T
    s_in = np.concatenate([shared, np.asarray(fs, np.float64)], 1)
    v_in = np.concatenate([shared, np.asarray(fv, np.float64)], 1)
    dc = leaky(s_in @ W["dc.0.weight"].T) @ W["dc.2.weight"].T
    op = 1 / (1 + np.exp(-(leaky(s_in @ W["opacity.0.weight"].T) @ W["opacity.2.weight"].T)[:, 0]))
    rest = leaky(v_in @ W["rest.0.weight"].T) @ W["rest.2.weight"].T
    return dc[:, None, :], rest.reshape(len(x), 47, 3), op


def test_forward_matches_independent_float64_reference():
    mlp = _mlp(3).double()
    xyz, fs, fv = (a.double() for a in _inputs(50, seed=3))
    state = {k: v.detach().numpy() for k, v in mlp.state_dict().items()}
    got = mlp(xyz, 0.42, fs, fv)
    want = _reference_forward(state, xyz.numpy(), 0.42, fs.numpy(), fv.numpy())
    for g, w in zip(got, want):
        np.testing.assert_allclose(g.detach().numpy(), w, rtol=1e-10, atol=1e-12)


def test_split_first_layer_matches_the_reference_for_rows_of_several_views():
    """Cached position term + per-view time term (the render and fine-tuning path) = the network on [x, t]."""
    mlp = _mlp(5).double()
    xyz, fs, fv = (a.double() for a in _inputs(40, seed=5))
    state = {k: v.detach().numpy() for k, v in mlp.state_dict().items()}
    times = torch.tensor([0.1, 0.65, 0.93], dtype=torch.float64)
    views = torch.tensor([2, 0, 1, 1, 2, 0, 0] * 5 + [1] * 5)  # row r belongs to view views[r]
    term = mlp.position_term(xyz, chunk=7)  # several blocks
    got = mlp.predict_from_position_term(term, times, views, fs, fv)
    # phases up to 2^15·π: float64 rounding of the phase alone reaches ~1e-11, hence 1e-9
    for v in range(3):
        rows = (views == v).nonzero()[:, 0]
        want = _reference_forward(state, xyz[rows].numpy(), float(times[v]), fs[rows].numpy(), fv[rows].numpy())
        dc, rest, logit = (g[rows].detach().numpy() for g in got)
        np.testing.assert_allclose(dc, want[0], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(rest, want[1], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(1 / (1 + np.exp(-logit)), want[2], rtol=1e-9, atol=1e-9)


def test_split_first_layer_has_the_gradients_of_the_direct_network():
    mlp = _mlp(6).double()
    xyz, fs, fv = (a.double() for a in _inputs(30, seed=6))
    times = torch.tensor([0.3, 0.8], dtype=torch.float64)
    views = torch.arange(30) % 2
    grads = []
    for split in (False, True):
        mlp.zero_grad()
        f_s, f_v = fs.clone().requires_grad_(True), fv.clone().requires_grad_(True)
        if split:
            dc, rest, logit = mlp.predict_from_position_term(mlp.position_term(xyz), times, views, f_s, f_v)
        else:
            dc, rest, logit = mlp.predict(xyz, times[views], f_s, f_v)
        (dc.sin().sum() + rest.square().sum() + logit.tanh().sum()).backward()
        grads.append([f_s.grad, f_v.grad] + [p.grad.clone() for p in mlp.parameters()])
    for a, b in zip(*grads):
        torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-12)


def test_position_term_needs_a_time_conditioned_network():
    with pytest.raises(ValueError):
        AppearanceMLP(num_inputs=3).position_term(torch.zeros(2, 3))


def test_time_conditioning():
    mlp = _mlp()
    xyz, fs, fv = _inputs(64)
    with torch.no_grad():
        a, b, a2 = mlp(xyz, 0.2, fs, fv), mlp(xyz, 0.7, fs, fv), mlp(xyz, 0.2, fs, fv)
    for x, y, x2 in zip(a, b, a2):
        assert torch.equal(x, x2)
        assert float((x - y).abs().max()) > 1e-3


def test_gradients_reach_features_and_weights_but_not_xyz():
    mlp = _mlp()
    xyz, fs, fv = _inputs(64)
    xyz.requires_grad_(True)
    fs.requires_grad_(True)
    fv.requires_grad_(True)
    dc, rest, opacity = mlp(xyz, 0.5, fs, fv)
    (dc.square().sum() + rest.square().sum() + opacity.sum()).backward()
    assert xyz.grad is None
    for name, t in [("f_static", fs), ("f_view", fv), *mlp.named_parameters()]:
        assert t.grad is not None and float(t.grad.abs().sum()) > 0, name


def test_fp16_state_round_trip():
    mlp = _mlp(5)
    state = mlp.to_fp16_state()
    assert all(v.dtype == np.float16 for v in state.values())
    assert sum(v.size for v in state.values()) == EXPECTED_PARAMS
    assert sum(v.nbytes for v in state.values()) == 2 * EXPECTED_PARAMS == 42752
    loaded = AppearanceMLP.from_fp16_state(state)
    xyz, fs, fv = _inputs(40, seed=5)
    # exact against the same weights rounded to fp16
    rounded = _mlp(5)
    with torch.no_grad():
        for p in rounded.parameters():
            p.copy_(p.half().float())
    for x, y, z in zip(loaded(xyz, 0.6, fs, fv), rounded(xyz, 0.6, fs, fv), mlp(xyz, 0.6, fs, fv)):
        torch.testing.assert_close(x, y, rtol=0, atol=1e-6)
        torch.testing.assert_close(x, z, rtol=0, atol=5e-3)  # fp16 weight rounding only


@pytest.mark.parametrize("damage", ["missing", "shape", "nan", "dtype"])
def test_from_fp16_state_rejects_bad_weights(damage):
    state = _mlp().to_fp16_state()
    if damage == "missing":
        state.pop("rest.2.weight")
    elif damage == "shape":
        state["dc.2.weight"] = state["dc.2.weight"][:, :10]
    elif damage == "nan":
        state["opacity.0.weight"] = state["opacity.0.weight"].copy()
        state["opacity.0.weight"][0, 0] = np.nan
    else:
        state["shared.0.weight"] = state["shared.0.weight"].astype(np.float32)
    with pytest.raises(CorruptFileError):
        AppearanceMLP.from_fp16_state(state)


def test_fits_a_time_varying_colour():
    """The MLPs + per-Gaussian features learn a colour and opacity that change with time.

    The final loss must be far below both the initial loss and the best loss any time-blind
    predictor (the per-point mean over time) could reach.
    """
    torch.manual_seed(0)
    n = 300
    g = torch.Generator().manual_seed(7)
    xyz = torch.rand(n, 3, generator=g) * 2 - 1
    base = torch.rand(n, 3, generator=g) - 0.5
    times = torch.linspace(0, 1, 6).tolist()

    def target(t):
        dc = base * math.cos(2 * math.pi * t) + 0.3 * torch.sin(3 * xyz + 4 * t)
        return dc, torch.sigmoid(2 * xyz[:, 0] - 3 * t + 1)

    dcs, ops = (torch.stack(v) for v in zip(*(target(t) for t in times)))
    time_blind = float((dcs - dcs.mean(0)).square().mean() + (ops - ops.mean(0)).square().mean())

    mlp = AppearanceMLP()
    fs = base.clone().requires_grad_(True)
    fv = torch.zeros(n, 3, requires_grad=True)
    opt = torch.optim.Adam([*mlp.parameters(), fs, fv], lr=5e-3, eps=1e-15)
    sched = torch.optim.lr_scheduler.MultiStepLR(opt, [200, 300], gamma=0.33)

    def loss_at(t):
        dc, rest, op = mlp(xyz, t, fs, fv)
        tdc, top = target(t)
        return (dc[:, 0] - tdc).square().mean() + (op - top).square().mean() + 1e-3 * rest.square().mean()

    def mean_loss():
        with torch.no_grad():
            return float(sum(loss_at(t) for t in times)) / len(times)

    initial = mean_loss()
    for step in range(360):
        opt.zero_grad()
        loss_at(times[step % len(times)]).backward()
        opt.step()
        sched.step()
    final = mean_loss()
    assert final < initial / 30, (initial, final)
    assert final < time_blind / 10, (time_blind, final)


def test_a_decoded_network_declares_at_most_24_frequency_bands():
    """2^24·π keeps float32 phases meaningful: 24 bands decode, 25 are refused (shapes from the file)."""
    small = dict(num_rest=3, hidden=4, shared_dim=2)
    assert AppearanceMLP.from_fp16_state(AppearanceMLP(num_freqs=24, **small).to_fp16_state()).shared[0].weight.shape \
        == (4, 2 * 4 * 24)
    with pytest.raises(CorruptFileError, match="invalid sizes"):
        AppearanceMLP.from_fp16_state(AppearanceMLP(num_freqs=25, **small).to_fp16_state())


def test_default_networks_have_the_documented_sizes():
    """docs/file-format.md: by default hidden = 64, freqs = 16, shared_dim = 13, num_rest = 47 (4 inputs)."""
    state = AppearanceMLP().to_fp16_state()
    assert state["shared.0.weight"].shape == (64, 2 * 4 * 16)
    assert state["shared.2.weight"].shape == (13, 64)
    assert state["dc.0.weight"].shape == (64, 13 + 3) and state["rest.2.weight"].shape == (3 * 47, 64)
