"""The submerged Gaussians' colours' trend with depth moved into the water's attenuation (`detrend_albedo`):
a colour that starts from the images' (a track's) already holds the water's dimming, and without the
transfer c stays where it started."""

from __future__ import annotations

from collections.abc import Callable

import torch

from ragsplat.camera import Camera
from ragsplat.gaussians import SH_C0
from ragsplat.refraction import linear_to_srgb, srgb_to_linear, waterline_weight
from ragsplat.rendering import view_gaussians, visible_weights
from ragsplat.train.config import ATTENUATION_RANGE
from ragsplat.train.water_terms import LogTerm
from ragsplat.water_surface import WaterSurface

# The least spread (standard deviation, m) of the submerged Gaussians' depths over which their colours' trend
# with depth is taken for the water's: over a narrower range (a riffle, or a bed with one depth) the trend is
# as much the bed's pattern's, and the attenuation is left to the views.
TREND_SPREAD = 0.25
# The fit counts each Gaussian by the share of the images it makes (`visible_weights`, summed over TREND_VIEWS
# training views spread through the list): counted by opacity alone, the Gaussians the images hardly see
# (brighter at depth) balance the seen ones. The probes cost a render a view, so the weights are taken every
# TREND_EVERY steps (and after the strategy changes the Gaussians) while the transfer runs every step.
TREND_VIEWS = 8
TREND_EVERY = 100


def image_shares(splats, cameras: list[Camera], centers: list[torch.Tensor], water: WaterSurface,
                 flags: dict | None, surfels: bool, backend: str, compiled: bool = False,
                 masks: list[torch.Tensor | None] | None = None, depth: str = "ray") -> torch.Tensor:
    """[N] each Gaussian's share of the images the trend transfer counts it by: its `visible_weights` through
    `water` (`view_gaussians`' apparent Gaussians), summed over `TREND_VIEWS` of `cameras` spread evenly
    through the list (centres `centers`; over the pixels of `masks`, when given)."""
    total = torch.zeros(len(splats["means"]), device=splats["means"].device)
    for i in torch.linspace(0, len(cameras) - 1, min(TREND_VIEWS, len(cameras))).round().long().tolist():
        with torch.no_grad():
            g = view_gaussians(splats, centers[i], 0, water, flags, backend, surfels, compiled)
        total += visible_weights(g, cameras[i], surfels, backend, None if masks is None else masks[i], depth)
    return total


def albedo_trend(lin, depth, weight):
    """(b [3], spread [3]): the weighted least-squares slope b (1/m) of the log of the Gaussians' linear
    colours lin [M, 3] against their depth [M] (m), and the weighted standard deviation of the depths it was
    fitted over (m); weight [M] >= 0. Colours under 1e-3 are left out of the fit; b = 0 where the depths do
    not spread."""
    w = weight[:, None] * (lin > 1e-3)  # [M, 3]
    total = w.sum(0).clamp_min(1e-12)
    dx = depth[:, None] - (w * depth[:, None]).sum(0) / total  # [M, 3] from the weighted mean depth
    var = (w * dx * dx).sum(0)
    b = (w * dx * lin.clamp_min(1e-3).log()).sum(0) / var.clamp_min(1e-12)
    return torch.where(var > 1e-12, b, torch.zeros_like(b)), (var / total).sqrt()


class AlbedoTransfer:
    """The transfer after every step. `shares()`: [N] the current Gaussians' `image_shares` over the training
    views; `downwelling` k: metres of path per metre of depth beyond the depth itself, seen from above."""

    def __init__(self, shares: Callable[[], torch.Tensor], downwelling: float):
        self.shares, self.downwelling = shares, downwelling
        self._seen = None  # (the means parameter they were taken for, [N] `shares()`)

    def seen_weights(self, means: torch.Tensor, step: int) -> torch.Tensor:
        """[N] `shares()`, taken again on the first step of every `TREND_EVERY` and whenever the strategy has
        replaced the Gaussians (a refinement, a reset), else kept: a resumed run (from a checkpoint at a
        multiple of `TREND_EVERY`) takes them on the same steps as the uninterrupted one."""
        if self._seen is None or self._seen[0] is not means or (step - 1) % TREND_EVERY == 0:
            self._seen = (means, self.shares())
        return self._seen[1]

    def transfer(self, splats, water: WaterSurface, attenuation: LogTerm, step: int) -> None:
        """The trend b [3] of the submerged Gaussians' degree-0 colours (log colour per metre, `albedo_trend`)
        is what c (1 + k) d dims, so c rises by -b / (1 + k) (within `ATTENUATION_RANGE`) and each degree-0
        colour is raised by exp(dc (1 + k) d): a nadir view of a degree-0 bed renders the same, and what is
        left of the trend is the range's; only where the depths spread by `TREND_SPREAD` or more. The fit
        counts the Gaussians as opaque as the extraction keeps, each by its share of the images
        (`seen_weights`) and the water line's blend. Fitted on the degree-0 colours, not on the colours seen
        from straight above (sh0 with the SH's z terms), which lost cover on the field's development
        reach."""
        with torch.no_grad():
            depth = water.depth(splats["means"])  # [N], > 0 under the surface
            wet = torch.nonzero(depth > 0)[:, 0]
            if len(wet) < 2:
                return
            from ragsplat.surface import ExtractConfig

            d = depth[wet]
            srgb = SH_C0 * splats["sh0"][wet][:, 0] + 0.5  # [M, 3] the degree-0 colours
            opacity = torch.sigmoid(splats["opacities"][wet])
            # the bed the extraction keeps (a faint haze where the bed is lost does not count), as the images
            # see it (the Gaussians hidden under its skin do not count)
            weight = (self.seen_weights(splats["means"], step)[wet] * (opacity >= ExtractConfig.min_opacity)
                      * waterline_weight(d))
            lin = srgb_to_linear(srgb)  # converted once: the fit and the raise both work in linear light
            b, spread = albedo_trend(lin, d, weight)
            if not bool((spread >= TREND_SPREAD).any()):  # too narrow: the bed's pattern, not the water
                return
            k = 1 + self.downwelling
            c = attenuation.log.exp()
            raised = torch.where(spread >= TREND_SPREAD, c - b / k, c).clamp(*ATTENUATION_RANGE)
            attenuation.log.copy_(raised.log())
            lin = lin * torch.exp((raised - c) * k * d[:, None])
            splats["sh0"][wet] += ((linear_to_srgb(lin) - srgb) / SH_C0)[:, None]
