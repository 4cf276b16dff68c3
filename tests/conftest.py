"""Shared fixtures: tiny synthetic datasets rendered with our own rasterizer (no Blender, seconds).

Tests that start Blender carry the `blender` marker (`pytest -m "not blender"` skips them)."""

import math
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ragsplat.threads import THREAD_VARIABLES, cores_share

# Under pytest-xdist (`make test`) each worker process takes its share of the cores, set before torch and
# numba load: a threading library that takes every core in each of several processes slows them all.
WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if WORKERS > 1:
    for name in THREAD_VARIABLES:
        os.environ.setdefault(name, cores_share(WORKERS))

from ragsplat import train
from ragsplat.bench.synthetic import bed_scene, render_views, ring_cameras, write_dataset
from ragsplat.dataset import layout
from ragsplat.eval import metrics
from ragsplat.water_surface import WaterSurface

WATER = WaterSurface(0.0, 1.33)


def survey_cameras(lines_along_x: bool = False):
    """The synthetic surveys' flight: 12 nadir photos from 4 m over a 4 x 3 grid (flight lines along y, or
    along x), then 6 obliques on a 2.2 m ring aimed at the bed 0.8 m down; 240 x 180 px, 60 degrees."""
    from ragsplat.camera import Camera

    xs, ys = np.linspace(-1.2, 1.2, 4), np.linspace(-1.0, 1.0, 3)
    grid = [(x, y) for y in ys for x in xs] if lines_along_x else [(x, y) for x in xs for y in ys]
    cams = [Camera.look_at([x, y, 4.0], [x, y, 0.0], 240, 180, 60.0) for x, y in grid]
    return cams + [Camera.look_at([2.2 * math.cos(a), 2.2 * math.sin(a), 4.0], [0, 0, -0.8], 240, 180, 60.0,
                                  up=(0.0, 0.0, 1.0)) for a in np.arange(6) * math.pi / 3]


def channel_scene(seed: int) -> dict:
    """A channel 0.5 m deep at its centre between banks 0.3 m above the water (z = 0) beyond |y| = 1.5 m:
    `bed_scene`'s Gaussians raised onto it, speckled like gravel. A surveyed river's geometry in small:
    what fixes an unmeasured level is the depth varying and the waterline on both banks."""
    import torch

    from ragsplat.bench.synthetic import bed_scene

    scene = bed_scene(30000, half=3.0, depth=0.8, seed=seed)
    y = scene["means"][:, 1]
    scene["means"][:, 2] += 0.3 + 0.8 - 0.8 * torch.exp(-(y / 1.5) ** 2)
    scene["colors"] = torch.rand(30000, 3, generator=torch.Generator().manual_seed(seed + 1))
    return scene


def tiny_smoke(mp: pytest.MonkeyPatch, folder) -> None:
    """An ablation row in seconds: the smoke preset at 6 iterations of the torch rasterizer, opaque from the
    start and with no opacity reset (so the median depth, T <= 0.5, has a surface to fuse; the stretched
    schedule would reset at every step), and LPIPS n/a (its weights looked for in `folder`, where they are
    not)."""
    mp.setattr(metrics, "default_vgg16_path", lambda: folder / "absent.pth")
    smoke = train.PRESETS["smoke"]
    mp.setitem(train.PRESETS, "smoke", replace(smoke, iterations=6, init_count=200, init_opacity=0.9,
                                               densify=replace(smoke.densify, reset_every=30_000),
                                               backend="torch"))


def render_dataset(root, scene, cameras, water, test_views: int, region: dict, bed: dict | None = None,
                   backend: str = "auto"):
    """Render `scene` from `cameras` (the last `test_views` held out) and write it as a dataset."""
    views = render_views(scene, cameras, water, backend=backend)
    for i, v in enumerate(views):
        v["split"] = "train" if i < len(views) - test_views else "test"
    return write_dataset(root, views, water, region, bed)


@pytest.fixture(scope="session")
def evaluable_dataset(tmp_path_factory):
    """A bed 1 m under water seen by 5 training and 2 held-out views, with bed depth, evaluation region and
    a ground-truth grid of the bed surface: everything `ragsplat ablation` reads."""
    root = tmp_path_factory.mktemp("data")
    scene = bed_scene(200, half=1.0, depth=1.0, seed=0)
    cams = ring_cameras(4, 16, height=2.0, radius=0.8) + ring_cameras(2, 16, 2.2, 0.5, nadir=False)
    render_dataset(root, scene, cams, WATER, 2, {"xmin": -0.5, "xmax": 0.5, "ymin": -0.5, "ymax": 0.5},
                   bed={"depth": 1.0}, backend="torch")
    x, y = np.meshgrid(np.arange(-10, 11) * 0.05, np.arange(-10, 11) * 0.05, indexing="ij")
    z = -1.0 + 0.1 * np.sin(2.0 * x) * np.cos(1.5 * y)  # bed_scene's surface
    (root / "gt").mkdir()
    layout.write_npy(root / layout.GT_GRID, np.column_stack([x.ravel(), y.ravel(), z.ravel()]))
    return root


