"""omg4: Optimized Minimal 4D Gaussian Splatting (OMG4, ICLR 2026) on Real-Time4DGS and FreeTimeGS.

Train a baseline from multi-view video, compress it with every OMG4 stage into one ``.omg4`` file,
decode that file alone, render and evaluate it. The public API (:mod:`omg4.api`, ``docs/api.md``) is
importable from here; it is loaded on first use, so ``import omg4`` and the ``omg4`` command start fast.
"""

from __future__ import annotations

import importlib

__version__ = "0.2.0"

#: public name → the module that defines it
_PUBLIC = {
    **dict.fromkeys(("synthesize_scene", "load_scene", "train_config", "train_baseline", "train_segments",
                     "load_baseline", "compress_to_file", "compress_segments", "load_model", "render_frame",
                     "evaluate_model", "Scene", "Camera", "TrainConfig", "CompressConfig", "TrainResult"), "omg4.api"),
    "View": "omg4.data.scene",
    "prepare_capture": "omg4.prepare.pipeline",
    "MergeConfig": "omg4.compress.merge_clusters",
    "StageLengths": "omg4.compress.schedule",
    "CompactGrids": "omg4.codec.payload",
    "Gaussians4D": "omg4.gaussians.model",
    "GaussianConfig": "omg4.gaussians.model",
    "Backbone": "omg4.gaussians.backbone",
    "BACKBONES": "omg4.gaussians.backbone",
    "register_backbone": "omg4.gaussians.backbone",
    "DensityStrategy": "omg4.train.strategies",
    "using_kernels": "omg4.kernels",
    "OMG4Error": "omg4.errors",
    "CorruptFileError": "omg4.errors",
}

__all__ = ["__version__", *_PUBLIC]


def __getattr__(name: str):
    if name in _PUBLIC:
        value = getattr(importlib.import_module(_PUBLIC[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'omg4' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
