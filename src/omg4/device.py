"""Where tensors live: the one parser of the ``device`` settings and the ``--device`` option.

Training, compression, evaluation and rendering keep every tensor on one torch device
(``TrainConfig.device``, ``CompressConfig.device``, ``evaluate(..., device=)``). Random draws
are made with CPU generators and then moved, so a run is reproducible whatever the device.
Files (checkpoints, ``.omg4`` payloads, score ``.npz``) always hold CPU data; loaders take the
device to put it on.
"""

from __future__ import annotations

import torch

from omg4.errors import OMG4Error

DEVICE_HELP = "cpu (default), cuda, cuda:N, or auto (cuda when available, else cpu)"


def resolve_device(spec: str | torch.device) -> torch.device:
    """The torch device named by ``spec``: ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"auto"``.

    Raises:
        OMG4Error: an unknown name, a CUDA device on a machine without CUDA, or a CUDA index
            beyond the machine's devices (one-line messages).
    """
    if str(spec) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(spec)
    except (RuntimeError, TypeError):
        raise OMG4Error(f"unknown device '{spec}' (expected {DEVICE_HELP})") from None
    if device.type == "cpu":
        return device
    if device.type != "cuda":
        raise OMG4Error(f"device '{spec}' is not supported (expected {DEVICE_HELP})")
    if not torch.cuda.is_available():
        raise OMG4Error(f"device '{spec}': CUDA is not available on this machine "
                        "(torch.cuda.is_available() is False)")
    count = torch.cuda.device_count()
    if device.index is not None and device.index >= count:
        raise OMG4Error(f"device '{spec}': this machine has {count} CUDA device(s)")
    return device


def to_device(tensor: torch.Tensor, device: torch.device | str) -> torch.Tensor:
    """``tensor`` on ``device``; a CPU tensor goes to a CUDA device without stopping the host.

    A plain ``.to("cuda")`` of pageable host memory synchronizes the stream: the host waits
    until the GPU has run every queued kernel, so a training step that copies its cameras and
    images that way drains the GPU a dozen times. Here the tensor is staged in pinned memory
    (torch's caching host allocator keeps it alive until the copy has run) and copied without
    blocking, in stream order with the kernels that use it.
    """
    device = torch.device(device)
    if device.type != "cuda" or tensor.device.type != "cpu":
        return tensor.to(device)
    return tensor.pin_memory().to(device, non_blocking=True)


__all__ = ["DEVICE_HELP", "resolve_device", "to_device"]
