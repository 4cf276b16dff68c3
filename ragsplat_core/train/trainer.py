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
water terms at the start and, once finished, at the end), `ckpt.pt` (latest checkpoint), `point_cloud.ply`
(standard 3DGS PLY), `train_stats.json` (time, Gaussian count, last loss, final water and water terms).

The water is the dataset's unless the config overrides its level or n (`start.py`); `optimize_water`
calibrates it (`water_terms.CalibratedWater`, frozen for the warm-up), and `trainer.water` is always the
current one. A variant with water terms (`WATER_TERMS`) also trains them (`trainer.terms`, `water_terms.py`):
the water's attenuation (`trainer.attenuation`: c [3], 1/m), its backscatter (`trainer.backscatter`: B_inf
and c_b, the veil added to the render) and the sky the surface mirrors (`trainer.reflection`: a map of linear
radiance, Fresnel-weighted over the wet pixels), each saved in the checkpoint and in config.json
(`attenuation_final`, `backscatter_final`, `reflection_final`: what `runs.Model` renders with). A view with
a mask trains on its used pixels only.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from ragsplat.camera import Camera
from ragsplat.dataset import layout
from ragsplat.dataset.load import Dataset
from ragsplat.errors import ConfigError, DatasetError, OutputError, TrainingDiverged
from ragsplat.gaussians import PARAM_NAMES
from ragsplat.outputs import claim, versions, write_json
from ragsplat.ply import save_ply
from ragsplat.rasterize import choose_backend
from ragsplat.rasterize_surfels import depth_normals
from ragsplat.refraction import facet_offsets, opacity_factor
from ragsplat.rendering import fades_opacity, median_depth, render_splats
from ragsplat.ssim import psnr, ssim, ssim_map
from ragsplat.train.albedo import AlbedoTransfer, image_shares
from ragsplat.train.checkpoint import CHECKPOINT, read_checkpoint, write_checkpoint
from ragsplat.train.config import VARIANTS, TrainConfig
from ragsplat.train.start import check_cameras_above, initial_splats, start_water
from ragsplat.train.strategy import DefaultStrategy
from ragsplat.train.water_terms import TERM_NAMES, CalibratedWater, water_terms
from ragsplat.water_surface import WaterSurface

PLY = "point_cloud.ply"
# Kept as the third scale of a surfel so that code written for three axes (a split's offsets, the volume
# sampling of `surface.py`) treats it as the flat disk it renders as.
SURFEL_THICKNESS = 1e-5  # metres


