"""Training of the Real-Time4DGS baseline (rt4dgs §3)."""

from omg4.train.config import PRESETS, TrainConfig, make_config
from omg4.train.trainer import TrainResult, Trainer, train

__all__ = ["PRESETS", "TrainConfig", "make_config", "TrainResult", "Trainer", "train"]
