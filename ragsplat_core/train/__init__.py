"""RA-GS training: `config` (variants, TrainConfig, presets), `strategy` (densification), `trainer`."""

from ragsplat.train.config import PRESETS, VARIANTS, TrainConfig, preset_config
from ragsplat.train.trainer import Trainer

__all__ = ["PRESETS", "VARIANTS", "TrainConfig", "Trainer", "preset_config"]
