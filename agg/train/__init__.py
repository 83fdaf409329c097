"""Training: the Tick-Tock schedule, losses, densification, topology evolution, the training loop and the
reconstruction entry point (``reconstruct``)."""

from agg.train.config import PRESETS, TrainConfig, get_preset
from agg.train.reconstruct import reconstruct
from agg.train.trainer import Cancelled, Trainer

__all__ = ["PRESETS", "TrainConfig", "get_preset", "reconstruct", "Trainer", "Cancelled"]