class Trainer:
    """The Gaussians, their optimisers, the water's trained fields and terms and the densification state of
    one run (one variant). `view_ripples(name, xy [M, 2]) -> [M, 2]`: the gradient of training view `name`'s
    own (horizontal) water surface, given (`tools.tune --true-ripples`: the photos' true ripples); each of its
    renders shows the Gaussians as that surface would (`rippled`). None: the one surface every view shares."""

    def __init__(self, cfg: TrainConfig, dataset: Dataset, out_dir: str | Path | None = None,
                 resume: bool = True,
                 view_ripples: Callable[[str, torch.Tensor], torch.Tensor] | None = None):
        self.cfg = cfg
        self.view_ripples = view_ripples
        self.ds = dataset
        self.out = None if out_dir is None else Path(out_dir)
        self.device = torch_device(cfg)
        self.views = dataset.train
        if not self.views:
            raise DatasetError(f"{dataset.root}: the dataset has no training views")
        water0 = start_water(cfg, dataset)
        if view_ripples is not None and (water0 is None or water0.tilted or water0.curved):
            raise ConfigError("view_ripples: a dataset with a horizontal water surface only")
        self.calibrated = CalibratedWater(water0, cfg, self.device)  # a resumed run overwrites its values
        flags = VARIANTS[cfg.variant]
        # A dry scene (or n = 1 that is not calibrated) trains as plain 3DGS: the transform is skipped, not
        # run as an identity.
        self.flags = None if (flags is None or water0 is None or
                              (water0.n == 1 and "n" not in self.calibrated.params)) else flags
        # the water's optics, only where the water is modelled: else no parameter, no optimizer, not one op
        self.terms = {} if self.flags is None else water_terms(cfg, self.device)
        self.albedo = AlbedoTransfer(self._image_shares, cfg.downwelling) \
            if cfg.detrend_albedo and "attenuation" in self.terms else None
        self.targets = [v.image.to(self.device) for v in self.views]  # [H, W, 3] each
        self.masks = [None if v.mask is None else v.mask.to(self.device) for v in self.views]  # [H, W] bool
        self.centers = [torch.tensor(v.camera.camera_center, dtype=torch.float32, device=self.device)
                        for v in self.views]
        self.background = torch.tensor(cfg.background, dtype=torch.float32, device=self.device)
        self.scene_scale = dataset.camera_extent() if cfg.scene_scale is None else cfg.scene_scale
        self.gen = torch.Generator().manual_seed(cfg.seed)  # view order and split samples
        # pruning and resets test the opacity as rendered (through the water for a variant that fades it)
        self.strategy = DefaultStrategy(cfg.schedule, self.gen,
                                        (lambda means: opacity_factor(means, self.water))
                                        if fades_opacity(self.flags) else None)
        self.step, self.elapsed, self.cpu_elapsed = 0, 0.0, 0.0
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
            self.splats = initial_splats(cfg, dataset, self.water).to(self.device)
            self._flatten_surfels()
            self.optimizers = self._make_optimizers()
            self.strat_state = self.strategy.initialize_state(self.scene_scale)
        self.strategy.check_sanity(self.splats, self.optimizers)

    # ---- state ------------------------------------------------------------------------------------
    @property
    def water(self) -> WaterSurface | None:
        """The water as it stands now: the dataset's, overridden by the config, moved by calibration."""
        return self.calibrated.surface()

    # as they stand now (None: not trained): c [3] (1/m, linear RGB); [2, 3] the veil B_inf (linear RGB) and
    # its c_b (1/m); [S, S, 3] the sky map the surface mirrors (linear radiance)
    attenuation, backscatter, reflection = (
        property(lambda self, k=k: self.terms[k].value if k in self.terms else None) for k in TERM_NAMES)

    def _make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        # one Adam per parameter (gsplat's layout): the strategy swaps tensors one optimiser at a time.
        # fused: one kernel per step instead of about ten ops (on the 2-core CPU 3 ms instead of 12 at 40k)
        c = self.cfg
        lr = {"means": c.lr_means * self.scene_scale, "scales": c.lr_scales, "quats": c.lr_quats,
              "opacities": c.lr_opacities, "sh0": c.lr_sh0, "shN": c.lr_shN}
        return {k: torch.optim.Adam([{"params": [p], "lr": lr[k], "name": k}], eps=1e-15, fused=True)
                for k, p in self.splats.items()}

    def means_lr(self, step: int) -> float:
        """3DGS's exponential (log-linear) decay of the position learning rate over the run."""
        c = self.cfg
        t = min(step / c.iterations, 1.0)
        return self.scene_scale * math.exp((1 - t) * math.log(c.lr_means) + t * math.log(c.lr_means_final))

    @property
    def active_sh_degree(self) -> int:
        return self.cfg.active_sh_degree(self.step)

    @property
    def num_gaussians(self) -> int:
        return int(self.splats["means"].shape[0])

    # ---- rendering ----------------------------------------------------------------------------------
    def _render(self, camera: Camera, center: torch.Tensor, interface: bool, water: WaterSurface | None,
                splats: dict | None = None, check_camera: bool = True):
        # splats: the Gaussians to render, self.splats when None; check_camera: `render_splats`'
        optics = [self.terms[k].log.exp() if interface and k in self.terms else None for k in TERM_NAMES]
        return render_splats(self.splats if splats is None else splats, camera, center, self.active_sh_degree,
                             water, self.flags if interface else None, self.cfg.surfels, self.background,
                             self.cfg.backend, self.cfg.compile_refraction, *optics,
                             self.cfg.wet_sh_degree, self.cfg.surfel_depth, self.cfg.downwelling,
                             check_camera)

    def render(self, camera: Camera, interface: bool = True):
        """(image [H,W,3], alpha [H,W,1], depth [H,W,1]) of `camera`, no gradients.

        interface=True: through the water as trained (apparent Gaussians); False: the true Gaussians with
        their own colours (for full+color the true albedo): the scene "without the interface".
        """
        center = torch.tensor(camera.camera_center, dtype=torch.float32, device=self.device)
        with torch.no_grad():
            img, alpha, depth, _ = self._render(camera, center, interface, self.water)
        return img.clamp(0, 1), alpha, depth

    def median_depth(self, camera: Camera) -> torch.Tensor:  # [H, W], see `median_depth`
        return median_depth(self.splats, camera, self.cfg.surfels,
                            self.water if fades_opacity(self.flags) else None, self.cfg.backend)

    def _image_shares(self) -> torch.Tensor:  # [N] `image_shares` over the training views' used pixels
        return image_shares(self.splats, [v.camera for v in self.views], self.centers, self.water, self.flags,
                            self.cfg.surfels, self.cfg.backend, self.cfg.compile_refraction, self.masks,
                            self.cfg.surfel_depth)

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
        calibrate = self.calibrated.opt is not None and step > self.cfg.water_start
        water = self.calibrated.surface(calibrate)
        shown = None if self.view_ripples is None else rippled(
            self.splats, self.centers[i], water, lambda xy: self.view_ripples(self.views[i].name, xy))
        # the training cameras are checked above the water at the start and after each move of it
        img, _, depth, info = self._render(cam, self.centers[i], True, water, shown, check_camera=False)
        loss = photometric_loss(img, gt, mask, self.cfg.ssim_lambda)
        if self.cfg.surfels:
            loss = loss + surfel_loss(self.cfg, cam, depth, info, mask, step)
        info.update(width=cam.width, height=cam.height)
        self.strategy.step_pre_backward(self.splats, self.optimizers, self.strat_state, step, info)
        loss.backward()
        shown = (img.detach(), gt) if mask is None else (img.detach()[mask], gt[mask])
        self._check_before_step(step, loss, psnr(*shown), self.views[i].name)
        self.optimizers["means"].param_groups[0]["lr"] = self.means_lr(step)
        for opt in self.optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        for term in self.terms.values():
            term.step()
        if self.albedo is not None:
            self.albedo.transfer(self.splats, self.water, self.terms["attenuation"], step)
        if calibrate:
            self.calibrated.step()
            check_cameras_above(self.views, self.water, TrainingDiverged)  # a level that rose above them
        self.strategy.step_post_backward(self.splats, self.optimizers, self.strat_state, step, info)
        self._flatten_surfels()  # a split divides all three scales
        return self.last

    def _check_before_step(self, step: int, loss: torch.Tensor, psnr_db: torch.Tensor, view: str) -> None:
        """TrainingDiverged where the loss, a gradient or a parameter (as the last step left it) is not
        finite; else the step's loss and PSNR into `self.last`. One read from the device for all of it: each
        read waits for the device's queue. One sum per tensor: a sum is finite only if every element is
        (gradients and parameters are far too small to overflow float32 when added up)."""
        named = [*self.splats.items(), *self._water_named()]
        sums = [t for _, p in named for t in ((p.grad if p.grad is not None else p.new_zeros(())).sum(),
                                               p.detach().sum())]
        values = torch.stack([x.detach().float() for x in (loss, psnr_db, *sums)])
        loss_value, psnr_value, *read = values.tolist()
        if all(math.isfinite(x) for x in (loss_value, *read)):
            self.last = {"loss": loss_value, "psnr": psnr_value, "n": self.num_gaussians}
            return
        cause = nonfinite_report(self.splats, self._water_named())
        if not math.isfinite(loss_value):
            raise TrainingDiverged(f"iteration {step}: loss is {loss_value} (view {view}); {cause}")
        if cause:  # a bad parameter poisons the others' gradients: name it
            raise TrainingDiverged(f"iteration {step}: {cause} before the optimizer step")
        name, p = next((name, p) for k, (name, p) in enumerate(named) if not math.isfinite(read[2 * k]))
        raise TrainingDiverged(f"iteration {step}: non-finite gradient of parameter '{name}' "
                               f"({int((~torch.isfinite(p.grad)).sum())} values)")

    def _check_after_step(self) -> None:
        """TrainingDiverged where the last optimizer step left a parameter non-finite (the next step's check
        would find it; a checkpoint or the end comes first)."""
        bad = nonfinite_report(self.splats, self._water_named())
        if bad:
            raise TrainingDiverged(f"iteration {self.step}: {bad} after the optimizer step")

    def _flatten_surfels(self) -> None:
        """The third axis of a surfel is its normal: no thickness, no gradient. Kept at `SURFEL_THICKNESS`
        so that the extraction, which samples in proportion to volume, weighs every surfel by its area."""
        if self.cfg.surfels:
            with torch.no_grad():
                self.splats["scales"][:, 2] = math.log(SURFEL_THICKNESS)

    def _water_named(self):  # (name, parameter) of the trained water fields and terms, named as in messages
        return self.calibrated.named() + [(t.label, t.log) for t in self.terms.values()]

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
                due = self.out is not None and every and self.step % every == 0
                if self.step in marks or due:
                    self._check_after_step()  # before an evaluation or a checkpoint reads the parameters
                if self.step in marks and self.step < cfg.iterations:
                    for cb in callbacks:
                        cb(self, self.step)
                if due:
                    self.save_checkpoint()
        except KeyboardInterrupt:
            if self.out is not None and not in_step:  # a step cut in half would save a half-updated state
                self.save_checkpoint()
            raise
        self._check_after_step()
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

    def _terms_json(self) -> dict:  # each water term a variant can have, as it stands now (None: not trained)
        return {k: self.terms[k].as_json(self.terms[k].value) if k in self.terms else None
                for k in TERM_NAMES}

    def stats(self) -> dict:
        return {"variant": self.cfg.variant, "seed": self.cfg.seed, "iterations": self.step,
                "train_seconds": self.elapsed, "train_cpu_seconds": self.cpu_elapsed,
                "median_step_seconds": float(np.median(self.step_seconds)) if self.step_seconds else None,
                "num_gaussians": self.num_gaussians, "refraction": self.flags,
                "water": layout.water_json(self.water), **self._terms_json(),
                **{f"last_{k}": v for k, v in self.last.items() if k != "n"}}

    # ---- persistence -------------------------------------------------------------------------------------
    def _write_config(self) -> None:
        done = self.step >= self.cfg.iterations
        # the water and its terms at the start and, once finished, at the end (renders use them)
        start = {"water": layout.water_json(self.calibrated.start),
                 **{k: self.terms[k].start if k in self.terms else None for k in TERM_NAMES}}
        final = {"water": layout.water_json(self.water), **self._terms_json()} if done else {}
        meta = {"config": self.cfg.to_dict(), "dataset": str(Path(self.ds.root).resolve()),
                "dataset_fingerprint": self.ds.fingerprint, "scene_scale": self.scene_scale,
                **{x: y for k in start for x, y in ((k, start[k]), (f"{k}_final", final.get(k)))},
                "refraction_applied": self.flags, "device": str(self.device),
                "num_train_views": len(self.views), "versions": versions("torch")}
        write_json(self.out / "config.json", meta, indent=1)

    def save_checkpoint(self, path: str | Path | None = None) -> Path:
        water, water_opt = self.calibrated.state()
        terms = {k: self.terms[k].state() if k in self.terms else (None, None) for k in TERM_NAMES}
        return write_checkpoint(Path(path) if path is not None else self.out / CHECKPOINT, {
            "config": self.cfg.to_dict(), "dataset_fingerprint": self.ds.fingerprint, "step": self.step,
            "elapsed": self.elapsed, "cpu_elapsed": self.cpu_elapsed, "step_seconds": list(self.step_seconds),
            "splats": {k: v.detach().cpu() for k, v in self.splats.items()},
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "strategy": {k: (v.cpu() if torch.is_tensor(v) else v) for k, v in self.strat_state.items()},
            "generator": self.gen.get_state(), "order": list(self._order), "last": self.last,
            "water": water, "water_optimizer": water_opt,
            **{x: y for k, (v, o) in terms.items() for x, y in ((k, v), (f"{k}_optimizer", o))}})

    def _load(self, path: Path) -> None:
        data, self.extended_from = read_checkpoint(path, self.cfg, self.ds.fingerprint, self.ds.root)
        self.splats = torch.nn.ParameterDict(
            {k: torch.nn.Parameter(v.to(self.device)) for k, v in data["splats"].items()})
        self.optimizers = self._make_optimizers()
        for k, o in self.optimizers.items():
            o.load_state_dict(data["optimizers"][k])
        self.calibrated.load(data["water"], data["water_optimizer"])
        for k, term in self.terms.items():  # the same variant: the same terms
            if data.get(k) is None:
                raise OutputError(f"{path}: checkpoint of {self.cfg.variant} without the water's {k}; use "
                                  "another output directory")
            term.load(data[k], data[f"{k}_optimizer"])
        self.strat_state = {k: (v.to(self.device) if torch.is_tensor(v) else v)
                            for k, v in data["strategy"].items()}
        self.step, self.elapsed = int(data["step"]), float(data["elapsed"])
        self.cpu_elapsed = float(data.get("cpu_elapsed", 0.0))
        self.step_seconds = [float(t) for t in data.get("step_seconds", [])]
        self.gen.set_state(data["generator"])
        self._order = list(data["order"])
        self.last = dict(data["last"])