def kill_a_worker(argv: list[str], victim, env: dict | None = None, timeout: float = 300):
    """Runs the command `argv`, SIGKILLs the worker process `victim()` names once it does ((pid, log) or
    None, polled), and returns (that log, the command's stderr, its exit status) when the command ends."""
    import os
    import signal
    import subprocess
    import time

    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    found, deadline = None, time.time() + timeout
    while found is None and time.time() < deadline and proc.poll() is None:
        found = victim()
        time.sleep(0.01)
    assert found is not None, proc.communicate()
    os.kill(found[0], signal.SIGKILL)
    _, err = proc.communicate(timeout=600)
    return found[1], err, proc.returncode


def killed_and_resumed(cfg, dataset, folder, steps: int = 4):
    """(a trainer killed after `steps` steps of `cfg`, checkpointing every `cfg.checkpoint_every`; a new
    trainer on its folder, resumed from its last checkpoint, not yet trained on)."""
    from ragsplat.train import Trainer

    killed = Trainer(cfg, dataset, folder)
    for _ in range(steps):
        killed.train_step()
        if killed.step % cfg.checkpoint_every == 0:
            killed.save_checkpoint()
    return killed, Trainer(cfg, dataset, folder)


def water_bed(size: int = 24, count: int = 300, **optics):
    """The water terms' tiny scene: a textured bed 1 m below a level at 0.2 m rendered through water with the
    optics `optics` (`render_views`' attenuation= or backscatter=), seen by a nadir and six obliques 59
    degrees off it in air (each Gaussian's path 1.3x its depth); returns (the dataset, the bed's points and
    colours [N, 6]: a start that already has the geometry, so that the water's coefficients alone move)."""
    from pathlib import Path

    import torch

    from ragsplat.dataset import BedInfo, Dataset
    from ragsplat.dataset.load import View

    level, depth = 0.2, 1.0
    scene = bed_scene(count, 1.0, depth, seed=0)
    scene["means"][:, 2] += level
    water = WaterSurface(level, 1.33)
    cams = ring_cameras(6, size, level + 1.5, 2.5, target=(0, 0, level - depth))
    views = [View(f"{i:04d}", "train", "nadir", v["camera"], (v["image"] * 255).round().to(torch.uint8),
                  None, "", None, None) for i, v in enumerate(render_views(scene, cams, water, **optics))]
    return Dataset(Path("mem"), water, views, BedInfo(depth=depth, size=2.0)), \
        np.concatenate([scene["means"].numpy(), scene["colors"].numpy()], 1)


def water_bed_config(variant: str, **overrides):
    """A smoke training config of `variant` for `water_bed`: sh degree 0, no densification, checkpoints
    off."""
    from ragsplat.train import preset_config
    from ragsplat.train.strategy import DensifyConfig

    base = {"variant": variant, "iterations": 6, "init_depth": 1.0, "init_count": 300, "init_opacity": 0.9,
            "checkpoint_every": 0, "sh_degree": 0,
            "densify": DensifyConfig(refine_start_iter=10**6, refine_stop_iter=10**6, reset_every=10**6)}
    return preset_config("smoke", **{**base, **overrides})


def tiny_bed_run(root) -> Path:
    """A finished 2-iteration smoke run (root/run) on a bed 1 m under water seen by a ring of 5 cameras
    (root/data), for the tests of what reads a finished run (export, the TVU95 band)."""
    from ragsplat.cli.main import main

    region = {"xmin": -0.8, "xmax": 0.8, "ymin": -0.8, "ymax": 0.8}
    cams = ring_cameras(5, 20, 1.5, 0.8, target=(0, 0, -1))
    render_dataset(root / "data", bed_scene(300, 1.0, 1.0, seed=2), cams, WATER, 1, region)
    assert main(["train", "--data", str(root / "data"), "--out", str(root / "run"), "--preset", "smoke",
                 "--iterations", "2", "--init-depth", "1.0", "--no-progress"]) == 0
    return root / "run"
