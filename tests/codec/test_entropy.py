"""Index-stream entropy coders: bit-exact round trips, rate vs. empirical entropy, damage handling."""

from __future__ import annotations

import lzma

import dahuffman
import numpy as np
import pytest

from omg4.codec.entropy import (decode_indices, decode_uints, encode_indices, encode_uints, pack_varints,
                                unpack_varints)
from omg4.errors import CorruptFileError

METHODS = ["ans", "paper"]


def _skewed(rng, n, k, p=0.01):
    return np.minimum(rng.geometric(p, n) - 1, k - 1)


def _entropy_bits(x: np.ndarray) -> float:
    """Empirical (order-0) entropy of the whole stream in bits, float64."""
    counts = np.bincount(x).astype(np.float64)
    p = counts[counts > 0] / x.size
    return float(-(counts[counts > 0] * np.log2(p)).sum())


CASES = {
    "uniform-512": lambda rng: (rng.integers(0, 512, 20_000), 512),
    "uniform-8192": lambda rng: (rng.integers(0, 8192, 30_000), 8192),
    "skewed-8192": lambda rng: (_skewed(rng, 30_000, 8192, 0.002), 8192),
    "skewed-2": lambda rng: (_skewed(rng, 5_000, 2, 0.9), 2),
    "single-repeated": lambda rng: (np.full(7_000, 4095), 8192),
    "single-symbol-alphabet": lambda rng: (np.zeros(100, np.int64), 1),
    "one-element": lambda rng: (np.array([511]), 512),
    "empty": lambda rng: (np.zeros(0, np.int64), 512),
    "max-alphabet-edges": lambda rng: (np.array([0, 8191] * 50 + [1]), 8192),
}


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("case", list(CASES))
def test_round_trip_is_bit_exact(method, case):
    x, k = CASES[case](np.random.default_rng(7))
    data = encode_indices(x, k, method)
    y = decode_indices(data, k, x.size, method)
    assert y.dtype == np.int64
    np.testing.assert_array_equal(y, x)


@pytest.mark.parametrize("dtype", [np.uint8, np.int16, np.uint16, np.int32, np.int64])
def test_any_integer_dtype(dtype):
    x = np.arange(200, dtype=dtype) % 7
    np.testing.assert_array_equal(decode_indices(encode_indices(x, 7), 7, 200), x)


@pytest.mark.parametrize("k,p", [(512, 0.01), (8192, 0.001), (8192, 0.05)])
def test_ans_rate_is_close_to_empirical_entropy(k, p):
    x = _skewed(np.random.default_rng(1), 200_000, k, p)
    bits = 8 * len(encode_indices(x, k, "ans"))
    ideal = _entropy_bits(x)
    assert bits >= ideal  # no i.i.d. coder with its model stored beats the empirical entropy
    assert bits <= 1.004 * ideal + 8 * 2048  # ≤ 0.4% excess plus a 2 KiB model budget


def test_paper_rate_within_huffman_bound():
    x = _skewed(np.random.default_rng(2), 100_000, 8192, 0.003)
    bits = 8 * len(encode_indices(x, 8192, "paper"))
    assert bits <= _entropy_bits(x) + x.size + 8 * 4096  # Huffman: < 1 bit/symbol above entropy, + table


def test_paper_stream_is_dahuffman_then_lzma():
    """The stream is LZMA over (counts table, dahuffman bitstream) with the size dahuffman's own codec gives."""
    x = _skewed(np.random.default_rng(3), 20_000, 1024, 0.01)
    data = encode_indices(x, 1024, "paper")
    plain = lzma.decompress(data[1:], format=lzma.FORMAT_RAW, filters=[{"id": lzma.FILTER_LZMA2}])
    (n, k), used = unpack_varints(plain, 2)
    _, used_table = unpack_varints(plain[used:], 2 * int(k))
    huffman = plain[used + used_table:]
    reference = dahuffman.HuffmanCodec.from_data(x.tolist())  # the official call (first-seen symbol order)
    assert (n, k) == (x.size, np.unique(x).size)
    assert len(huffman) == len(reference.encode(x.tolist()))  # every Huffman code has the same total length
    assert reference.decode(reference.encode(x.tolist())) == x.tolist()


