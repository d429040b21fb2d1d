"""Media output: H.264 video round trip through PyAV, side-by-side frames, PNG/NPY image files."""

import math
import os
import platform
import subprocess
import sys

import av
import numpy as np
import pytest
import torch

from omg4.errors import CorruptFileError, OMG4Error
from omg4.io.images import load_image, save_npy, save_png, to_uint8
from omg4.io.video import side_by_side, write_video


def _pattern(h, w, t, period=20.0):
    """Smooth, moving colour pattern in [0.1, 0.9], float64 [h, w, 3]."""
    yy, xx = np.mgrid[0:h, 0:w]
    return np.stack([0.5 + 0.4 * np.sin(xx / period + t / 3), 0.5 + 0.4 * np.cos(yy / period - t / 4),
                     0.5 + 0.3 * np.sin((xx + yy) / period + t / 5)], -1)


def _decode(path):
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        meta = (stream.codec_context.name, stream.codec_context.pix_fmt, stream.average_rate)
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    return meta, frames


def _psnr8(decoded, reference):
    mse = np.mean((decoded.astype(np.float64) / 255.0 - reference) ** 2)
    return -10 * math.log10(mse)


def _leftovers(folder):
    return [p.name for p in folder.iterdir() if ".tmp" in p.name]


def test_video_round_trip(tmp_path):
    frames = [_pattern(96, 128, t) for t in range(12)]
    path = tmp_path / "clip.mp4"
    assert write_video(path, (f for f in frames), fps=24) == 12  # a generator streams
    (codec, pix_fmt, rate), decoded = _decode(path)
    assert (codec, pix_fmt, rate) == ("h264", "yuv420p", 24)
    assert len(decoded) == 12
    assert all(d.shape == (96, 128, 3) for d in decoded)
    assert min(_psnr8(d, f) for d, f in zip(decoded, frames)) > 35.0
    assert _leftovers(tmp_path) == []


def test_odd_sizes_are_padded_to_even_and_uint8_frames_accepted(tmp_path):
    frames = [to_uint8(_pattern(47, 65, t)) for t in range(5)]
    path = tmp_path / "odd.mp4"
    write_video(path, frames, fps=30, crf=18)
    _, decoded = _decode(path)
    assert len(decoded) == 5 and decoded[0].shape == (48, 66, 3)
    assert min(_psnr8(d[:47, :65], f / 255.0) for d, f in zip(decoded, frames)) > 35.0


def test_lower_crf_gives_larger_file_and_higher_quality(tmp_path):
    frames = [_pattern(64, 64, t, period=6.0) for t in range(6)]
    write_video(tmp_path / "hi.mp4", frames, crf=10)
    write_video(tmp_path / "lo.mp4", frames, crf=35)
    assert (tmp_path / "hi.mp4").stat().st_size > (tmp_path / "lo.mp4").stat().st_size
    q_hi = np.mean([_psnr8(d, f) for d, f in zip(_decode(tmp_path / "hi.mp4")[1], frames)])
    q_lo = np.mean([_psnr8(d, f) for d, f in zip(_decode(tmp_path / "lo.mp4")[1], frames)])
    assert q_hi > q_lo


def test_bad_video_input_leaves_no_file(tmp_path):
    path = tmp_path / "bad.mp4"
    with pytest.raises(OMG4Error, match="no frames"):
        write_video(path, [])
    with pytest.raises(ValueError, match="expected 64x48"):
        write_video(path, [_pattern(48, 64, 0), _pattern(48, 62, 1)])
    with pytest.raises(OMG4Error, match="NaN"):
        write_video(path, [np.full((8, 8, 3), np.nan)])
    assert not path.exists() and _leftovers(tmp_path) == []


def test_side_by_side_concatenates_and_labels():
    a, b = _pattern(40, 30, 0), to_uint8(_pattern(40, 50, 1))
    c = torch.zeros(40, 20, 3)
    frame = side_by_side(a, b, c)
    assert frame.dtype == np.uint8 and frame.shape == (40, 100, 3)
    assert np.array_equal(frame[:, :30], to_uint8(a))
    assert np.array_equal(frame[:, 30:80], b)
    assert not frame[:, 80:].any()
    labelled = side_by_side(a, b, c, labels=["GT", None, "OMG4"])
    assert np.array_equal(labelled[:, 30:80], b)  # unlabelled panel untouched
    assert (labelled[:20, 80:] > 200).any()  # white (anti-aliased) text on the black panel
    assert np.array_equal(labelled[25:, :30], frame[25:, :30])  # label stays in the corner
    assert not (labelled[:20, :30] == frame[:20, :30]).all()
    with pytest.raises(ValueError, match="height"):
        side_by_side(a, _pattern(41, 30, 0))
    with pytest.raises(ValueError, match="labels"):
        side_by_side(a, b, labels=["only one"])


