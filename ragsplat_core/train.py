"""RA-GS training: 3D Gaussian splatting with the per-view refraction transform plugged in before rasterizing.

Programmatic use (what `ragsplat train` and the ablation harness do):

    cfg = preset_config("small", variant="full", seed=0)
    trainer = Trainer(cfg, load_dataset(data_dir), out_dir)      # resumes from out_dir/ckpt.pt if present
    trainer.train(callbacks=[fn], eval_steps=[250, 500, 1000])   # fn(trainer, step) at those steps + the end
    image, alpha, depth = trainer.render(camera, interface=False)  # "without the interface": true Gaussians

`trainer.elapsed` is the training wall-clock time in seconds, excluding the time spent inside callbacks
and checkpoint writes, so error-against-time curves are not inflated by evaluation.

Outputs in out_dir: `config.json` (resolved config, seed, versions, variant flags), `ckpt.pt` (latest
checkpoint), `point_cloud.ply` (standard 3DGS PLY), `train_stats.json` (time, Gaussian count, last loss).
"""

from __future__ import annotations

import json
import math
import os
import platform
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import torch

from ragsplat_core.camera import Camera
from ragsplat_core.data import Dataset
from ragsplat_core.gaussians import PARAM_NAMES, activated, colors_for_view, init_grid, init_points
from ragsplat_core.ply import save_ply
from ragsplat_core.rasterize import rasterize
from ragsplat_core.refraction import WaterSurface, refract_gaussians
from ragsplat_core.ssim import ssim
from ragsplat_core.strategy import PAPER_ITERATIONS, DefaultStrategy, DensifyConfig

# variant -> refract_gaussians flags (None: plain 3DGS, no refraction work at all)
VARIANTS: dict[str, dict | None] = {
    "3dgs": None,
    "position": {"position": True, "scale": "none", "opacity": False, "color": False},
    "position+scale": {"position": True, "scale": "isotropic", "opacity": False, "color": False},
    "position+opacity": {"position": True, "scale": "none", "opacity": True, "color": False},
    "full": {"position": True, "scale": "isotropic", "opacity": True, "color": False},
    "full+anisotropic": {"position": True, "scale": "anisotropic", "opacity": True, "color": False},
    "full+color": {"position": True, "scale": "isotropic", "opacity": True, "color": True},
}
CHECKPOINT = "ckpt.pt"
PLY = "point_cloud.ply"


class TrainingDiverged(RuntimeError):
    """A non-finite loss or parameter; the message names the iteration and the parameter."""


@dataclass(frozen=True)
class TrainConfig:
    variant: str = "full"
    preset: str = "small"
    seed: int = 0
    iterations: int = 1500
    # initialisation: "grid" (the paper: a horizontal grid at the bed depth) or "points" (a point cloud file)
    init: str = "grid"
    init_depth: float | None = None  # grid depth below the water level (m); None: scene.json spec.bed.depth
    init_count: int = 10_000  # grid Gaussians (approximately: a square grid over the views' footprint)
    init_points: str | None = None  # .npy [N, 3] or [N, 6] (xyz, rgb in [0, 1]) for init="points"
    init_opacity: float = 0.1
    sh_degree: int = 3
    sh_degree_every: int = 1000  # raise the active SH degree by one every this many iterations (at 30k)
    # Adam learning rates (3DGS / gsplat defaults); means decays exponentially to lr_means_final
    lr_means: float = 1.6e-4  # x scene scale (camera extent)
    lr_means_final: float = 1.6e-6
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacities: float = 5e-2
    lr_sh0: float = 2.5e-3
    lr_shN: float = 2.5e-3 / 20
    ssim_lambda: float = 0.2
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    densify: DensifyConfig = field(default_factory=DensifyConfig)  # at 30k iterations; scaled to `iterations`
    backend: str = "auto"
    device: str = "auto"  # "auto": CUDA when available, else CPU
    checkpoint_every: int = 500  # also written at the end; 0: only at the end

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown variant {self.variant!r}; choose one of {', '.join(VARIANTS)}")
        if self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        if self.init not in ("grid", "points"):
            raise ValueError(f"init must be 'grid' or 'points', got {self.init!r}")
        if self.init == "points" and not self.init_points:
            raise ValueError("init='points' needs init_points (a .npy point cloud)")
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be 0..3, got {self.sh_degree}")
        if self.init_depth is not None and not self.init_depth > 0:
            raise ValueError(f"init_depth is a depth below the water level and must be > 0, got {self.init_depth}")

    @property
    def schedule(self) -> DensifyConfig:
        """The densification schedule stretched to this run's iteration count."""
        return self.densify.scaled(self.iterations)

    @property
    def sh_every(self) -> int:
        return max(1, round(self.sh_degree_every * self.iterations / PAPER_ITERATIONS))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["background"] = list(self.background)
        d["refraction"] = VARIANTS[self.variant]
        d["densify_scaled"] = asdict(self.schedule)
        d["sh_every_scaled"] = self.sh_every
        return d

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        names = {f.name for f in fields(cls)}
        kw = {k: v for k, v in d.items() if k in names}
        kw["densify"] = DensifyConfig(**kw.get("densify", {}))
        kw["background"] = tuple(kw.get("background", (0.0, 0.0, 0.0)))
        return cls(**kw)


