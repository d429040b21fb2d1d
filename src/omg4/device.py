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


__all__ = ["DEVICE_HELP", "resolve_device"]
