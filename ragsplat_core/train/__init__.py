"""RA-GS training: `config` (variants, TrainConfig, presets), `strategy` (densification), `trainer`."""

from ragsplat_core.train.config import PRESETS, VARIANTS, TrainConfig, preset_config
from ragsplat_core.train.trainer import Trainer

__all__ = ["PRESETS", "VARIANTS", "TrainConfig", "Trainer", "preset_config"]