# Presets: smoke (CI, seconds), small (the 2-core CPU default of `make ablation`), paper (30k, a GPU).
# The short presets start the position rate 10x higher (1.6e-3): with the 30k schedule squeezed into 1500
# steps the default rate lets a Gaussian travel at most about 0.3 m (sum of the per-step rates x extent),
# less than the refraction shift it must be free to follow (0.74 m at 3 m depth). Measured on the small
# dataset at 1500 steps, 1x vs 10x: full F1@10cm 0.66 -> 0.95, 3dgs 0.63 -> 0.57 (README).
SHORT_LR_MEANS = 1.6e-3
PRESETS: dict[str, TrainConfig] = {
    "smoke": TrainConfig(preset="smoke", iterations=150, init_count=1_500, sh_degree=1, checkpoint_every=0,
                         lr_means=SHORT_LR_MEANS, densify=DensifyConfig(max_gaussians=4_000)),
    "small": TrainConfig(preset="small", iterations=1500, init_count=16_000, lr_means=SHORT_LR_MEANS,
                         densify=DensifyConfig(max_gaussians=40_000)),
    "paper": TrainConfig(preset="paper", iterations=30_000, init_count=40_000, checkpoint_every=5000),
}


def preset_config(name: str, **overrides) -> TrainConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return replace(PRESETS[name], **overrides)


def psnr(img: torch.Tensor, ref: torch.Tensor) -> float:
    mse = float(torch.mean((img.detach().float() - ref.float()) ** 2))
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def footprint(cameras: list[Camera], water: WaterSurface | None, z: float) -> tuple[float, float, float, float]:
    """(xmin, xmax, ymin, ymax) where the image-corner rays of `cameras` meet the plane `z` (refracted at the
    water when it is above the plane); rays that never reach it are ignored."""
    pts = []
    for cam in cameras:
        px = np.array([[0, 0], [cam.width, 0], [0, cam.height], [cam.width, cam.height]], float)
        far = cam.unproject(px, np.ones(4))  # [4, 3] world points at z-depth 1
        origin = cam.camera_center
        d = far - origin
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = np.repeat(origin[None], 4, 0)
        if water is not None and water.level > z and origin[2] > water.level:
            t = (water.level - o[:, 2]) / np.where(d[:, 2] < 0, d[:, 2], np.nan)
            o = o + t[:, None] * d
            # Snell in vector form at the horizontal interface (normal +z): keep the horizontal direction,
            # sin(theta_w) = sin(theta_a) / n
            sin_a = np.linalg.norm(d[:, :2], axis=1)
            sin_w = sin_a / water.n
            horiz = d[:, :2] / np.maximum(sin_a, 1e-12)[:, None]
            d = np.concatenate([horiz * sin_w[:, None], -np.sqrt(1 - sin_w**2)[:, None]], 1)
        t = (z - o[:, 2]) / np.where(d[:, 2] < 0, d[:, 2], np.nan)
        hit = o + t[:, None] * d
        pts.append(hit[np.isfinite(hit).all(1) & (t > 0)])
    pts = np.concatenate(pts)
    if len(pts) == 0:
        raise ValueError(f"no camera sees the plane z = {z}")
    return float(pts[:, 0].min()), float(pts[:, 0].max()), float(pts[:, 1].min()), float(pts[:, 1].max())


