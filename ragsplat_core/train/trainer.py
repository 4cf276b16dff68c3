"""RA-GS training: 3D Gaussian splatting with the per-view refraction transform plugged in before rasterizing.

Programmatic use (what `ragsplat train` and the ablation harness do):

    cfg = preset_config("small", variant="full", seed=0)
    trainer = Trainer(cfg, load_dataset(data_dir), out_dir)      # resumes from out_dir/ckpt.pt if present
    trainer.train(callbacks=[fn], eval_steps=[250, 500, 1000])   # fn(trainer, step) at those steps + the end
    image, alpha, depth = trainer.render(camera, interface=False)  # "without the interface": true Gaussians

`trainer.elapsed` is the training wall-clock time in seconds, excluding the time spent inside callbacks
and checkpoint writes, so error-against-time curves are not inflated by evaluation; `trainer.cpu_elapsed`
is the CPU time of the process (all threads) over the same steps, and `trainer.step_seconds` the wall
time of each step (a shared machine moves the wall clock; CPU time and the median step much less).

Outputs in out_dir: `config.json` (resolved config, seed, versions, variant flags, the water and a variant's
attenuation, backscatter and sky at the start and, once finished, at the end), `ckpt.pt` (latest checkpoint),
`point_cloud.ply` (standard 3DGS PLY), `train_stats.json` (time, Gaussian count, last loss, final water,
attenuation, backscatter and sky).

The water is the dataset's unless the config overrides its level or n; `optimize_water` calibrates it (own
Adam, frozen for the warm-up), and `trainer.water` is always the current one. A variant with water terms
(`WATER_TERMS`) also trains the water's attenuation coefficients (`trainer.attenuation`, own Adam on
log c, clamped to `ATTENUATION_RANGE`) and the water column's backscatter (`trainer.backscatter`: B_inf and
c_b, own Adam on their logs, clamped to `VEIL_RANGE` and `BACKSCATTER_RANGE`; the veil is added to the render,
`rendering.render_splats`) and the sky the surface mirrors (`trainer.reflection`: a map of linear radiance,
own Adam on its log, clamped to `SKY_RANGE`; Fresnel-weighted over the wet pixels, `rendering.render_splats`),
each only where its variant has it, saved in the checkpoint and in config.json (`attenuation_final`,
`backscatter_final`, `reflection_final`: what `runs.Model` renders with). A view with a mask trains on its
used pixels only.
"""

from __future__ import annotations

import math
import pickle
import time
from collections.abc import Callable
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import torch

from ragsplat.camera import Camera
from ragsplat.dataset import layout
from ragsplat.dataset.load import Dataset
from ragsplat.errors import ConfigError, DatasetError, OutputError, TrainingDiverged
from ragsplat.gaussians import PARAM_NAMES, SH_C0, init_grid, init_points
from ragsplat.outputs import atomic_path, claim, versions, write_json
from ragsplat.ply import save_ply
from ragsplat.rasterize import choose_backend
from ragsplat.rasterize_surfels import depth_normals
from ragsplat.reflection import SKY_SIZE
from ragsplat.refraction import (
    WaterSurface,
    facet_offsets,
    linear_to_srgb,
    opacity_factor,
    srgb_to_linear,
    waterline_weight,
)
from ragsplat.rendering import (
    backscatter_json,
    fades_opacity,
    median_depth,
    reflection_json,
    render_splats,
    view_gaussians,
    visible_weights,
)
from ragsplat.snell import footprint
from ragsplat.ssim import psnr, ssim, ssim_map
from ragsplat.train.config import (
    ATTENUATION_RANGE,
    BACKSCATTER_RANGE,
    RUN_ONLY,
    SKY_RANGE,
    VARIANTS,
    VEIL_RANGE,
    TrainConfig,
)
from ragsplat.train.strategy import DefaultStrategy

CHECKPOINT = "ckpt.pt"
# No camera sees a bed deeper than this many times its height above the water through clear water (light,
# not geometry, limits photogrammetric bathymetry to a few tens of metres).
MAX_DEPTH_PER_HEIGHT = 10
PLY = "point_cloud.ply"
# The least spread (standard deviation, m) of the submerged Gaussians' depths over which their colours' trend
# with depth is taken for the water's (`Trainer._detrend_albedo`): over a narrower range (a riffle, or a bed
# with one depth) the trend is as much the bed's pattern's, and the attenuation is left to the views (the
# field development reach's wet cells: 0.80 m).
TREND_SPREAD = 0.25
# The fit counts each Gaussian by the share of the images it makes (`visible_weights`, summed over TREND_VIEWS
# training views spread through the list). Counted by opacity alone, the Gaussians the images hardly see
# (brighter at depth) balanced the seen ones, whose colours still darkened by 0.10-0.11 per metre at the end,
# and c stopped at 70 % of the water's in green and 82 % in blue (the field development reach;
# `python -m tools.attenuation`). The probes cost about 0.2 s a view at 40k Gaussians on one CPU thread, so
# the weights are taken every TREND_EVERY steps (and after the strategy changes the Gaussians) while the
# transfer runs every step. (Moved every 100 steps instead, at 68eef96, the development reach at twice the
# field's turbidity lost its pool to faint, bright Gaussians: 76.9 at 3 %, cover 62 %; c and the colours
# jumping at each move was the suspect.)
TREND_VIEWS = 8
TREND_EVERY = 100
# Kept as the third scale of a surfel so that code written for three axes (a split's offsets, the volume
# sampling of `surface.py`) treats it as the flat disk it renders as.
SURFEL_THICKNESS = 1e-5  # metres


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


