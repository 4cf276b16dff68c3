"""A finished training run read back: its config, dataset and Gaussians (`load_run`), the model ready to
render as training rendered it (`Model`, `load_model`), the water it ended with (`run_water`), and its
renders at its dataset's views, through the water, without it, or as z-depth (`ragsplat render`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ragsplat.camera import Camera
from ragsplat.dataset import layout
from ragsplat.dataset.load import Dataset, View, load_dataset
from ragsplat.errors import ConfigError, DatasetError, OutputError
from ragsplat.gaussians import activated
from ragsplat.outputs import claim
from ragsplat.ply import load_ply
from ragsplat.rasterize import choose_backend
from ragsplat.rendering import (
    backscatter_tensor,
    fades_opacity,
    median_depth,
    reflection_tensor,
    render_splats,
)
from ragsplat.train.config import TrainConfig
from ragsplat.train.trainer import PLY
from ragsplat.water_surface import WaterSurface


def load_run(run: Path, data: Path | None = None) -> tuple[dict, Dataset, int]:
    """A finished run directory -> (activated Gaussians {means, scales, quats, opacities}, its `Dataset` read
    without images, the run's seed, which also seeds the extraction). `data` replaces the dataset directory
    config.json names (a moved dataset). Raises OutputError (not a finished run) or DatasetError (dataset
    missing or changed)."""
    _, ds, splats, seed = read_run(Path(run), data, splits=())
    return activated_dict(splats), ds, seed


def activated_dict(splats: dict) -> dict:
    """Raw parameters -> the activated Gaussians {means, scales, quats, opacities} the extraction takes."""
    scales, quats, opacities = activated(splats)
    return {"means": splats["means"], "scales": scales, "quats": quats, "opacities": opacities}


def read_run(run: Path, data: Path | None, **load) -> tuple[dict, Dataset, dict, int]:
    """(config.json, the dataset as `load_dataset(root, **load)` reads it, the PLY's raw parameters, the seed)
    of a finished run, checked as `load_run` says."""
    for name in ("config.json", PLY):
        if not (run / name).is_file():
            raise OutputError(f"{run}: not a finished training run (no {name}; `ragsplat train` writes it)")
    try:
        meta = json.loads((run / "config.json").read_text())
        dataset, seed = Path(meta["dataset"]), int(meta["config"]["seed"])
    except (ValueError, KeyError, TypeError):
        raise OutputError(f"{run / 'config.json'}: not a training run's config (no dataset or "
                          "seed)") from None
    root = dataset if data is None else Path(data)
    if not root.is_dir():
        raise DatasetError(f"{root}: the run's dataset directory does not exist (moved? give --data)")
    ds = load_dataset(root, **load)
    if meta.get("dataset_fingerprint") not in (None, ds.fingerprint):
        raise DatasetError(f"{root} is not the dataset {run} was trained on (fingerprint {ds.fingerprint}, "
                           f"the run's {meta['dataset_fingerprint']})")
    try:
        splats = load_ply(run / PLY)
    except ValueError as err:
        raise OutputError(str(err)) from None
    return meta, ds, splats, seed


RENDER_KINDS = ("wet", "dry", "depth")  # through the water as trained; the true Gaussians; z-depth of "dry"


@dataclass(eq=False)
class Model:
    """A finished run's Gaussians as the trainer held them, and what rendering them as training did takes."""

    splats: dict[str, torch.Tensor]  # raw parameters (`gaussians.py` layout) on `device`
    cfg: TrainConfig
    flags: dict | None  # the `refract_gaussians` flags training applied (config.json); None: plain 3DGS
    water: WaterSurface | None
    device: torch.device
    backend: str
    # the water's attenuation coefficients [3] (1/m) training ended with (config.json); None: not trained
    attenuation: torch.Tensor | None = None
    # the water's backscatter [2, 3] (B_inf, c_b) training ended with (config.json); None: not trained
    backscatter: torch.Tensor | None = None
    # the sky map [S, S, 3] the surface mirrors (linear radiance) training ended with (config.json); None: not
    # trained
    reflection: torch.Tensor | None = None

    def gaussians(self) -> dict:
        return activated_dict(self.splats)

    def render(self, camera: Camera, interface: bool = True):
        """(image [H,W,3] in [0, 1], alpha [H,W,1], z-depth [H,W,1]) of `camera`, as `Trainer.render` gives
        them: interface=True through the water as trained, False the true Gaussians (the bed drained)."""
        center = torch.tensor(camera.camera_center, dtype=torch.float32, device=self.device)
        background = torch.tensor(self.cfg.background, dtype=torch.float32, device=self.device)
        with torch.no_grad():
            img, alpha, depth, _ = render_splats(
                self.splats, camera, center, self.cfg.active_sh_degree(self.cfg.iterations), self.water,
                self.flags if interface else None, self.cfg.surfels, background, self.backend,
                attenuation=self.attenuation if interface else None,
                backscatter=self.backscatter if interface else None,
                reflection=self.reflection if interface else None, wet_degree=self.cfg.wet_sh_degree,
                surfel_depth=self.cfg.surfel_depth, downwelling=self.cfg.downwelling)
        return img.clamp(0, 1), alpha, depth

    def median_depth(self, camera: Camera) -> torch.Tensor:  # [H, W], see `rendering.median_depth`
        return median_depth(self.splats, camera, self.cfg.surfels,
                            self.water if fades_opacity(self.flags) else None, self.backend)


def load_model(run: Path, data: Path | None = None, splits: tuple[str, ...] = ()) -> tuple[Model, Dataset]:
    """A finished run ready to render, and its dataset with the views of `splits` (their wet images only).
    It renders where it trained when this machine can (the same pixels as in training), else on the CPU.
    Raises as `load_run`."""
    run = Path(run)
    meta, ds, splats, _ = read_run(run, data, splits=splits, load_dry=False)
    try:
        cfg, flags, trained_on = (TrainConfig.from_dict(meta["config"]), meta["refraction_applied"],
                                  meta["device"])
    except (KeyError, TypeError):
        raise OutputError(f"{run / 'config.json'}: not a training run's config (no refraction_applied or "
                          "device)") from None
    device = torch.device(trained_on)
    if device.type == "cuda" and not torch.cuda.is_available():
        device = torch.device("cpu")
    backend = cfg.backend
    try:
        choose_backend(backend, device)
    except ConfigError:  # e.g. trained with gsplat, rendered here without it: the same semantics
        backend = "auto"
    splats = {k: v.to(device) for k, v in splats.items()}
    c = meta.get("attenuation_final")
    attenuation = None if c is None else torch.tensor(c, dtype=torch.float32, device=device)
    b = meta.get("backscatter_final")
    backscatter = None if b is None else backscatter_tensor(b, device)
    r = meta.get("reflection_final")
    reflection = None if r is None else reflection_tensor(r, device)
    return Model(splats, cfg, flags, run_water(meta, ds), device, backend, attenuation, backscatter,
                 reflection), ds


def run_water(meta: dict, ds: Dataset) -> WaterSurface | None:
    """The water a run is rendered and exported under, read in this one place: where training left it as
    config.json records it (`water_final`: calibrated or overridden; None for a dry scene), else the water it
    started from, else, for a config.json without the record, the dataset's."""
    for key in ("water_final", "water"):
        if meta.get(key) is not None or (key == "water" and key in meta):
            w = meta[key]
            return None if w is None else WaterSurface(float(w["level"]), float(w["n"]),
                                                       tuple(float(v) for v in w.get("slope", (0.0, 0.0))))
    return ds.water


def select_views(ds: Dataset, name: str, split: str = "all") -> list[View]:
    """The views of `split` ("train", "test", "all") named `name`, or all of them for "all". Raises
    ConfigError for a name not among them (naming a few that are)."""
    views = ds.views if split == "all" else ds.split(split)
    if name == "all":
        return views
    found = [v for v in views if v.name == name]
    if not found:
        names = [v.name for v in views]
        few = ", ".join(names[:3] + (["...", names[-1]] if len(names) > 4 else names[3:]))
        where = "" if split == "all" else f" {split}"
        raise ConfigError(f"no view {name!r} among the {len(names)}{where} views of {ds.root} ({few})")
    return found


def write_render(model: Model, view: View, kind: str, out: Path) -> list[Path]:
    """Render `view` as `kind` (`RENDER_KINDS`) into `out`: NAME.png; for "depth" also NAME.exr, the z-depth
    in metres (float32 channel "Y" as the dataset's gt/depth files, `layout.NO_HIT` where nothing was drawn),
    the PNG then showing it in colour (near yellow, far purple, stretched from the view's nearest to its
    farthest 1 % of opaque pixels; black: nothing drawn). Returns the paths written."""
    if kind not in RENDER_KINDS:
        raise ConfigError(f"unknown render kind {kind!r}; choose one of {', '.join(RENDER_KINDS)}")
    img, alpha, depth = model.render(view.camera, interface=kind == "wet")
    png = Path(out) / f"{view.name}.png"
    if kind != "depth":
        layout.write_png(png, img)
        return [png]
    alpha, depth = alpha[..., 0].cpu().numpy(), depth[..., 0].cpu().numpy()
    hit = alpha > 0  # the rasterizer's depth is 0 where no Gaussian was composited
    exr = png.with_suffix(".exr")
    layout.write_depth(exr, np.where(hit, depth, layout.NO_HIT))
    layout.write_png(png, depth_colours(depth, hit, alpha >= 0.5))
    return [exr, png]


def depth_colours(depth: np.ndarray, hit: np.ndarray, opaque: np.ndarray) -> np.ndarray:
    """[H, W] z-depth -> [H, W, 3] colours in [0, 1] (viridis reversed: near is yellow), black where not
    `hit`; the scale spans the 1st to 99th percentile of the `opaque` pixels (of the hit ones if none is)."""
    import matplotlib

    ref = depth[opaque] if opaque.any() else depth[hit]
    lo, hi = np.percentile(ref, [1, 99]) if len(ref) else (0.0, 1.0)
    t = np.clip((depth - lo) / max(hi - lo, 1e-9), 0, 1)
    rgb = matplotlib.colormaps["viridis_r"](t)[..., :3]
    return np.where(hit[..., None], rgb, 0.0)


def render_views(model: Model, views: list[View], kind: str, out: Path, on_view=None) -> list[Path]:
    """`write_render` of every view into `out` (a directory of ragsplat's renders: one holding other files
    is refused); `on_view(view)` after each. Returns the paths written."""
    claim(out, "renders")
    written = []
    for view in views:
        written += write_render(model, view, kind, out)
        if on_view is not None:
            on_view(view)
    return written
