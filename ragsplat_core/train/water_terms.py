"""What a run trains of the water beside the Gaussians, each with its own Adam: the surface's calibrated
fields (`CalibratedWater`: level, n) and the terms of its optics (`LogTerm`: the attenuation c [3], the
backscatter [B_inf, c_b] [2, 3], the sky map the surface mirrors [S, S, 3]), each trained on its log so it
stays positive, clamped to the natural range of what it is (`config.py`). One interface, as the
densification strategy has one: a step after the Gaussians', the value as it stands, JSON, a checkpoint's
state."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import torch

from ragsplat.reflection import SKY_SIZE
from ragsplat.rendering import backscatter_json, reflection_json
from ragsplat.train.config import ATTENUATION_RANGE, BACKSCATTER_RANGE, SKY_RANGE, VEIL_RANGE, TrainConfig
from ragsplat.water_surface import WaterSurface

# every term a variant can train, in the order they step and render_splats takes them
TERM_NAMES = ("attenuation", "backscatter", "reflection")


class LogTerm:
    """A term of the water's optics as log values `log` (a Parameter) with its own Adam. `ranges`: one
    (low, high) for every value, or one per row of the first axis. `start` is its config.json entry at the
    start; `as_json` writes a value."""

    def __init__(self, label: str, log: torch.Tensor, lr: float, ranges: tuple, start,
                 as_json: Callable[[torch.Tensor], object]):
        self.label, self.start, self.as_json = label, start, as_json
        self.log = torch.nn.Parameter(log)
        self.ranges = ranges if isinstance(ranges[0], tuple) else (ranges,)
        self.opt = torch.optim.Adam([self.log], lr=lr, eps=1e-15)

    @property
    def value(self) -> torch.Tensor:  # as it stands now, no gradient
        return self.log.detach().exp()

    def step(self) -> None:
        self.opt.step()
        self.opt.zero_grad(set_to_none=True)
        with torch.no_grad():
            if len(self.ranges) == 1:
                self.log.clamp_(*(math.log(b) for b in self.ranges[0]))
            else:
                for row, bounds in enumerate(self.ranges):
                    self.log[row].clamp_(*(math.log(b) for b in bounds))

    def state(self) -> tuple[torch.Tensor, dict]:  # (its values, its optimizer's state) for a checkpoint
        return self.log.detach().cpu(), self.opt.state_dict()

    def load(self, values: torch.Tensor, opt_state: dict) -> None:
        with torch.no_grad():
            self.log.copy_(values)
        self.opt.load_state_dict(opt_state)


def water_terms(cfg: TrainConfig, device) -> dict[str, LogTerm]:
    """The terms `cfg`'s variant trains (`cfg.water_terms`), by name, in the order they step."""
    made = {
        "attenuation": lambda: LogTerm(
            "water attenuation (log)", torch.full((3,), math.log(cfg.attenuation_start), device=device),
            cfg.lr_attenuation, ATTENUATION_RANGE, [cfg.attenuation_start] * 3,
            lambda c: [float(x) for x in c]),
        "backscatter": lambda: LogTerm(
            "water backscatter (log)",
            torch.tensor([[cfg.veil_start] * 3, [cfg.backscatter_start] * 3], device=device).log(),
            cfg.lr_backscatter, (VEIL_RANGE, BACKSCATTER_RANGE),
            {"veil": [cfg.veil_start] * 3, "coefficients": [cfg.backscatter_start] * 3}, backscatter_json),
        "reflection": lambda: LogTerm(
            "water reflection sky (log)", torch.full((SKY_SIZE, SKY_SIZE, 3), math.log(cfg.sky_start),
                                                     device=device),
            cfg.lr_reflection, SKY_RANGE, {"sky": cfg.sky_start, "size": SKY_SIZE}, reflection_json),
    }
    return {name: made[name]() for name in TERM_NAMES if name in cfg.water_terms}


class CalibratedWater:
    """The water surface `start` with the fields `names` (of `cfg.water_params`) trained, on float64
    parameters (Adam's late steps are far below a float32 ulp of a level given in survey heights), with
    their own Adam; `surface()` is the water as it stands."""

    def __init__(self, start: WaterSurface | None, cfg: TrainConfig, device):
        self.start = start
        self.params = {k: torch.nn.Parameter(torch.tensor(float(getattr(start, k)), dtype=torch.float64,
                                                          device=device))
                       for k in cfg.water_params}
        self.opt = None if not self.params else torch.optim.Adam(
            [{"params": [p], "lr": getattr(cfg, f"lr_water_{k}"), "name": k} for k, p in self.params.items()],
            eps=1e-15)

    def surface(self, grad: bool = False) -> WaterSurface | None:
        if self.start is None:
            return None
        return replace(self.start, **{k: p if grad else float(p.detach()) for k, p in self.params.items()})

    def named(self) -> list[tuple[str, torch.nn.Parameter]]:  # named as in messages
        return [(f"water {k}", p) for k, p in self.params.items()]

    def step(self) -> None:
        self.opt.step()
        self.opt.zero_grad(set_to_none=True)
        with torch.no_grad():
            if "n" in self.params:  # the index of water relative to air: n < 1 is not a medium
                self.params["n"].clamp_(min=1.0)

    def state(self) -> tuple[dict, dict | None]:  # (its values, its optimizer's state) for a checkpoint
        return {k: p.detach().cpu() for k, p in self.params.items()}, \
            None if self.opt is None else self.opt.state_dict()

    def load(self, values: dict, opt_state: dict | None) -> None:
        with torch.no_grad():
            for k, p in self.params.items():  # the same config: the same calibrated fields
                p.copy_(values[k])
        if self.opt is not None:
            self.opt.load_state_dict(opt_state)