class Trainer:
    """Holds the Gaussians, their optimisers and the densification state for one run (one variant).

    `view_ripples(name, xy [M, 2]) -> [M, 2]`: the gradient of training view `name`'s own water surface at
    horizontal points, given (a bound: `tools.tune --true-ripples` gives the photos' true ripples); each
    training render then shows the Gaussians as that surface would (`facet_offsets`). None: the one surface
    every view shares. A horizontal surface only."""

    def __init__(self, cfg: TrainConfig, dataset: Dataset, out_dir: str | Path | None = None,
                 resume: bool = True,
                 view_ripples: Callable[[str, torch.Tensor], torch.Tensor] | None = None):
        self.cfg = cfg
        self.view_ripples = view_ripples
        self.ds = dataset
        self.out = None if out_dir is None else Path(out_dir)
        try:
            self.device = torch.device(("cuda" if torch.cuda.is_available() else "cpu")
                                       if cfg.device == "auto" else cfg.device)
        except RuntimeError:
            raise ConfigError(f"unknown torch device {cfg.device!r} (e.g. cpu, cuda, cuda:1)") from None
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ConfigError(f"device {cfg.device!r} requested but CUDA is not available here")
        choose_backend(cfg.backend, self.device)  # an impossible backend is refused before any work
        self.views = dataset.train
        if not self.views:
            raise DatasetError(f"{dataset.root}: the dataset has no training views")
        self._water0 = self._start_water()
        if view_ripples is not None and (self._water0 is None or self._water0.tilted or self._water0.curved):
            raise ConfigError("view_ripples: a dataset with a horizontal water surface only")
        # The calibrated fields of the water (float64: Adam's late steps are far below a float32 ulp of a
        # level given in survey heights); a resumed run overwrites their values.
        self.water_params = {k: torch.nn.Parameter(torch.tensor(float(getattr(self._water0, k)),
                                                                dtype=torch.float64, device=self.device))
                             for k in cfg.water_params}
        self.water_opt = self._make_water_optimizer()
        flags = VARIANTS[cfg.variant]
        # A dry scene (or n = 1 that is not calibrated) trains as plain 3DGS: the transform is skipped, not
        # run as an identity.
        self.flags = None if (flags is None or self._water0 is None or
                              (self._water0.n == 1 and "n" not in self.water_params)) else flags
        # The water's attenuation, log c [3] (c > 0), only where the water is modelled: otherwise no
        # parameter, no optimizer, not one op. A resumed run overwrites its values.
        self.log_attenuation = None
        if self.flags is not None and "attenuation" in cfg.water_terms:
            self.log_attenuation = torch.nn.Parameter(torch.full((3,), math.log(cfg.attenuation_start),
                                                                 device=self.device))
        self.attenuation_opt = None if self.log_attenuation is None else \
            torch.optim.Adam([self.log_attenuation], lr=cfg.lr_attenuation, eps=1e-15)
        self._seen = None  # (the means parameter they were taken for, [N] `_visible_weights`) of the transfer
        # The backscatter, log [B_inf, c_b] [2, 3] (both > 0), on the same terms.
        self.log_backscatter = None
        if self.flags is not None and "backscatter" in cfg.water_terms:
            start = torch.tensor([[cfg.veil_start] * 3, [cfg.backscatter_start] * 3], device=self.device)
            self.log_backscatter = torch.nn.Parameter(start.log())
        self.backscatter_opt = None if self.log_backscatter is None else \
            torch.optim.Adam([self.log_backscatter], lr=cfg.lr_backscatter, eps=1e-15)
        # The sky the surface mirrors, log radiance [S, S, 3], on the same terms.
        self.log_sky = None
        if self.flags is not None and "reflection" in cfg.water_terms:
            self.log_sky = torch.nn.Parameter(torch.full((SKY_SIZE, SKY_SIZE, 3), math.log(cfg.sky_start),
                                                         device=self.device))
        self.sky_opt = None if self.log_sky is None else \
            torch.optim.Adam([self.log_sky], lr=cfg.lr_reflection, eps=1e-15)
        self.targets = [v.image.to(self.device) for v in self.views]  # [H, W, 3] each
        self.masks = [None if v.mask is None else v.mask.to(self.device) for v in self.views]  # [H, W] bool
        self.centers = [torch.tensor(v.camera.camera_center, dtype=torch.float32, device=self.device)
                        for v in self.views]
        self.background = torch.tensor(cfg.background, dtype=torch.float32, device=self.device)
        self.scene_scale = dataset.camera_extent() if cfg.scene_scale is None else cfg.scene_scale
        self.schedule = cfg.schedule
        self.gen = torch.Generator().manual_seed(cfg.seed)  # view order and split samples
        # pruning and resets test the opacity as rendered (through the water for a variant that fades it)
        self.strategy = DefaultStrategy(self.schedule, self.gen,
                                        (lambda means: opacity_factor(means, self.water))
                                        if fades_opacity(self.flags) else None)
        self.step = 0
        self.elapsed = 0.0
        self.cpu_elapsed = 0.0
        self.step_seconds: list[float] = []
        self.last = {}  # last step's loss / psnr
        self._order: list[int] = []
        self.extended_from: int | None = None  # a resumed run's old iteration count, when extended
        if self.out is not None:
            claim(self.out, "train run", legacy=(CHECKPOINT,))
        if resume and self.out is not None and (self.out / CHECKPOINT).exists():
            self._load(self.out / CHECKPOINT)
        else:
            torch.manual_seed(cfg.seed)
            self.splats = self._init_splats().to(self.device)
            self._flatten_surfels()
            self.optimizers = self._make_optimizers()
            self.strat_state = self.strategy.initialize_state(self.scene_scale)
        self.strategy.check_sanity(self.splats, self.optimizers)

    # ---- setup ------------------------------------------------------------------------------------
    def _start_water(self) -> WaterSurface | None:
        """The dataset's water with the config's overrides (None: train without water)."""
        cfg, water = self.cfg, self.ds.water
        if water is None and cfg.water_level is None:
            if cfg.water_n is not None or cfg.water_params:
                raise ConfigError(f"{self.ds.root}: the dataset has no water; give its level (water_level, "
                                  f"--water-level) to {'calibrate' if cfg.water_params else 'set n'}")
            return None
        given = {"level": cfg.water_level, "n": cfg.water_n,
                 "slope": None if cfg.water_slope is None else tuple(cfg.water_slope)}
        water = replace(water or WaterSurface(), **{k: v for k, v in given.items() if v is not None})
        self._check_cameras_above(water, ConfigError)
        return water

    def _check_cameras_above(self, water: WaterSurface, error: type) -> None:
        """Every training camera in air above `water`; else `error` in one line (refraction needs it)."""
        centres = np.array([v.camera.camera_center for v in self.views])
        i = int(np.argmax(water.depth(centres)))
        if not water.depth(centres[i]) < 0:
            raise error(f"the water surface ({float(water.height(centres[i, :2])):g} m there) is not below "
                        f"every training camera ({self.views[i].name} is at {centres[i, 2]:g} m): refraction "
                        f"needs the cameras in air")

    @property
    def water(self) -> WaterSurface | None:
        """The water as it stands now: the dataset's, overridden by the config, moved by calibration."""
        return self._water(grad=False)

    def _water(self, grad: bool) -> WaterSurface | None:
        if self._water0 is None:
            return None
        return replace(self._water0,
                       **{k: p if grad else float(p.detach()) for k, p in self.water_params.items()})

    def _init_splats(self) -> torch.nn.ParameterDict:
        cfg = self.cfg
        if cfg.init in ("points", "triangulated", "refracted"):
            from ragsplat.dataset.colmap import refracted_points, triangulated_points
            from ragsplat.tracks import fill_gaps

            if cfg.init == "refracted":
                if self.water is None:
                    raise ConfigError("init='refracted' intersects rays through the water: the dataset has "
                                      "none")
                arr = refracted_points(self.ds.root, self.ds.fingerprint,
                                       {v.file_path: v.camera for v in self.views}, self.water)
            else:
                source = triangulated_points(self.ds.root, self.ds.fingerprint) \
                    if cfg.init == "triangulated" else Path(cfg.init_points)
                if not source.is_file():
                    raise ConfigError(f"{source}: point cloud file is missing")
                arr = np.load(source)
                if arr.ndim != 2 or arr.shape[1] not in (3, 6):
                    raise ConfigError(f"{source}: expected an array [N, 3] or [N, 6], got {arr.shape}")
            if len(arr) > cfg.init_count:  # a survey's model can hold millions: a seeded random subset
                arr = arr[np.sort(
                    np.random.default_rng(cfg.seed).choice(len(arr), cfg.init_count, replace=False))]
            if cfg.init_fill > 0:  # after the cap: it fills the gaps of the points actually used
                arr = np.concatenate([arr, fill_gaps(arr, cfg.init_fill)])
            pts = torch.from_numpy(arr[:, :3]).float()
            rgb = torch.from_numpy(arr[:, 3:]).float() if arr.shape[1] == 6 else torch.full_like(pts, 0.5)
            # straight-ray points sit at apparent depths (x n, the field's correction);
            # refracted ones are true
            return init_points(pts, rgb, None if cfg.init == "refracted" else self.water, cfg.sh_degree,
                               cfg.init_opacity)
        bed = self.ds.bed
        depth = cfg.init_depth if cfg.init_depth is not None else bed.depth
        if depth is None:
            raise ConfigError("grid initialisation needs the bed depth: scene.json has no spec.bed.depth, "
                              "give init_depth (--init-depth)")
        water = self.water or WaterSurface(0.0, 1.0)
        centres = np.array([v.camera.camera_center for v in self.views])
        # the plane's height under the flight
        z = float(water.height(np.median(centres[:, :2], axis=0))) - depth
        height = float(-water.depth(centres).max())
        # e.g. a depth given in mm: the grid would be kilometres wide
        if depth > MAX_DEPTH_PER_HEIGHT * height:
            raise ConfigError(f"init depth {depth:g} m is more than {MAX_DEPTH_PER_HEIGHT}x the cameras' "
                              f"height above the water ({height:.3g} m); give the bed depth in metres below "
                              "the water level (--init-depth)")
        # Everything the training views see of the plane (images are filled with bed to their edges, and
        # an uncovered part would render as background), clipped to the bed when its size is known.
        try:
            box = footprint([v.camera for v in self.views], self.water, z)
        except ValueError as err:
            raise DatasetError(f"{self.ds.root}: {err}") from None
        if bed.size is not None:
            h = bed.size / 2
            box = (max(box[0], -h), min(box[1], h), max(box[2], -h), min(box[3], h))
            if box[0] >= box[1] or box[2] >= box[3]:
                raise DatasetError(f"{self.ds.root}: the training views do not see the {bed.size} m bed "
                                   f"at depth {depth} m")
        spacing = math.sqrt((box[1] - box[0]) * (box[3] - box[2]) / cfg.init_count)
        splats = init_grid(*box, z, spacing, cfg.sh_degree, cfg.init_opacity)
        if water.tilted:  # the start follows the surface: `depth` below it everywhere
            with torch.no_grad():
                means = splats["means"]
                means[:, 2] = water.height(means[:, :2].double()).to(means) - depth
        return splats

    def _lr(self, name: str) -> float:
        c = self.cfg
        return {"means": c.lr_means * self.scene_scale, "scales": c.lr_scales, "quats": c.lr_quats,
                "opacities": c.lr_opacities, "sh0": c.lr_sh0, "shN": c.lr_shN}[name]

    def _make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        # one Adam per parameter (gsplat's layout): the strategy swaps tensors one optimiser at a time.
        # fused: one kernel per step instead of about ten ops (on the 2-core CPU 3 ms instead of 12 at 40k)
        return {k: torch.optim.Adam([{"params": [p], "lr": self._lr(k), "name": k}], eps=1e-15, fused=True)
                for k, p in self.splats.items()}

    def _make_water_optimizer(self) -> torch.optim.Optimizer | None:
        if not self.water_params:
            return None
        return torch.optim.Adam([{"params": [p], "lr": getattr(self.cfg, f"lr_water_{k}"), "name": k}
                                 for k, p in self.water_params.items()], eps=1e-15)

    def means_lr(self, step: int) -> float:
        """3DGS's exponential (log-linear) decay of the position learning rate over the run."""
        c = self.cfg
        t = min(step / c.iterations, 1.0)
        return self.scene_scale * math.exp((1 - t) * math.log(c.lr_means) + t * math.log(c.lr_means_final))

    @property
    def attenuation(self) -> torch.Tensor | None:
        """The water's attenuation coefficients c [3] (1/m, linear RGB) as they stand now, None when not
        trained."""
        return None if self.log_attenuation is None else self.log_attenuation.detach().exp()

    @property
    def backscatter(self) -> torch.Tensor | None:
        """[2, 3] the water's veil B_inf (linear RGB) and its coefficients c_b (1/m) as they stand now, None
        when not trained."""
        return None if self.log_backscatter is None else self.log_backscatter.detach().exp()

    @property
    def reflection(self) -> torch.Tensor | None:
        """[S, S, 3] the sky map the surface mirrors (linear radiance) as it stands now, None when not
        trained."""
        return None if self.log_sky is None else self.log_sky.detach().exp()

    @property
    def active_sh_degree(self) -> int:
        return self.cfg.active_sh_degree(self.step)

    @property
    def num_gaussians(self) -> int:
        return int(self.splats["means"].shape[0])

    # ---- rendering ----------------------------------------------------------------------------------
    def _render(self, camera: Camera, center: torch.Tensor, interface: bool, water: WaterSurface | None,
                splats: dict | None = None):  # splats: the Gaussians to render, self.splats when None
        attenuation = None if self.log_attenuation is None or not interface else self.log_attenuation.exp()
        backscatter = None if self.log_backscatter is None or not interface else self.log_backscatter.exp()
        sky = None if self.log_sky is None or not interface else self.log_sky.exp()
        return render_splats(self.splats if splats is None else splats, camera, center, self.active_sh_degree,
                             water, self.flags if interface else None, self.cfg.surfels, self.background,
                             self.cfg.backend, self.cfg.compile_refraction, attenuation, backscatter, sky,
                             self.cfg.wet_sh_degree, self.cfg.surfel_depth, self.cfg.downwelling)

    def render(self, camera: Camera, interface: bool = True):
        """(image [H,W,3], alpha [H,W,1], depth [H,W,1]) of `camera`, no gradients.

        interface=True: through the water as trained (apparent Gaussians); False: the true Gaussians with
        their own colours (for full+color the true albedo): the scene "without the interface".
        """
        center = torch.tensor(camera.camera_center, dtype=torch.float32, device=self.device)
        with torch.no_grad():
            img, alpha, depth, _ = self._render(camera, center, interface, self.water)
        return img.clamp(0, 1), alpha, depth

    # ---- training -------------------------------------------------------------------------------------
    def _next_view(self) -> int:
        if not self._order:  # a fresh random pass over the training views (3DGS)
            self._order = torch.randperm(len(self.views), generator=self.gen).tolist()
        return self._order.pop()

    def train_step(self) -> dict:
        """One optimisation step on one training view; returns {loss, psnr, n}."""
        self.step += 1
        step = self.step
        i = self._next_view()
        cam, gt, mask = self.views[i].camera, self.targets[i], self.masks[i]
        calibrate = self.water_opt is not None and step > self.cfg.water_start
        water = self._water(calibrate)
        img, _, depth, info = self._render(cam, self.centers[i], True, water, self._rippled(i, water))
        lam = self.cfg.ssim_lambda
        if mask is None:
            l1 = torch.abs(img - gt).mean()
            loss = (1 - lam) * l1 + lam * (1 - ssim(img, gt))
        else:
            # SSIM windows straddle the mask's edge: both images are zeroed outside it, so neither the
            # unused target pixels nor the render there reach the loss, and the map is averaged where used.
            l1 = torch.abs(img - gt)[mask].mean()
            both = [torch.where(mask[..., None], x, 0.0) for x in (img, gt)]
            loss = (1 - lam) * l1 + lam * (1 - ssim_map(*both)[0][:, mask].mean())
        if self.cfg.surfels:
            loss = loss + self._surfel_loss(cam, depth, info, mask, step)
        if not torch.isfinite(loss):
            raise TrainingDiverged(f"iteration {step}: loss is {float(loss.detach())} (view "
                                   f"{self.views[i].name}); {self._nonfinite_report()}")
        info.update(width=cam.width, height=cam.height)
        self.strategy.step_pre_backward(self.splats, self.optimizers, self.strat_state, step, info)
        loss.backward()
        # one reduction per tensor: a sum is finite only if every element is (gradients and parameters are
        # far too small to overflow float32 when added up)
        for name, p in (*self.splats.items(), *self._water_named()):
            if p.grad is not None and not torch.isfinite(p.grad.sum()):
                cause = self._nonfinite_report()  # a bad parameter poisons the others' gradients: name it
                raise TrainingDiverged(f"iteration {step}: "
                                       + (f"{cause} before the optimizer step" if cause else
                                          f"non-finite gradient of parameter '{name}' "
                                          f"({int((~torch.isfinite(p.grad)).sum())} values)"))
        self.optimizers["means"].param_groups[0]["lr"] = self.means_lr(step)
        for opt in self.optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        if self.attenuation_opt is not None:
            self._attenuation_step()
            if self.cfg.detrend_albedo:
                self._detrend_albedo()
        if self.backscatter_opt is not None:
            self._backscatter_step()
        if self.sky_opt is not None:
            self._sky_step()
        if calibrate:
            self._water_step(step)
        bad = self._nonfinite_report()
        if bad:
            raise TrainingDiverged(f"iteration {step}: {bad} after the optimizer step")
        self.strategy.step_post_backward(self.splats, self.optimizers, self.strat_state, step, info)
        self._flatten_surfels()  # a split divides all three scales
        shown = (img.detach(), gt) if mask is None else (img.detach()[mask], gt[mask])
        self.last = {"loss": float(loss.detach()), "psnr": float(psnr(*shown)), "n": self.num_gaussians}
        return self.last

    def _rippled(self, i: int, water: WaterSurface) -> dict | None:
        """The Gaussians as training view i's own surface (`view_ripples`) shows them: each submerged mean
        moved back by its `facet_offsets` (the surface is given: no gradient through the offsets); None
        without `view_ripples`."""
        if self.view_ripples is None:
            return None
        means = self.splats["means"]
        with torch.no_grad():
            moved = facet_offsets(means, self.centers[i], water,
                                  lambda xy: self.view_ripples(self.views[i].name, xy))
        return {**self.splats, "means": means - torch.cat([moved, torch.zeros_like(moved[:, :1])], -1)}

    def _flatten_surfels(self) -> None:
        """The third axis of a surfel is its normal: no thickness, no gradient. Kept at `SURFEL_THICKNESS`
        so that the extraction, which samples in proportion to volume, weighs every surfel by its area."""
        if self.cfg.surfels:
            with torch.no_grad():
                self.splats["scales"][:, 2] = math.log(SURFEL_THICKNESS)

    def median_depth(self, camera: Camera) -> torch.Tensor:  # [H, W], see `median_depth`
        return median_depth(self.splats, camera, self.cfg.surfels,
                            self.water if fades_opacity(self.flags) else None, self.cfg.backend)

    def _surfel_loss(self, cam: Camera, depth, info: dict, mask, step: int):
        """2DGS's geometry terms over the used pixels: depth distortion, and normal consistency between the
        rendered normals and those of the rendered depth map (both in the space the camera sees: apparent
        under water, where the apparent bed is a surface too)."""
        c = self.cfg
        loss = depth.new_zeros(())
        used = (lambda x: x.reshape(-1)) if mask is None else (lambda x: x[mask])
        if step > c.distortion_from * c.iterations:
            loss = loss + c.lambda_distortion * used(info["distortion"][..., 0]).mean()
        if step > c.normal_from * c.iterations:
            from_depth = depth_normals(depth[..., 0], cam)  # [H, W, 3] unit, zero where undefined
            loss = loss + c.lambda_normal * used(1 - (info["normals"] * from_depth).sum(-1)).mean()
        return loss

    def _water_named(self):  # (name, parameter) of the trained water fields and terms, named as in messages
        terms = [] if self.log_attenuation is None else [("water attenuation (log)", self.log_attenuation)]
        terms += [] if self.log_backscatter is None else [("water backscatter (log)", self.log_backscatter)]
        terms += [] if self.log_sky is None else [("water reflection sky (log)", self.log_sky)]
        return [(f"water {k}", p) for k, p in self.water_params.items()] + terms

    def _attenuation_step(self) -> None:
        self.attenuation_opt.step()
        self.attenuation_opt.zero_grad(set_to_none=True)
        with torch.no_grad():  # natural waters' range: no black water, none clearer than the clearest ocean
            self.log_attenuation.clamp_(*(math.log(c) for c in ATTENUATION_RANGE))

    def _detrend_albedo(self) -> None:
        """Moves the submerged Gaussians' colours' trend with depth into the attenuation (`detrend_albedo`):
        the trend b [3] of their degree-0 colours (log colour per metre, `albedo_trend`) is what c (1 + k) d
        dims, k the downwelling, so c rises by -b / (1 + k) (within `ATTENUATION_RANGE`) and each degree-0
        colour is raised by exp(dc (1 + k) d): a nadir view of a degree-0 bed renders the same, and what is
        left of the trend is the range's; only where the depths spread by `TREND_SPREAD` or more. The fit
        counts the Gaussians as opaque as the extraction keeps, each by its share of the images
        (`_seen_weights`) and the water line's blend. Without the transfer a colour that starts from the
        images' (a track's) already holds the water's dimming, and c stays where it started. (Fitted on the
        colours seen from straight above, sh0 with the SH's z terms, it lost 9.5 points of cover on the
        field's development reach.)"""
        with torch.no_grad():
            depth = self.water.depth(self.splats["means"])  # [N], > 0 under the surface
            wet = torch.nonzero(depth > 0)[:, 0]
            if len(wet) < 2:
                return
            from ragsplat.surface import ExtractConfig

            d = depth[wet]
            srgb = SH_C0 * self.splats["sh0"][wet][:, 0] + 0.5  # [M, 3] the degree-0 colours
            opacity = torch.sigmoid(self.splats["opacities"][wet])
            # the bed the extraction keeps (a faint haze where the bed is lost does not count), as the images
            # see it (the Gaussians hidden under its skin do not count)
            weight = (self._seen_weights()[wet] * (opacity >= ExtractConfig.min_opacity)
                      * waterline_weight(d))
            lin = srgb_to_linear(srgb)  # converted once: the fit and the raise both work in linear light
            b, spread = albedo_trend(lin, d, weight)
            if not bool((spread >= TREND_SPREAD).any()):  # too narrow: the bed's pattern, not the water
                return
            k = 1 + self.cfg.downwelling  # metres of path per metre of depth, seen from above
            c = self.log_attenuation.exp()
            raised = torch.where(spread >= TREND_SPREAD, c - b / k, c).clamp(*ATTENUATION_RANGE)
            self.log_attenuation.copy_(raised.log())
            lin = lin * torch.exp((raised - c) * k * d[:, None])
            self.splats["sh0"][wet] += ((linear_to_srgb(lin) - srgb) / SH_C0)[:, None]

    def _seen_weights(self) -> torch.Tensor:
        """[N] `_visible_weights`, taken again on the first step of every `TREND_EVERY` and whenever the
        strategy has replaced the Gaussians (a refinement, a reset), else kept: a resumed run (from a
        checkpoint at a multiple of `TREND_EVERY`) takes them on the same steps as the uninterrupted one."""
        means = self.splats["means"]
        if self._seen is None or self._seen[0] is not means or (self.step - 1) % TREND_EVERY == 0:
            self._seen = (means, self._visible_weights())
        return self._seen[1]

    def _visible_weights(self) -> torch.Tensor:
        """[N] `image_shares` over the training views (the used pixels of each)."""
        return image_shares(self.splats, [v.camera for v in self.views], self.centers, self.water, self.flags,
                            self.cfg.surfels, self.cfg.backend, self.cfg.compile_refraction, self.masks,
                            self.cfg.surfel_depth)

    def _backscatter_step(self) -> None:
        self.backscatter_opt.step()
        self.backscatter_opt.zero_grad(set_to_none=True)
        with torch.no_grad():  # natural waters' ranges (config)
            for row, bounds in enumerate((VEIL_RANGE, BACKSCATTER_RANGE)):
                self.log_backscatter[row].clamp_(*(math.log(b) for b in bounds))

    def _sky_step(self) -> None:
        self.sky_opt.step()
        self.sky_opt.zero_grad(set_to_none=True)
        with torch.no_grad():  # a sky's range (config)
            self.log_sky.clamp_(*(math.log(b) for b in SKY_RANGE))

    def _water_step(self, step: int) -> None:
        self.water_opt.step()
        self.water_opt.zero_grad(set_to_none=True)
        with torch.no_grad():
            if "n" in self.water_params:  # the index of water relative to air: n < 1 is not a medium
                self.water_params["n"].clamp_(min=1.0)
        self._check_cameras_above(self.water, TrainingDiverged)  # a calibrated level that rose above them

    def _nonfinite_report(self) -> str:
        for name in PARAM_NAMES:
            if name in self.splats and not torch.isfinite(self.splats[name].detach().sum()):
                count = int((~torch.isfinite(self.splats[name])).sum())
                return f"non-finite values in parameter '{name}' ({count} of {self.splats[name].numel()})"
        for name, p in self._water_named():
            if not torch.isfinite(p.detach()).all():
                return f"non-finite value of parameter '{name}'"
        return ""

    def train(self, callbacks: list[Callable[[Trainer, int], None]] = (), eval_steps=(),
              on_step: Callable[[Trainer], None] | None = None) -> dict:
        """Train up to cfg.iterations (continuing from a resumed step); returns the final stats.

        `callbacks` run at each step in `eval_steps` and once at the end, outside the timed region.
        `on_step(trainer)` runs after every step (progress display), also outside the timed region; a
        KeyboardInterrupt raised there (or arriving between steps) saves a checkpoint of the finished steps
        before it propagates.
        """
        cfg = self.cfg
        marks = {int(s) for s in eval_steps if self.step < int(s) <= cfg.iterations}
        if self.out is not None:
            self.out.mkdir(parents=True, exist_ok=True)
            self._write_config()
        every = cfg.checkpoint_interval
        in_step = False
        try:
            while self.step < cfg.iterations:
                t0, c0 = time.perf_counter(), time.process_time()
                in_step = True
                self.train_step()
                in_step = False
                if self.device.type == "cuda":
                    torch.cuda.synchronize(self.device)
                dt = time.perf_counter() - t0
                self.elapsed += dt
                self.cpu_elapsed += time.process_time() - c0
                self.step_seconds.append(dt)
                if on_step is not None:
                    on_step(self)
                if self.step in marks and self.step < cfg.iterations:
                    for cb in callbacks:
                        cb(self, self.step)
                if self.out is not None and every and self.step % every == 0:
                    self.save_checkpoint()
        except KeyboardInterrupt:
            if self.out is not None and not in_step:  # a step cut in half would save a half-updated state
                self.save_checkpoint()
            raise
        if self.out is not None:
            self.save_checkpoint()
            save_ply(self.out / PLY, self.splats)
            self._write_config()  # now with the final water
        stats = self.stats()
        if self.out is not None:
            write_json(self.out / "train_stats.json", stats, indent=1)
        for cb in callbacks:
            cb(self, self.step)
        return stats

    def stats(self) -> dict:
        return {"variant": self.cfg.variant, "seed": self.cfg.seed, "iterations": self.step,
                "train_seconds": self.elapsed, "train_cpu_seconds": self.cpu_elapsed,
                "median_step_seconds": float(np.median(self.step_seconds)) if self.step_seconds else None,
                "num_gaussians": self.num_gaussians, "refraction": self.flags, "water": self._water_dict(),
                "attenuation": self._attenuation_list(), "backscatter": self._backscatter_dict(),
                "reflection": self._reflection_dict(),
                **{f"last_{k}": v for k, v in self.last.items() if k != "n"}}

    def _water_dict(self) -> dict | None:  # the water as it stands now, as JSON
        return layout.water_json(self.water)

    def _attenuation_list(self) -> list[float] | None:  # c (1/m, linear RGB) as it stands now, as JSON
        return None if self.attenuation is None else [float(c) for c in self.attenuation]

    def _backscatter_dict(self) -> dict | None:  # B_inf (linear RGB) and c_b (1/m) as they stand now, as JSON
        return None if self.backscatter is None else backscatter_json(self.backscatter)

    def _reflection_dict(self) -> dict | None:  # the sky map (linear RGB) as it stands now, as JSON
        return None if self.reflection is None else reflection_json(self.reflection)

    # ---- persistence -------------------------------------------------------------------------------------
    def _write_config(self) -> None:
        meta = {"config": self.cfg.to_dict(), "dataset": str(Path(self.ds.root).resolve()),
                "dataset_fingerprint": self.ds.fingerprint, "scene_scale": self.scene_scale,
                "water": layout.water_json(self._water0),
                "water_final": self._water_dict() if self.step >= self.cfg.iterations else None,
                # the attenuation coefficients (1/m) at the start and, once finished, at the end
                # (renders use it)
                "attenuation": None if self.attenuation is None else [self.cfg.attenuation_start] * 3,
                "attenuation_final": self._attenuation_list() if self.step >= self.cfg.iterations else None,
                # the backscatter likewise
                "backscatter": None if self.backscatter is None else {
                    "veil": [self.cfg.veil_start] * 3, "coefficients": [self.cfg.backscatter_start] * 3},
                "backscatter_final": self._backscatter_dict() if self.step >= self.cfg.iterations else None,
                # the sky map: at the start every texel's radiance and the map's side, at the end the map
                "reflection": (None if self.reflection is None
                               else {"sky": self.cfg.sky_start, "size": SKY_SIZE}),
                "reflection_final": self._reflection_dict() if self.step >= self.cfg.iterations else None,
                "refraction_applied": self.flags,
                "device": str(self.device),
                "num_train_views": len(self.views), "versions": versions("torch")}
        write_json(self.out / "config.json", meta, indent=1)

    def save_checkpoint(self, path: str | Path | None = None) -> Path:
        path = Path(path) if path is not None else self.out / CHECKPOINT
        data = {"config": self.cfg.to_dict(), "dataset_fingerprint": self.ds.fingerprint, "step": self.step,
                "elapsed": self.elapsed, "cpu_elapsed": self.cpu_elapsed,
                "step_seconds": list(self.step_seconds),
                "splats": {k: v.detach().cpu() for k, v in self.splats.items()},
                "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
                "strategy": {k: (v.cpu() if torch.is_tensor(v) else v) for k, v in self.strat_state.items()},
                "generator": self.gen.get_state(), "order": list(self._order), "last": self.last,
                "water": {k: p.detach().cpu() for k, p in self.water_params.items()},
                "water_optimizer": None if self.water_opt is None else self.water_opt.state_dict(),
                "attenuation": None if self.log_attenuation is None else self.log_attenuation.detach().cpu(),
                "attenuation_optimizer": (None if self.attenuation_opt is None
                                          else self.attenuation_opt.state_dict()),
                "backscatter": None if self.log_backscatter is None else self.log_backscatter.detach().cpu(),
                "backscatter_optimizer": (None if self.backscatter_opt is None
                                          else self.backscatter_opt.state_dict()),
                "reflection": None if self.log_sky is None else self.log_sky.detach().cpu(),
                "reflection_optimizer": None if self.sky_opt is None else self.sky_opt.state_dict()}
        with atomic_path(path) as tmp:  # a kill never leaves a half-written checkpoint
            torch.save(data, tmp)
        return path

    def _load(self, path: Path) -> None:
        try:
            data = torch.load(path, map_location="cpu", weights_only=True)
        except (RuntimeError, KeyError, EOFError, ValueError,
                pickle.UnpicklingError) as err:  # truncated, garbage
            raise OutputError(f"{path}: not a readable checkpoint ({type(err).__name__}); move it away to "
                              "start over") from None
        theirs, ours = data.get("dataset_fingerprint"), self.ds.fingerprint
        if theirs is not None and ours is not None and theirs != ours:
            raise OutputError(f"{path}: checkpoint of another dataset (fingerprint {theirs}, {self.ds.root} "
                              f"is {ours}); use another output directory")
        saved = TrainConfig.from_dict(data["config"])
        diff = [f.name for f in fields(TrainConfig)
                if f.name not in RUN_ONLY and getattr(saved, f.name) != getattr(self.cfg, f.name)]
        # More iterations extend a run (the schedule stretches to the new count from here on, so the result
        # is not that of a fresh run of that length); anything else would mix two configurations.
        if diff == ["iterations"] and self.cfg.iterations >= int(data["step"]):
            self.extended_from = saved.iterations
        elif diff:
            raise OutputError(f"{path}: checkpoint was written with different settings ({', '.join(diff)}); "
                              "use another output directory or the same settings")
        self.splats = torch.nn.ParameterDict(
            {k: torch.nn.Parameter(v.to(self.device)) for k, v in data["splats"].items()})
        self.optimizers = self._make_optimizers()
        for k, o in self.optimizers.items():
            o.load_state_dict(data["optimizers"][k])
        with torch.no_grad():
            for k, p in self.water_params.items():  # the same config: the same calibrated fields
                p.copy_(data["water"][k])
        if self.water_opt is not None:
            self.water_opt.load_state_dict(data["water_optimizer"])
        if self.log_attenuation is not None:  # the same variant: the same terms
            with torch.no_grad():
                self.log_attenuation.copy_(data["attenuation"])
            self.attenuation_opt.load_state_dict(data["attenuation_optimizer"])
        if self.log_backscatter is not None:
            with torch.no_grad():
                self.log_backscatter.copy_(data["backscatter"])
            self.backscatter_opt.load_state_dict(data["backscatter_optimizer"])
        if self.log_sky is not None:
            if data.get("reflection") is None:  # 2dgs+full+water before it had the reflection
                raise OutputError(f"{path}: checkpoint of {self.cfg.variant} without the surface's "
                                  "reflection (written before the variant had it); use another output "
                                  "directory")
            with torch.no_grad():
                self.log_sky.copy_(data["reflection"])
            self.sky_opt.load_state_dict(data["reflection_optimizer"])
        self.strat_state = {k: (v.to(self.device) if torch.is_tensor(v) else v)
                            for k, v in data["strategy"].items()}
        self.step, self.elapsed = int(data["step"]), float(data["elapsed"])
        self.cpu_elapsed = float(data.get("cpu_elapsed", 0.0))
        self.step_seconds = [float(t) for t in data.get("step_seconds", [])]
        self.gen.set_state(data["generator"])
        self._order = list(data["order"])
        self.last = dict(data["last"])