def torch_device(cfg: TrainConfig) -> torch.device:
    """The device `cfg.device` names ("auto": CUDA where there is one); an impossible one, or a backend the
    device cannot run, refused before any work."""
    try:
        device = torch.device(("cuda" if torch.cuda.is_available() else "cpu")
                              if cfg.device == "auto" else cfg.device)
    except RuntimeError:
        raise ConfigError(f"unknown torch device {cfg.device!r} (e.g. cpu, cuda, cuda:1)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device {cfg.device!r} requested but CUDA is not available here")
    choose_backend(cfg.backend, device)
    return device


def photometric_loss(img, gt, mask, lam: float) -> torch.Tensor:
    """3DGS's loss, (1 - lam) L1 + lam (1 - SSIM), of img [H, W, 3] against gt over mask [H, W] (None: every
    pixel). SSIM windows straddle the mask's edge: both images are zeroed outside it, so neither the unused
    target pixels nor the render there reach the loss, and the map is averaged where used."""
    if mask is None:
        return (1 - lam) * torch.abs(img - gt).mean() + lam * (1 - ssim(img, gt))
    both = [torch.where(mask[..., None], x, 0.0) for x in (img, gt)]
    return (1 - lam) * torch.abs(img - gt)[mask].mean() + lam * (1 - ssim_map(*both)[0][:, mask].mean())


