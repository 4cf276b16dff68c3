"""How much of the bed's texture a wet photo still carries above the renderer's own noise, by depth:
`python -m tools.render_noise DATA [--pass wet] [--views 4] [--seed-offset 1000] [--samples N]
[--sigma 2]`.

DATA is a synthetic dataset (`ragsplat generate`). The PASS (wet, or dry: the same scene without the water)
of the VIEWS training views that see the most of the deepest third is rendered again with Cycles' sampling
seed moved by SEED_OFFSET (everything else, the ripples included, as the dataset has it); the first of them
also with the dataset's own seed, a check that the second render differs by its sampling alone. With SAMPLES,
both photos are rendered here at that count instead. Each pixel is binned by the water depth of the bed point
its dry z-depth lands on (the wet ray meets the bed a little beside it: a bin, not a per-pixel truth). With A
the first photo and B the second, both high-passed (the image minus its Gaussian blur of SIGMA pixels):

- noise: the std of A - B over sqrt 2 (8-bit levels), in the whole image and in the high-pass band;
- texture: sqrt(cov(hp A, hp B)), the bed's texture in the wet photo (the noise of two seeds is independent,
  so the covariance holds the signal alone); dry: the std of the dry photo's high pass in the same pixels;
- SNR: texture over the high-pass noise of one photo (training sees each point in many).

Prints one Markdown table per colour channel."""

from __future__ import annotations

import argparse
import json
import tempfile
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from ragsplat.datagen import flight
from ragsplat.datagen.build import _task, render_job, run_blender
from ragsplat.datagen.spec import SceneSpec
from ragsplat.dataset import layout

CHANNELS = ("red", "green", "blue")


def thirds(root: Path) -> list[tuple[float, float]]:
    """The evaluation's depth bands (`eval.evaluate`), (lo, hi] metres: thirds of the reach's deepest water,
    the last one open below."""
    deepest = json.loads((root / layout.SCENE).read_text())["null_models"]["max_depth_m"]
    return [(k * deepest / 3, (k + 1) * deepest / 3 if k < 2 else np.inf) for k in range(3)]


def dataset_spec(root: Path) -> SceneSpec:
    """The spec the dataset was rendered from, as `ragsplat generate` saved it."""
    return SceneSpec.from_dict(json.loads((root / "scene" / "spec.json").read_text()))


def water_depth(pose, root: Path, level: float) -> np.ndarray:
    """[H, W] metres below `level` of the dry bed point each pixel sees (NaN where none or above it)."""
    depth = layout.read_depth(layout.output_path(root, "depth", pose.name)).astype(np.float64)
    cam = pose.camera
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    pixels = np.stack([u.ravel() + 0.5, v.ravel() + 0.5], -1).astype(np.float64)
    points = cam.unproject(pixels, depth.ravel())
    d = (level - points[:, 2]).reshape(depth.shape)
    d[(depth >= layout.NO_HIT / 2) | (d <= 0)] = np.nan
    return d


def read_rgb(path: Path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float64)  # [H, W, 3] RGB levels


def high_pass(image: np.ndarray, sigma: float) -> np.ndarray:
    return image - cv2.GaussianBlur(image, (0, 0), sigma)


def band_figures(a: np.ndarray, b: np.ndarray, dry: np.ndarray, sigma: float) -> dict[str, np.ndarray]:
    """Per-pixel products the table's statistics are means of: [H, W, 3] each."""
    ha, hb, hd = high_pass(a, sigma), high_pass(b, sigma), high_pass(dry, sigma)
    return {"diff2": (a - b) ** 2 / 2, "hdiff2": (ha - hb) ** 2 / 2, "cov": ha * hb, "dry2": hd ** 2,
            "mean": (a + b) / 2}


