"""Median time of one training iteration, per rasterizer backend and size (`ragsplat bench train-step`).

Each timed iteration is `Trainer.train_step` itself (SH colours, the refraction transform for `full`,
rasterize, L1 + SSIM loss, backward, NaN checks, Adam, densification statistics) at 256 x 256 on a
synthetic under-water bed seen from a nadir and four 20-degree oblique cameras, with N Gaussians on a grid
over the nadir footprint (all in view), SH degree 3 active and no growing or pruning during the timing
(refinement starts later in the paper schedule), so N stays fixed. `3dgs`, `full` and `2dgs+full` (refracted
surfels) iterations alternate in one loop so all see the same machine state; the overhead ratios are
median(full) / median(3dgs) and median(2dgs+full) / median(full).
The two do not rasterize the same work (the apparent Gaussians are smaller, fainter and closer to the
axis), so the transform's own cost, forward + backward of `refract_gaussians`, is printed beside it
(`refr`, and as a share of the 3dgs iteration). `--attenuation` also times `2dgs+full+attenuation` (the
water's attenuation) in the same loop, beside `2dgs+full` and as a ratio to it (of the medians, and
the median of the step-by-step ratios, which a busy machine moves less); `--backscatter` likewise
`2dgs+full+backscatter` (the water column's veil) and `2dgs+full+water` (all three terms); `--reflection`
`2dgs+full+reflection` (the surface's reflection of the sky).
"""

from __future__ import annotations

import math
import statistics
import time
from pathlib import Path

import torch

from ragsplat.bench.synthetic import bed_scene, render_views
from ragsplat.camera import Camera
from ragsplat.dataset.load import BedInfo, Dataset, View
from ragsplat.water_surface import WaterSurface

SIZE = 256
ALTITUDE = 4.0  # camera height above the water (m)
DEPTH = 3.0  # bed depth below the water (m)


def backends_available() -> list[tuple[str, str]]:
    """(backend, device) pairs this machine can run."""
    from ragsplat.rasterize import gsplat_available

    pairs = [("cpu", "cpu"), ("torch", "cpu")]
    if torch.cuda.is_available():
        pairs.append(("torch", "cuda"))
        if gsplat_available():
            pairs.append(("gsplat", "cuda"))
    return pairs


def _dataset(count: int, water: WaterSurface, device: str) -> Dataset:
    """Five views of a textured bed rendered through the water, kept in memory."""
    # nadir footprint on the bed (paraxial)
    half = (ALTITUDE + DEPTH / water.n) * math.tan(math.radians(35.0))
    cams = [Camera.look_at([0.0, 0.0, ALTITUDE], [0.0, 0.0, -DEPTH], SIZE, SIZE, 70.0)]
    for k in range(4):
        a = k * math.pi / 2
        r = ALTITUDE * math.tan(math.radians(20.0))
        cams.append(Camera.look_at([r * math.cos(a), r * math.sin(a), ALTITUDE], [0.0, 0.0, -DEPTH], SIZE,
                                   SIZE, 70.0, up=(0.0, 0.0, 1.0)))
    scene = bed_scene(count, half, DEPTH, seed=1, device=device)
    views = []
    for i, v in enumerate(render_views(scene, cams, water)):
        rgb = (v["image"].cpu() * 255 + 0.5).to(torch.uint8)
        views.append(View(f"{i:04d}", "train", "bench", v["camera"], rgb, None, "", None, None))
    # a bed exactly the nadir footprint: the trainer's grid is clipped to it, so every Gaussian is in view
    return Dataset(Path("."), water, views, BedInfo(depth=DEPTH, size=2 * half),
                   {"xmin": -half, "xmax": half, "ymin": -half, "ymax": half})


def _transform_time(tr, steps: int, device: str, transform) -> float:
    """Median seconds of `transform` (`refract_gaussians` or its compiled twin) alone, forward + backward with
    `full` flags, on the trainer's Gaussians, cut out of the graph: the part of a `full` iteration that plain
    3DGS does not do."""
    from ragsplat.gaussians import activated, colors_for_view

    with torch.no_grad():
        scales, quats, opac = activated(tr.splats)
        colors = colors_for_view(tr.splats, tr.centers[0], tr.active_sh_degree)
    leaves = [t.detach().clone().requires_grad_(True)
              for t in (tr.splats["means"], scales, quats, opac, colors)]
    out = []
    for i in range(steps + 1):
        center = tr.centers[i % len(tr.centers)]
        t0 = time.perf_counter()
        a = transform(*leaves, center, tr.water, **tr.flags)
        (a.means.sum() + a.scales.sum() + a.opacities.sum() + a.colors.sum()).backward()
        if device == "cuda":
            torch.cuda.synchronize()
        if i:  # the first call warms up (and compiles)
            out.append(time.perf_counter() - t0)
    return statistics.median(out)


