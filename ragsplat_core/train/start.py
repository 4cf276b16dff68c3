"""Where a run starts: the water it trains through (the dataset's with the config's overrides) and the
Gaussians it starts from (a point cloud, the refracted or straight-ray triangulation, or a plane at the bed's
depth)."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from ragsplat.dataset.load import Dataset, View
from ragsplat.errors import ConfigError, DatasetError
from ragsplat.gaussians import init_grid, init_points
from ragsplat.snell import footprint
from ragsplat.train.config import TrainConfig
from ragsplat.water_surface import WaterSurface

# No camera sees a bed deeper than this many times its height above the water through clear water (light,
# not geometry, limits photogrammetric bathymetry to a few tens of metres).
MAX_DEPTH_PER_HEIGHT = 10


def start_water(cfg: TrainConfig, ds: Dataset) -> WaterSurface | None:
    """The dataset's water with the config's overrides (None: train without water)."""
    water = ds.water
    if water is None and cfg.water_level is None:
        if cfg.water_n is not None or cfg.water_params:
            raise ConfigError(f"{ds.root}: the dataset has no water; give its level (water_level, "
                              f"--water-level) to {'calibrate' if cfg.water_params else 'set n'}")
        return None
    given = {"level": cfg.water_level, "n": cfg.water_n,
             "slope": None if cfg.water_slope is None else tuple(cfg.water_slope)}
    water = replace(water or WaterSurface(), **{k: v for k, v in given.items() if v is not None})
    check_cameras_above(ds.train, water, ConfigError)
    return water


def check_cameras_above(views: list[View], water: WaterSurface, error: type) -> None:
    """Every camera of `views` in air above `water`; else `error` in one line (refraction needs it)."""
    centres = np.array([v.camera.camera_center for v in views])
    i = int(np.argmax(water.depth(centres)))
    if not water.depth(centres[i]) < 0:
        raise error(f"the water surface ({float(water.height(centres[i, :2])):g} m there) is not below "
                    f"every training camera ({views[i].name} is at {centres[i, 2]:g} m): refraction "
                    f"needs the cameras in air")


def initial_splats(cfg: TrainConfig, ds: Dataset, water: WaterSurface | None) -> torch.nn.ParameterDict:
    """The Gaussians `cfg.init` starts from, seen by the dataset's training views through `water`."""
    views = ds.train
    if cfg.init in ("points", "triangulated", "refracted"):
        return _from_points(cfg, ds, water)
    bed = ds.bed
    depth = cfg.init_depth if cfg.init_depth is not None else bed.depth
    if depth is None:
        raise ConfigError("grid initialisation needs the bed depth: scene.json has no spec.bed.depth, "
                          "give init_depth (--init-depth)")
    surface = water or WaterSurface(0.0, 1.0)
    centres = np.array([v.camera.camera_center for v in views])
    # the plane's height under the flight
    z = float(surface.height(np.median(centres[:, :2], axis=0))) - depth
    height = float(-surface.depth(centres).max())
    # e.g. a depth given in mm: the grid would be kilometres wide
    if depth > MAX_DEPTH_PER_HEIGHT * height:
        raise ConfigError(f"init depth {depth:g} m is more than {MAX_DEPTH_PER_HEIGHT}x the cameras' "
                          f"height above the water ({height:.3g} m); give the bed depth in metres below "
                          "the water level (--init-depth)")
    # Everything the training views see of the plane (images are filled with bed to their edges, and
    # an uncovered part would render as background), clipped to the bed when its size is known.
    try:
        box = footprint([v.camera for v in views], water, z)
    except ValueError as err:
        raise DatasetError(f"{ds.root}: {err}") from None
    if bed.size is not None:
        h = bed.size / 2
        box = (max(box[0], -h), min(box[1], h), max(box[2], -h), min(box[3], h))
        if box[0] >= box[1] or box[2] >= box[3]:
            raise DatasetError(f"{ds.root}: the training views do not see the {bed.size} m bed "
                               f"at depth {depth} m")
    spacing = math.sqrt((box[1] - box[0]) * (box[3] - box[2]) / cfg.init_count)
    splats = init_grid(*box, z, spacing, cfg.sh_degree, cfg.init_opacity)
    if surface.tilted:  # the start follows the surface: `depth` below it everywhere
        with torch.no_grad():
            means = splats["means"]
            means[:, 2] = surface.height(means[:, :2].double()).to(means) - depth
    return splats


def _from_points(cfg: TrainConfig, ds: Dataset, water: WaterSurface | None) -> torch.nn.ParameterDict:
    from ragsplat.dataset.colmap import refracted_points, triangulated_points
    from ragsplat.tracks import fill_gaps

    if cfg.init == "refracted":
        if water is None:
            raise ConfigError("init='refracted' intersects rays through the water: the dataset has none")
        arr = refracted_points(ds.root, ds.fingerprint, {v.file_path: v.camera for v in ds.train}, water,
                               robust=cfg.init_robust)
    else:
        source = triangulated_points(ds.root, ds.fingerprint) \
            if cfg.init == "triangulated" else Path(cfg.init_points)
        if not source.is_file():
            raise ConfigError(f"{source}: point cloud file is missing")
        arr = np.load(source)
        if arr.ndim != 2 or arr.shape[1] not in (3, 6):
            raise ConfigError(f"{source}: expected an array [N, 3] or [N, 6], got {arr.shape}")
    if len(arr) > cfg.init_count:  # a survey's model can hold millions: a seeded random subset
        arr = arr[np.sort(np.random.default_rng(cfg.seed).choice(len(arr), cfg.init_count, replace=False))]
    if cfg.init_fill > 0:  # after the cap: it fills the gaps of the points actually used
        arr = np.concatenate([arr, fill_gaps(arr, cfg.init_fill)])
    pts = torch.from_numpy(arr[:, :3]).float()
    rgb = torch.from_numpy(arr[:, 3:]).float() if arr.shape[1] == 6 else torch.full_like(pts, 0.5)
    # straight-ray points sit at apparent depths (x n, the field's correction); refracted ones are true
    return init_points(pts, rgb, None if cfg.init == "refracted" else water, cfg.sh_degree, cfg.init_opacity)