def table(sums: dict, channel: int, bands: list[tuple[float, float]]) -> str:
    lines = [("| depth | pixels | level | noise | noise (high pass) | texture | texture, dry | over dry "
              "| SNR |"),
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for (lo, hi), s in zip(bands, sums["thirds"]):
        band = f"{lo:.3g}-{hi:.3g} m" if np.isfinite(hi) else f"over {lo:.3g} m"
        n = s["n"]
        if n == 0:
            lines.append(f"| {band} | 0 | | | | | | | |")
            continue
        m = {k: v[channel] / n for k, v in s.items() if k != "n"}
        noise, hnoise = np.sqrt(m["diff2"]), np.sqrt(m["hdiff2"])
        texture, dry = np.sqrt(max(m["cov"], 0.0)), np.sqrt(m["dry2"])
        lines.append(f"| {band} | {n} | {m['mean']:.1f} | {noise:.2f} | {hnoise:.2f} | "
                     f"{texture:.2f} | {dry:.2f} | {texture / dry:.2f} | {texture / hnoise:.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.render_noise",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("--pass", dest="kind", choices=("wet", "dry"), default="wet")
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--seed-offset", type=int, default=1000)
    parser.add_argument("--samples", type=int, default=None,
                        help="render both photos at this many samples a pixel (default: A is the dataset's)")
    parser.add_argument("--sigma", type=float, default=2.0,
                        help="the high pass's Gaussian, pixels (default 2)")
    args = parser.parse_args(argv)
    root = args.data
    spec = dataset_spec(root)
    level, bands = spec.level, thirds(root)
    train = [p for p in flight.plan(spec) if p.split == "train"]
    depths = {p.name: water_depth(p, root, level) for p in train}
    deep = sorted(train, key=lambda p: -np.sum(depths[p.name] > bands[-1][0]))[:args.views]
    samples = args.samples or spec.render.samples
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)

        def rendered(views, seed: int, suffix: str) -> dict[str, Path]:
            paths = {p.name: tmp / f"{p.name}-{suffix}.png" for p in views}
            tasks = [_task(spec, args.kind, p, paths[p.name]) for p in views]
            job = render_job(spec, root, views[0].camera, tasks)
            run_blender(replace(job, render=replace(job.render, seed=seed, samples=samples)), tmp)
            return paths

        b = rendered(deep, spec.seed + args.seed_offset, "b")
        if args.samples is None:  # A: the dataset's photos, checked against a re-render at their own seed
            a = {p.name: layout.output_path(root, args.kind, p.name) for p in deep}
            again = rendered(deep[:1], spec.seed, "a")[deep[0].name]
            same = np.abs(read_rgb(again) - read_rgb(a[deep[0].name]))
            check = (f"re-rendered at the dataset's own seed, view {deep[0].name}: max |difference| "
                     f"{same.max():.0f} levels, {np.mean(same > 0) * 100:.2f} % of values differ")
        else:
            a = rendered(deep, spec.seed, "a")
            check = f"both photos rendered here at {samples} samples (the dataset has {spec.render.samples})"
        keys = ("diff2", "hdiff2", "cov", "dry2", "mean")
        sums = {"thirds": [{"n": 0, **{k: np.zeros(3) for k in keys}} for _ in bands]}
        for p in deep:
            dry = read_rgb(layout.output_path(root, "dry", p.name))
            fig = band_figures(read_rgb(a[p.name]), read_rgb(b[p.name]), dry, args.sigma)
            d = depths[p.name]
            for (lo, hi), s in zip(bands, sums["thirds"]):
                inside = (d > lo) & (d <= hi)
                s["n"] += int(inside.sum())
                for k in keys:
                    s[k] += fig[k][inside].sum(0)
    print(f"{root}, {args.kind} pass: views {', '.join(f'{p.name} ({p.kind})' for p in deep)}; "
          f"{samples} samples a pixel; sampling seed {spec.seed} against {spec.seed + args.seed_offset}; "
          f"high pass: minus a {args.sigma:g} px Gaussian; 8-bit levels")
    print(check)
    for c, name in enumerate(CHANNELS):
        print(f"\n{name}\n")
        print(table(sums, c, bands))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