def test_invalid_inputs_raise_value_error():
    with pytest.raises(ValueError):
        encode_indices(np.array([0, 5]), 5)
    with pytest.raises(ValueError):
        encode_indices(np.array([-1]), 5)
    with pytest.raises(ValueError):
        encode_indices(np.array([0.5]), 5)
    with pytest.raises(ValueError):
        encode_indices(np.array([0]), 5, "zip")
    with pytest.raises(ValueError):
        encode_indices(np.array([0]), 0)


@pytest.mark.parametrize("method", METHODS)
def test_every_truncation_raises(method):
    x = _skewed(np.random.default_rng(4), 2_000, 512, 0.05)
    data = encode_indices(x, 512, method)
    for length in range(len(data)):
        with pytest.raises(CorruptFileError):
            decode_indices(data[:length], 512, x.size, method)


@pytest.mark.parametrize("method", METHODS)
def test_damage_raises_corrupt_file_error_or_decodes_in_range(method):
    """Bit flips: only CorruptFileError may escape; a silent mis-decode stays in range (the container's
    checksums catch those)."""
    rng = np.random.default_rng(5)
    x = _skewed(rng, 2_000, 512, 0.05)
    data = encode_indices(x, 512, method)
    detected = 0
    for bit in rng.choice(8 * len(data), size=400, replace=False):
        damaged = bytearray(data)
        damaged[bit // 8] ^= 1 << (bit % 8)
        try:
            y = decode_indices(bytes(damaged), 512, x.size, method)
        except CorruptFileError:
            detected += 1
            continue
        assert y.shape == x.shape and y.min() >= 0 and y.max() < 512
    assert detected >= 300


@pytest.mark.parametrize("method", METHODS)
def test_wrong_count_alphabet_or_method(method):
    x = np.arange(100) % 10
    data = encode_indices(x, 10, method)
    other = "paper" if method == "ans" else "ans"
    for args in [(10, 99, method), (10, 101, method), (10, 100, other), (9, 100, method)]:
        with pytest.raises(CorruptFileError):
            decode_indices(data, *args)
    if method == "ans":  # the ANS model has one entry per symbol; Huffman stores only the symbols present
        with pytest.raises(CorruptFileError):
            decode_indices(data, 11, 100, method)
    with pytest.raises(CorruptFileError):
        decode_indices(data, 10, -1, method)


def test_garbage_bytes_never_escape_as_other_errors():
    rng = np.random.default_rng(6)
    for method in METHODS:
        for _ in range(200):
            blob = rng.integers(0, 256, rng.integers(0, 64), dtype=np.uint8).tobytes()
            blob = bytes([0xA1 if method == "ans" else 0xB1]) + blob
            try:
                y = decode_indices(blob, 64, 50, method)
            except CorruptFileError:
                continue
            assert y.shape == (50,) and y.min() >= 0 and y.max() < 64


def _varint_reference(values):
    out = bytearray()
    for v in values:
        v = int(v)
        while True:
            byte, v = v & 0x7F, v >> 7
            out.append(byte | (0x80 if v else 0))
            if not v:
                break
    return bytes(out)


def test_varints_match_scalar_leb128():
    rng = np.random.default_rng(8)
    spread = rng.integers(0, 2**63, 500, dtype=np.uint64) >> rng.integers(0, 63, 500).astype(np.uint64)
    values = np.concatenate([np.array([0, 1, 127, 128, 16383, 16384, 2**63, 2**64 - 1], dtype=np.uint64), spread])
    data = pack_varints(values)
    assert data == _varint_reference(values)
    decoded, used = unpack_varints(data + b"\x05tail", values.size)
    assert used == len(data)
    np.testing.assert_array_equal(decoded, values)
    with pytest.raises(CorruptFileError):
        unpack_varints(data[:-1], values.size)
    with pytest.raises(CorruptFileError):
        unpack_varints(b"\x80" * 11 + b"\x00", 1)


def test_uints_round_trip():
    rng = np.random.default_rng(9)
    spread = rng.integers(0, 2**62, 3000, dtype=np.uint64) >> rng.integers(0, 62, 3000).astype(np.uint64)
    values = np.concatenate([np.arange(40, dtype=np.uint64), np.array([2**64 - 1, 2**63, 2**48 - 1], np.uint64), spread])
    np.testing.assert_array_equal(decode_uints(encode_uints(values), values.size), values)
    np.testing.assert_array_equal(decode_uints(encode_uints(np.zeros(0, np.uint64)), 0), np.zeros(0, np.uint64))
    small = np.full(1000, 3, np.uint64)
    assert len(encode_uints(small)) < 16  # one repeated token, no raw bits


def test_uints_cost_about_log2_plus_token():
    """Geometric gaps with mean 2^20: about log2(mean) + ~2 bits each (Elias-gamma would need 2·log2)."""
    gaps = np.random.default_rng(10).geometric(2.0**-20, 50_000).astype(np.uint64)
    bits = 8 * len(encode_uints(gaps)) / gaps.size
    ideal = float(np.log2(np.e * 2.0**20))  # differential entropy of an exponential, in bits
    assert ideal - 0.1 <= bits <= ideal + 0.5


def test_uints_damage_raises():
    data = encode_uints(np.arange(1000, dtype=np.uint64) * 12345)
    for length in range(0, len(data), 7):
        with pytest.raises(CorruptFileError):
            decode_uints(data[:length], 1000)
    with pytest.raises(CorruptFileError):
        decode_uints(data + b"\x00", 1000)


def test_symbol_weights_are_the_documented_powers_of_two():
    """The ANS model's weights (docs/file-format.md §4): 2¹⁵·2^((q−1)/s) from an 8-entry mantissa table
    round(2¹⁵·2^(j/8)), for the steps per octave s in {1, 2, 4, 8}; 0 for q = 0."""
    from omg4.codec import entropy

    assert entropy._MANTISSA.tolist() == [round(2**15 * 2 ** (j / 8)) for j in range(8)]
    q = np.arange(0, 40)
    for steps in (1, 2, 4, 8):
        expected = np.where(q > 0, 2.0**15 * 2.0 ** ((q - 1) / steps), 0.0)
        np.testing.assert_allclose(entropy._weights(q, steps), expected, rtol=2e-5)


@pytest.mark.parametrize("steps", [1, 2, 4, 8])
def test_an_ans_stream_with_any_documented_octave_step_decodes(steps):
    """docs/file-format.md §4: the model's steps per octave s is one of 1, 2, 4, 8, whichever the encoder found
    shortest; a reader takes each (streams forced to each s here, laid out as the spec says)."""
    from omg4.codec import entropy

    idx = np.random.default_rng(steps).integers(0, 40, 500) ** 2 % 40
    counts = np.bincount(idx, minlength=40)
    q = np.where(counts > 0, 1 + np.rint(steps * np.log2(np.maximum(counts, 1))), 0).astype(np.uint8)
    table = entropy.deflate_raw(q.tobytes())
    stream = (bytes([entropy._TAG_ANS]) + pack_varints(np.array([idx.size])) + bytes([entropy._MODE_ANS, steps])
              + pack_varints(np.array([len(table)])) + table + entropy._ans_body(idx, entropy._weights(q, steps)))
    np.testing.assert_array_equal(decode_indices(stream, 40, idx.size, "ans"), idx)


def test_a_code_table_that_is_no_prefix_code_is_refused_by_the_walk():
    """The prefix-code walk builds its tree from the code table before reading a bit: a table that needs more
    than the 2·m nodes a prefix code of m symbols fills (one symbol of 2 bits; two symbols of 1 and 4 bits) is −1,
    whatever the stream."""
    from omg4.codec.entropy import _walk_prefix_code

    out = np.zeros(4, np.int64)
    for lengths, values in (([2], [0]), ([1, 4], [0, 0b1111])):
        assert _walk_prefix_code(np.array(lengths, np.int64), np.array(values, np.uint64),
                                 np.zeros(1, np.uint8), out) == -1
    # a valid code (0 → symbol 0, 1 → the end): "0 0 1" is two symbols, then the end
    assert _walk_prefix_code(np.array([1, 1], np.int64), np.array([0, 1], np.uint64),
                             np.array([0b00100000], np.uint8), out) == 2
