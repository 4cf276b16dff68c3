"""Refraction at a calm planar air-water interface."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class WaterSurface:
    """Horizontal water plane z = level (world metres) with refractive index n relative to air."""

    level: float = 0.0
    n: float = 1.33

    def __post_init__(self):
        if not math.isfinite(self.level):
            raise ValueError(f"water level must be finite, got {self.level}")
        if not (math.isfinite(self.n) and self.n >= 1.0):
            raise ValueError(f"refractive index must be finite and >= 1, got {self.n}")