def _bed(ds: Dataset) -> dict:
    """The generator's bed spec (scene.json `spec.bed`: `depth` below the water, square `size` centred on the
    origin), or {} for a dataset that has none."""
    bed = ((ds.scene or {}).get("spec") or {}).get("bed")
    return bed if isinstance(bed, dict) else {}


def _positive(value) -> float | None:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0
    return float(value) if ok else None


def _versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version

    try:
        own = version("ragsplat")
    except PackageNotFoundError:  # running from a source tree that was never installed
        own = "unknown"
    return {"python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__,
            "ragsplat": own}


class Trainer:
    """Holds the Gaussians, their optimisers and the densification state for one run (one variant)."""

    def __init__(self, cfg: TrainConfig, dataset: Dataset, out_dir: str | Path | None = None, resume: bool = True):
        self.cfg = cfg
        self.ds = dataset
        self.out = None if out_dir is None else Path(out_dir)
        self.device = torch.device(("cuda" if torch.cuda.is_available() else "cpu") if cfg.device == "auto"
                                   else cfg.device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"device {cfg.device!r} requested but CUDA is not available here")
        self.water = dataset.water
        flags = VARIANTS[cfg.variant]
        # A dry scene (or n = 1) trains as plain 3DGS: the transform is skipped, not run as an identity.
        self.flags = None if (flags is None or self.water is None or self.water.is_identity) else flags
        self.views = dataset.train
        if not self.views:
            raise ValueError("the dataset has no training views")
        self.targets = [v.image.to(self.device) for v in self.views]  # [H, W, 3] each
        self.centers = [torch.tensor(v.camera.camera_center, dtype=torch.float32, device=self.device)
                        for v in self.views]
        self.background = torch.tensor(cfg.background, dtype=torch.float32, device=self.device)
        self.scene_scale = dataset.camera_extent()
        self.schedule = cfg.schedule
        self.gen = torch.Generator().manual_seed(cfg.seed)  # view order and split samples
        self.strategy = DefaultStrategy(self.schedule, self.gen)
        self.step = 0
        self.elapsed = 0.0
        self.last = {}  # last step's loss / psnr
        self._order: list[int] = []
        if resume and self.out is not None and (self.out / CHECKPOINT).exists():
            self._load(self.out / CHECKPOINT)
        else:
            torch.manual_seed(cfg.seed)
            self.splats = self._init_splats().to(self.device)
            self.optimizers = self._make_optimizers()
            self.strat_state = self.strategy.initialize_state(self.scene_scale)
        self.strategy.check_sanity(self.splats, self.optimizers)

    # ---- setup ------------------------------------------------------------------------------------
    def _init_splats(self) -> torch.nn.ParameterDict:
        cfg = self.cfg
        if cfg.init == "points":
            if not Path(cfg.init_points).is_file():
                raise ValueError(f"{cfg.init_points}: point cloud file is missing")
            arr = np.load(cfg.init_points)
            if arr.ndim != 2 or arr.shape[1] not in (3, 6):
                raise ValueError(f"{cfg.init_points}: expected an array [N, 3] or [N, 6], got {arr.shape}")
            pts = torch.from_numpy(arr[:, :3]).float()
            rgb = torch.from_numpy(arr[:, 3:]).float() if arr.shape[1] == 6 else torch.full_like(pts, 0.5)
            return init_points(pts, rgb, self.water, cfg.sh_degree, cfg.init_opacity)
        bed = _bed(self.ds)
        depth = cfg.init_depth if cfg.init_depth is not None else _positive(bed.get("depth"))
        if depth is None:
            raise ValueError("grid initialisation needs the bed depth: scene.json has no spec.bed.depth, "
                             "give init_depth (--init-depth)")
        level = self.water.level if self.water is not None else 0.0
        z = level - depth
        # Everything the training views see of the plane (images are filled with bed to their edges, and
        # an uncovered part would render as background), clipped to the bed when its size is known.
        box = footprint([v.camera for v in self.views], self.water, z)
        size = _positive(bed.get("size"))
        if size is not None:
            h = size / 2
            box = (max(box[0], -h), min(box[1], h), max(box[2], -h), min(box[3], h))
            if box[0] >= box[1] or box[2] >= box[3]:
                raise ValueError(f"the training views do not see the {size} m bed at depth {depth} m")
        spacing = math.sqrt((box[1] - box[0]) * (box[3] - box[2]) / cfg.init_count)
        return init_grid(*box, z, spacing, cfg.sh_degree, cfg.init_opacity)

    def _lr(self, name: str) -> float:
        c = self.cfg
        return {"means": c.lr_means * self.scene_scale, "scales": c.lr_scales, "quats": c.lr_quats,
                "opacities": c.lr_opacities, "sh0": c.lr_sh0, "shN": c.lr_shN}[name]

    def _make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        # one Adam per parameter (gsplat's layout): the strategy swaps tensors one optimiser at a time
        return {k: torch.optim.Adam([{"params": [p], "lr": self._lr(k), "name": k}], eps=1e-15)
                for k, p in self.splats.items()}

    def means_lr(self, step: int) -> float:
        """3DGS's exponential (log-linear) decay of the position learning rate over the run."""
        c = self.cfg
        t = min(step / c.iterations, 1.0)
        return self.scene_scale * math.exp((1 - t) * math.log(c.lr_means) + t * math.log(c.lr_means_final))

    @property
    def active_sh_degree(self) -> int:
        return min(self.cfg.sh_degree, self.step // self.cfg.sh_every)

    @property
    def num_gaussians(self) -> int:
        return int(self.splats["means"].shape[0])

    # ---- rendering ----------------------------------------------------------------------------------
    def _gaussians(self, center: torch.Tensor, interface: bool):
        """(means, quats, scales, opacities, colors, covars) as the rasterizer takes them for one view."""
        s = self.splats
        scales, quats, opac = activated(s)
        colors = colors_for_view(s, center, self.active_sh_degree)
        means, covars = s["means"], None
        if interface and self.flags is not None:
            a = refract_gaussians(means, scales, quats, opac, colors, center, self.water, **self.flags)
            means, scales, quats, opac, colors, covars = a.means, a.scales, a.quats, a.opacities, a.colors, a.covars
        return means, quats, scales, opac, colors, covars

    def render(self, camera: Camera, interface: bool = True):
        """(image [H,W,3], alpha [H,W,1], depth [H,W,1]) of `camera`, no gradients.

        interface=True: through the water as trained (apparent Gaussians); False: the true Gaussians with
        their own colours (for full+color the true albedo): the scene "without the interface".
        """
        center = torch.tensor(camera.camera_center, dtype=torch.float32, device=self.device)
        with torch.no_grad():
            means, quats, scales, opac, colors, covars = self._gaussians(center, interface)
            img, alpha, depth, _ = rasterize(means, quats, scales, opac, colors, camera, self.background,
                                             covars=covars, backend=self.cfg.backend)
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
        cam, gt = self.views[i].camera, self.targets[i]
        means, quats, scales, opac, colors, covars = self._gaussians(self.centers[i], True)
        img, _, _, info = rasterize(means, quats, scales, opac, colors, cam, self.background, covars=covars,
                                    backend=self.cfg.backend)
        l1 = torch.abs(img - gt).mean()
        loss = (1 - self.cfg.ssim_lambda) * l1 + self.cfg.ssim_lambda * (1 - ssim(img, gt))
        if not torch.isfinite(loss):
            raise TrainingDiverged(f"iteration {step}: loss is {float(loss.detach())} (view {self.views[i].name}); "
                                   f"{self._nonfinite_report()}")
        info.update(width=cam.width, height=cam.height)
        self.strategy.step_pre_backward(self.splats, self.optimizers, self.strat_state, step, info)
        loss.backward()
        # one reduction per tensor: a sum is finite only if every element is (gradients and parameters are
        # far too small to overflow float32 when added up)
        for name, p in self.splats.items():
            if p.grad is not None and not torch.isfinite(p.grad.sum()):
                cause = self._nonfinite_report()  # a bad parameter poisons the others' gradients: name it
                raise TrainingDiverged(f"iteration {step}: " + (f"{cause} before the optimizer step" if cause else
                                       f"non-finite gradient of parameter '{name}' "
                                       f"({int((~torch.isfinite(p.grad)).sum())} values)"))
        self.optimizers["means"].param_groups[0]["lr"] = self.means_lr(step)
        for opt in self.optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        bad = self._nonfinite_report()
        if bad:
            raise TrainingDiverged(f"iteration {step}: {bad} after the optimizer step")
        self.strategy.step_post_backward(self.splats, self.optimizers, self.strat_state, step, info)
        self.last = {"loss": float(loss.detach()), "psnr": psnr(img, gt), "n": self.num_gaussians}
        return self.last

    def _nonfinite_report(self) -> str:
        for name in PARAM_NAMES:
            if name in self.splats and not torch.isfinite(self.splats[name].detach().sum()):
                count = int((~torch.isfinite(self.splats[name])).sum())
                return f"non-finite values in parameter '{name}' ({count} of {self.splats[name].numel()})"
        return ""

    def train(self, callbacks: list[Callable[[Trainer, int], None]] = (), eval_steps=(),
              on_step: Callable[[Trainer], None] | None = None) -> dict:
        """Train up to cfg.iterations (continuing from a resumed step); returns the final stats.

        `callbacks` run at each step in `eval_steps` and once at the end, outside the timed region.
        `on_step(trainer)` runs after every step (progress display), also outside the timed region.
        """
        cfg = self.cfg
        marks = {int(s) for s in eval_steps if self.step < int(s) <= cfg.iterations}
        if self.out is not None:
            self.out.mkdir(parents=True, exist_ok=True)
            self._write_config()
        while self.step < cfg.iterations:
            t0 = time.perf_counter()
            self.train_step()
            if self.device.type == "cuda":
                torch.cuda.synchronize(self.device)
            self.elapsed += time.perf_counter() - t0
            if on_step is not None:
                on_step(self)
            if self.step in marks and self.step < cfg.iterations:
                for cb in callbacks:
                    cb(self, self.step)
            if self.out is not None and cfg.checkpoint_every and self.step % cfg.checkpoint_every == 0:
                self.save_checkpoint()
        if self.out is not None:
            self.save_checkpoint()
            save_ply(self.out / PLY, self.splats)
        stats = self.stats()
        if self.out is not None:
            (self.out / "train_stats.json").write_text(json.dumps(stats, indent=1))
        for cb in callbacks:
            cb(self, self.step)
        return stats

    def stats(self) -> dict:
        return {"variant": self.cfg.variant, "seed": self.cfg.seed, "iterations": self.step,
                "train_seconds": self.elapsed, "num_gaussians": self.num_gaussians,
                "refraction": self.flags, **{f"last_{k}": v for k, v in self.last.items() if k != "n"}}

    # ---- persistence -------------------------------------------------------------------------------------
    def _write_config(self) -> None:
        meta = {"config": self.cfg.to_dict(), "dataset": str(self.ds.root), "scene_scale": self.scene_scale,
                "water": None if self.water is None else asdict(self.water), "refraction_applied": self.flags,
                "device": str(self.device),
                "num_train_views": len(self.views), "versions": _versions()}
        (self.out / "config.json").write_text(json.dumps(meta, indent=1))

    def save_checkpoint(self, path: str | Path | None = None) -> Path:
        path = Path(path) if path is not None else self.out / CHECKPOINT
        data = {"config": self.cfg.to_dict(), "step": self.step, "elapsed": self.elapsed,
                "splats": {k: v.detach().cpu() for k, v in self.splats.items()},
                "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
                "strategy": {k: (v.cpu() if torch.is_tensor(v) else v) for k, v in self.strat_state.items()},
                "generator": self.gen.get_state(), "order": list(self._order), "last": self.last}
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        torch.save(data, tmp)
        os.replace(tmp, path)  # atomic: a kill never leaves a half-written checkpoint
        return path

    def _load(self, path: Path) -> None:
        data = torch.load(path, map_location="cpu", weights_only=True)
        saved = TrainConfig.from_dict(data["config"])
        if saved != self.cfg:
            diff = [f.name for f in fields(TrainConfig) if getattr(saved, f.name) != getattr(self.cfg, f.name)]
            raise ValueError(f"{path}: checkpoint was written with different settings ({', '.join(diff)}); "
                             "use another output directory or the same settings")
        self.splats = torch.nn.ParameterDict(
            {k: torch.nn.Parameter(v.to(self.device)) for k, v in data["splats"].items()})
        self.optimizers = self._make_optimizers()
        for k, o in self.optimizers.items():
            o.load_state_dict(data["optimizers"][k])
        self.strat_state = {k: (v.to(self.device) if torch.is_tensor(v) else v) for k, v in data["strategy"].items()}
        self.step, self.elapsed = int(data["step"]), float(data["elapsed"])
        self.gen.set_state(data["generator"])
        self._order = list(data["order"])
        self.last = dict(data["last"])