def test_png_round_trip_is_exact_on_8bit_values(tmp_path):
    values = np.random.default_rng(0).integers(0, 256, size=(17, 23, 3), dtype=np.uint8)
    save_png(tmp_path / "img.png", values.astype(np.float32) / 255.0)
    loaded = load_image(tmp_path / "img.png")
    assert loaded.dtype == np.float32 and loaded.shape == (17, 23, 3)
    assert np.array_equal(np.rint(loaded * 255.0).astype(np.uint8), values)
    assert np.array_equal(loaded, values.astype(np.float32) / 255.0)


def test_png_rounds_half_up_and_clamps(tmp_path):
    k = np.arange(0, 255, dtype=np.float64)
    img = np.zeros((4, 255, 3))
    img[0, :, :] = ((k + 0.49) / 255.0)[:, None]
    img[1, :, :] = ((k + 0.51) / 255.0)[:, None]
    img[2, :, :] = -0.2
    img[3, :, :] = 1.3
    save_png(tmp_path / "r.png", torch.tensor(img))
    stored = np.rint(load_image(tmp_path / "r.png") * 255.0).astype(int)
    assert np.array_equal(stored[0, :, 0], k.astype(int))
    assert np.array_equal(stored[1, :, 0], k.astype(int) + 1)
    assert (stored[2] == 0).all() and (stored[3] == 255).all()


def test_npy_round_trip_keeps_float32_values(tmp_path):
    img = np.random.default_rng(2).uniform(-0.1, 1.1, size=(9, 11, 3))
    save_npy(tmp_path / "img.npy", img)
    loaded = load_image(tmp_path / "img.npy")
    assert loaded.dtype == np.float32 and np.array_equal(loaded, img.astype(np.float32))
    assert _leftovers(tmp_path) == []


def test_bad_image_files(tmp_path):
    with pytest.raises(OMG4Error, match="not found"):
        load_image(tmp_path / "missing.png")
    (tmp_path / "broken.png").write_bytes(b"\x89PNG not really")
    with pytest.raises(CorruptFileError, match="cannot read image"):
        load_image(tmp_path / "broken.png")
    np.save(tmp_path / "wrong.npy", np.zeros((4, 4), dtype=np.float32))
    with pytest.raises(CorruptFileError, match="not a float"):
        load_image(tmp_path / "wrong.npy")
    (tmp_path / "trunc.npy").write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(CorruptFileError, match="cannot read"):
        load_image(tmp_path / "trunc.npy")
    with pytest.raises(OMG4Error, match="NaN"):
        save_png(tmp_path / "nan.png", np.full((2, 2, 3), np.nan))
    with pytest.raises(ValueError, match="RGB"):
        save_png(tmp_path / "gray.png", np.zeros((2, 2)))
    assert not (tmp_path / "nan.png").exists()


_ENCODE_IN_CHILD = """
import sys, numpy as np
from omg4.io.video import write_video
write_video(sys.argv[2], list(np.load(sys.argv[1])), fps=30, crf=17, reproducible=True)
"""


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="fills the heap through glibc's malloc tunables")
def test_reproducible_video_does_not_depend_on_the_heap(tmp_path):
    """Two processes whose heaps hold different bytes (glibc's ``malloc.perturb``) encode the same frames to the
    same bytes. The frames are a synthetic camera's on which libx264 with B-frames gives two different videos."""
    from omg4.data.synthetic import SynthConfig, SyntheticScene, box_filter

    config = SynthConfig(num_cameras=5, num_frames=6, width=64, height=48, num_points=600)
    scene = SyntheticScene(config)
    layer = scene.static_layer(3)
    frames = np.stack([box_filter(scene.render_samples(3, f, layer).rgb, config.supersample) for f in range(6)])
    np.save(tmp_path / "frames.npy", frames)
    written = []
    for fill in (1, 90):
        env = {**os.environ, "GLIBC_TUNABLES": f"glibc.malloc.perturb={fill}:glibc.malloc.mmap_threshold=33554432"}
        out = tmp_path / f"fill{fill}.mp4"
        subprocess.run([sys.executable, "-c", _ENCODE_IN_CHILD, str(tmp_path / "frames.npy"), str(out)], env=env,
                       check=True)
        written.append(out.read_bytes())
    assert written[0] == written[1]
    assert b"bframes=0" in written[0]  # the encoder's own record of its settings (x264's SEI)