def surfel_loss(c: TrainConfig, cam: Camera, depth, info: dict, mask, step: int):
    """2DGS's geometry terms over the used pixels: depth distortion, and normal consistency between the
    rendered normals and those of the rendered depth map (both in the space the camera sees: apparent
    under water, where the apparent bed is a surface too)."""
    loss = depth.new_zeros(())
    used = (lambda x: x.reshape(-1)) if mask is None else (lambda x: x[mask])
    if step > c.distortion_from * c.iterations:
        loss = loss + c.lambda_distortion * used(info["distortion"][..., 0]).mean()
    if step > c.normal_from * c.iterations:
        from_depth = depth_normals(depth[..., 0], cam)  # [H, W, 3] unit, zero where undefined
        loss = loss + c.lambda_normal * used(1 - (info["normals"] * from_depth).sum(-1)).mean()
    return loss


def rippled(splats, center: torch.Tensor, water: WaterSurface, gradient) -> dict:
    """The Gaussians as a view from `center` sees them through its own surface (`gradient(xy [M, 2]) ->
    [M, 2]`): each submerged mean moved back by its `facet_offsets` (the surface is given: no gradient through
    the offsets)."""
    means = splats["means"]
    with torch.no_grad():
        moved = facet_offsets(means, center, water, gradient)
    return {**splats, "means": means - torch.cat([moved, torch.zeros_like(moved[:, :1])], -1)}


def nonfinite_report(splats, water_named) -> str:
    """The first parameter with a non-finite value, in one line ("": none), of the Gaussians and of the
    water's trained `(name, parameter)`s."""
    for name in PARAM_NAMES:
        if name in splats and not torch.isfinite(splats[name].detach().sum()):
            count = int((~torch.isfinite(splats[name])).sum())
            return f"non-finite values in parameter '{name}' ({count} of {splats[name].numel()})"
    for name, p in water_named:
        if not torch.isfinite(p.detach()).all():
            return f"non-finite value of parameter '{name}'"
    return ""