def bench_train_step(counts=(10_000, 40_000), pairs=None, steps: int = 10, warmup: int = 3, seed: int = 0,
                     log=print, compiled: bool = False, attenuation: bool = False,
                     backscatter: bool = False, reflection: bool = False) -> list[dict]:
    """One row per (backend, device, N): median seconds per iteration for 3dgs, full and 2dgs+full, and the
    ratios full / 3dgs and 2dgs+full / full. `compiled`: also `full` and `2dgs+full` with the transform
    through torch.compile (`TrainConfig.compile_refraction`; the warm-up steps take the compile), in the same
    loop, and their ratios to the eager ones. `attenuation`: also 2dgs+full+attenuation, and its ratio to
    2dgs+full; `backscatter`: also 2dgs+full+backscatter and 2dgs+full+water, and theirs; `reflection`: also
    2dgs+full+reflection, and its (row keys: the terms; `paired_ratio`: the median of the step-by-step
    ratios)."""
    from ragsplat.refraction import compiled_refract_gaussians, refract_gaussians
    from ragsplat.train import Trainer, preset_config

    water = WaterSurface(0.0, 1.33)
    rows = []
    for backend, device in pairs or backends_available():
        for count in counts:
            ds = _dataset(count, water, device)
            trainers = {}
            terms = {"attenuation": "2dgs+full+attenuation"} if attenuation else {}
            if backscatter:
                terms.update(backscatter="2dgs+full+backscatter", water="2dgs+full+water")
            if reflection:
                terms["reflection"] = "2dgs+full+reflection"
            runs = ([("3dgs", False), ("full", False), ("2dgs+full", False)]
                    + [(v, False) for v in terms.values()])
            for variant, fused in runs + ([("full", True), ("2dgs+full", True)] if compiled else []):
                # paper schedule (30k): refinement starts at 500, after the timed steps; SH degree 3 at once
                cfg = preset_config("paper", variant=variant, seed=seed, backend=backend, device=device,
                                    init_depth=DEPTH, init_count=count, sh_degree_every=1, checkpoint_every=0,
                                    compile_refraction=fused)
                trainers[variant + " compiled" * fused] = Trainer(cfg, ds, None)
            times = {v: [] for v in trainers}
            for i in range(warmup + steps):
                for variant, tr in trainers.items():
                    t0 = time.perf_counter()
                    tr.train_step()
                    if device == "cuda":
                        torch.cuda.synchronize()
                    if i >= warmup:
                        times[variant].append(time.perf_counter() - t0)
            med = {v: statistics.median(t) for v, t in times.items()}
            med["transform"] = _transform_time(trainers["full"], steps, device, refract_gaussians)
            row = {"backend": backend, "device": device, "size": f"{SIZE}x{SIZE}",
                   "gaussians": trainers["full"].num_gaussians, "steps": steps,
                   "median_s_3dgs": med["3dgs"], "median_s_full": med["full"],
                   "ratio_full_3dgs": med["full"] / med["3dgs"], "median_s_2dgs_full": med["2dgs+full"],
                   "ratio_2dgs_full_full": med["2dgs+full"] / med["full"],
                   "median_s_transform": med["transform"],
                   "transform_share_of_3dgs": med["transform"] / med["3dgs"],
                   "all_s_3dgs": times["3dgs"], "all_s_full": times["full"],
                   "all_s_2dgs_full": times["2dgs+full"]}
            rows.append(row)
            log(f"{backend:>6} {device:>4} {row['gaussians']:>6} {med['3dgs']:10.4f} {med['full']:10.4f} "
                f"{row['ratio_full_3dgs']:9.3f} {med['transform']:10.4f} "
                f"{row['transform_share_of_3dgs']:9.3f} {med['2dgs+full']:10.4f} "
                f"{row['ratio_2dgs_full_full']:9.3f}")
            for key, variant in terms.items():
                t, base = med[variant], med["2dgs+full"]
                paired = statistics.median(a / b for a, b in zip(times[variant], times["2dgs+full"]))
                row[key] = {"median_s": t, "ratio_2dgs_full": t / base, "paired_ratio": paired,
                            "all_s": times[variant]}
                log(f"{'':>18} {variant} {t:.4f} s, 2dgs+full {base:.4f} s: x{t / base:.3f} "
                    f"(step by step x{paired:.3f})")
            if compiled:
                med["transform compiled"] = _transform_time(trainers["full"], steps, device,
                                                            compiled_refract_gaussians())
                ratio = {k: med[f"{k} compiled"] / med[k] for k in ("full", "2dgs+full", "transform")}
                row["compiled"] = {k: {"median_s": med[f"{k} compiled"], "ratio_to_eager": r}
                                   for k, r in ratio.items()}
                row["compiled"]["all_s"] = {k: times[f"{k} compiled"] for k in ("full", "2dgs+full")}
                log(f"{'':>18} compiled: full {med['full compiled']:.4f} s (x{ratio['full']:.3f} of eager), "
                    f"2dgs+full {med['2dgs+full compiled']:.4f} s (x{ratio['2dgs+full']:.3f}), "
                    f"refr {med['transform compiled']:.4f} s (x{ratio['transform']:.3f})")
    return rows
