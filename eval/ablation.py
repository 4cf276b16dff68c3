"""`ragsplat ablation`: train every variant, evaluate it, and regenerate the paper's Tables 1 and 2.

    ragsplat ablation --data DIR --out DIR [--preset smoke|small|paper] [--variants ...] [--seed S]

Per variant (a row): train with evaluation checkpoints (PSNR in both conditions and F1@10cm against
training wall-clock time), then evaluate on the held-out views (PSNR, SSIM, LPIPS; `refr` = rendered
through the interface vs the with-water images, `dry` = true Gaussians without it vs the dry images) and
the geometry (extraction + Chamfer / F1 against `DIR/gt/bed_grid.npy` inside `eval_region`). Each finished
row is written to `OUT/<variant>/row.json` at once, so a rerun (after a kill) reuses it and trains only
what is missing. Then `OUT/results.json` (every number, per-view values, configs, seed, versions,
timings), `OUT/table1.md`, `OUT/table2.md` and `OUT/error_vs_time.png` are (re)written from all rows, and
the tables are printed with the paper's published values in adjacent columns.
"""

from __future__ import annotations

import hashlib
import json
import math
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from eval import metrics
from eval.geometry import ExtractConfig, extract_surface, geometry_metrics
from eval.plots import error_vs_time
from eval.tables import VARIANTS, load_published, table1, table2
from ragsplat_core.cli import UsageError

ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class AblationPreset:
    """What the harness itself varies by preset (training sizes come from the trainer's preset)."""

    name: str
    checkpoints: int  # evaluation points along training for the error-vs-time curves (end included)
    samples_per_cell: int  # extraction samples per GT grid cell (n_samples = this x GT points)
    curve_samples_per_cell: int  # the same for the cheaper F1 at the checkpoints


PRESETS = {
    "smoke": AblationPreset("smoke", checkpoints=2, samples_per_cell=16, curve_samples_per_cell=8),
    "small": AblationPreset("small", checkpoints=5, samples_per_cell=16, curve_samples_per_cell=8),
    "paper": AblationPreset("paper", checkpoints=8, samples_per_cell=16, curve_samples_per_cell=8),
}


# ---------------------------------------------------------------- evaluation of one trained model


def _mean(values) -> float | None:
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else None


def evaluate_views(render: Callable, views, lpips_metric=None) -> dict:
    """Appearance on `views` (objects with `.name`, `.kind`, `.image`, `.dry` as in `ragsplat_core.data`).

    `render(view, interface: bool) -> [H, W, 3]` renders through the interface (True) or the true
    Gaussians without it (False). Renders are clamped to [0, 1] (as 3DGS evaluates them); the metrics run
    on the render's device, where `lpips_metric` must already be (`LPIPS.to`). Returns
    {"refr": {"psnr", "ssim", "lpips"}, "dry": {...} or None, "per_view": [...]}.
    """
    per_view = []
    for view in views:
        entry = {"name": view.name, "kind": view.kind}
        for cond, target in (("refr", view.image), ("dry", view.dry)):
            if target is None:
                entry[cond] = None
                continue
            with torch.no_grad():
                img = render(view, cond == "refr").clamp(0, 1)
                target = target.to(img.device, img.dtype)  # metrics run where the render is (LPIPS too)
                entry[cond] = {"psnr": float(metrics.psnr(img, target)), "ssim": float(metrics.ssim(img, target)),
                               "lpips": None if lpips_metric is None else float(lpips_metric(img, target))}
        per_view.append(entry)
    out = {"per_view": per_view}
    for cond in ("refr", "dry"):
        rows = [v[cond] for v in per_view if v[cond] is not None]
        out[cond] = {k: _mean(r[k] for r in rows) for k in ("psnr", "ssim", "lpips")} if rows else None
    return out


def evaluate_geometry(gaussians: dict, gt: np.ndarray, region: dict, cfg: ExtractConfig) -> dict:
    """Extraction + metrics; `gaussians` has means, scales (linear), quats (wxyz), opacities ([0, 1]).

    `gt` is the dataset's grid, already limited to `region` by the data contract (not cropped again: its
    edge nodes would come and go with rounding).
    """
    origin = tuple(gt[:, :2].min(0))  # a node of the GT grid, so both grids share their nodes
    grid, stats = extract_surface(gaussians["means"], gaussians["scales"], gaussians["quats"],
                                  gaussians["opacities"], cfg, region, origin)
    return {**geometry_metrics(grid, gt), "extraction": stats}


# ---------------------------------------------------------------- rows on disk (resume)


def fingerprint(data: Path) -> str:
    """Identifies the dataset a row was computed on (its transforms.json and scene.json)."""
    h = hashlib.sha256()
    for name in ("transforms.json", "scene.json"):
        p = data / name
        h.update(p.read_bytes() if p.is_file() else b"-")
    return h.hexdigest()[:16]


def row_path(out: Path, variant: str) -> Path:
    return out / variant / "row.json"


def load_row(out: Path, variant: str, key: dict) -> dict | None:
    """A finished row for `variant`, or None; a row made under another dataset/preset/seed is an error."""
    path = row_path(out, variant)
    if not path.is_file():
        return None
    try:
        row = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise UsageError(f"{path}: unreadable finished row ({err}); delete it to recompute") from None
    if row.get("key") != key:
        raise UsageError(f"{path} was made with {row.get('key')}, not {key}; use another --out or delete it")
    return row


def save_row(out: Path, variant: str, row: dict) -> None:
    path = row_path(out, variant)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(_jsonable(row), indent=1))
    tmp.replace(path)  # atomic: a kill never leaves a half-written row that looks finished


def _jsonable(x):
    """Non-finite floats -> None (strict JSON), numpy scalars -> Python numbers."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def versions() -> dict:
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], check=False, cwd=ROOT, capture_output=True, text=True,
                                timeout=10).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        commit = None
    import scipy

    return {"python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__,
            "scipy": scipy.__version__, "platform": platform.platform(), "git_commit": commit}


# ---------------------------------------------------------------- outputs


def notes(rows: dict[str, dict], lpips_reason: str) -> list[str]:
    out = []
    if lpips_reason:
        out.append(f"LPIPS n/a: {lpips_reason}")
    if "3dgs" in rows:
        out.append("3dgs has no interface model: its `refr` values compare its plain render with the "
                   "with-water images (the paper leaves these cells empty).")
    out.append("Time: training wall clock on this machine (evaluation checkpoints excluded); the paper's is "
               "an RTX 3090 at 800 x 800, 30k iterations.")
    return out


def write_outputs(out: Path, rows: dict[str, dict], header: dict, lpips_reason: str) -> str:
    """results.json, table1.md, table2.md, error_vs_time.png from the rows; returns the tables' text."""
    published = load_published()
    ordered = {v: rows[v] for v in VARIANTS if v in rows}
    t1 = table1(ordered, published, notes(ordered, lpips_reason))
    t2 = table2(ordered, published, [f"Geometry: {header.get('geometry_note', '')}".rstrip(": ")])
    out.mkdir(parents=True, exist_ok=True)
    (out / "table1.md").write_text(t1)
    (out / "table2.md").write_text(t2)
    curves = {v: r.get("curve", []) for v, r in ordered.items()}
    error_vs_time(curves, out / "error_vs_time.png", title=f"error vs training time ({header.get('preset', '')})")
    results = {**header, "lpips": {"available": not lpips_reason, "reason": lpips_reason or None},
               "published": published, "variants": ordered}
    tmp = out / "results.json.tmp"
    tmp.write_text(json.dumps(_jsonable(results), indent=1))
    tmp.replace(out / "results.json")
    return t1 + "\n" + t2


def run_ablation(data: Path, out: Path, preset: str, variants: list[str], seed: int,
                 train_and_evaluate: Callable[..., dict], vgg16: str | None = None,
                 log: Callable[[str], None] = print) -> dict[str, dict]:
    """Rows for `variants` (reused from `out` when finished there, else trained via `train_and_evaluate`),
    then all outputs. `train_and_evaluate(variant=, data=, out=, preset=, seed=, lpips_metric=)` returns a row.
    """
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise UsageError(f"unknown variant {unknown[0]!r}; choose from {', '.join(VARIANTS)}")
    if preset not in PRESETS:
        raise UsageError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    key = {"data": str(data.resolve()), "fingerprint": fingerprint(data), "preset": preset, "seed": seed}
    lpips_metric, lpips_reason = metrics.load_lpips(vgg16)
    if lpips_reason:
        log(f"LPIPS n/a: {lpips_reason}")
    rows = {}
    for variant in variants:
        row = load_row(out, variant, key)
        if row is not None:
            log(f"[{variant}] reusing the finished row in {row_path(out, variant)}")
        else:
            log(f"[{variant}] training ...")
            t0 = time.perf_counter()
            row = train_and_evaluate(variant=variant, data=data, out=out / variant, preset=preset, seed=seed,
                                     lpips_metric=lpips_metric)
            row = {**row, "key": key, "variant": variant, "lpips_reason": lpips_reason or None,
                   "timings": {**row.get("timings", {}), "row_total_s": time.perf_counter() - t0}}
            save_row(out, variant, row)
        rows[variant] = row
    # rows finished in earlier runs for variants not asked for this time stay in the tables
    for variant in VARIANTS:
        if variant not in rows and row_path(out, variant).is_file():
            rows[variant] = load_row(out, variant, key)
    header = {"data": key["data"], "dataset_fingerprint": key["fingerprint"], "preset": preset, "seed": seed,
              "harness_preset": asdict(PRESETS[preset]), "versions": versions(), "command": sys.argv,
              "geometry_note": "CD in metres (mean of accuracy and completeness, unsquared); P/R/F1 in %, "
                               "strict < threshold."}
    log(write_outputs(out, rows, header, lpips_reason))
    return rows


def extract_config(preset: str, n_gt: int, seed: int, curve: bool = False) -> ExtractConfig:
    p = PRESETS[preset]
    per_cell = p.curve_samples_per_cell if curve else p.samples_per_cell
    return replace(ExtractConfig(), n_samples=per_cell * n_gt, seed=seed)


# ---------------------------------------------------------------- the trainer integration


def eval_steps(iterations: int, checkpoints: int, reset_every: int = 0, reset_stop: int = 0) -> list[int]:
    """Evenly spaced evaluation steps before the end (the trainer adds the end itself).

    A step that lands on an opacity reset (every `reset_every` steps before `reset_stop`) moves one step
    earlier: right after a reset every opacity sits below the extraction's cull threshold, so the curve
    would show the reset, not the state of training.
    """
    steps = set()
    for k in range(1, checkpoints):
        step = round(k * iterations / checkpoints)
        if reset_every and step < reset_stop and step % reset_every == 0:
            step -= 1
        steps.add(step)
    return sorted(steps - {0, iterations})


class TrainEval:
    """`train_and_evaluate` for `run_ablation` on a dataset directory, with `ragsplat_core.train`.

    The dataset (with its dry images) and the GT grid are loaded once for all variants.
    """

    def __init__(self, data: Path, device: str | None = None):
        from ragsplat_core.data import load_dataset

        self.ds = load_dataset(data)
        if not self.ds.test:
            raise UsageError(f"{data}/transforms.json: no frame has split 'test' (held-out views are needed)")
        if self.ds.eval_region is None:
            raise UsageError(f"{data}/scene.json: no eval_region (needed for the geometry table)")
        grid = data / "gt" / "bed_grid.npy"
        if not grid.is_file():
            raise UsageError(f"{grid}: ground-truth bed grid is missing")
        self.gt = np.load(grid)
        if self.gt.ndim != 2 or self.gt.shape[1] != 3 or len(self.gt) == 0:
            raise UsageError(f"{grid}: expected a non-empty float array [N, 3], got shape {self.gt.shape}")
        self.device = device

    def _gaussians(self, trainer) -> dict:
        from ragsplat_core.gaussians import activated

        scales, quats, opac = activated(trainer.splats)
        return {"means": trainer.splats["means"].detach(), "scales": scales.detach(), "quats": quats.detach(),
                "opacities": opac.detach()}

    def _render(self, trainer):
        return lambda view, interface: trainer.render(view.camera, interface=interface)[0]

    def __call__(self, variant: str, data: Path, out: Path, preset: str, seed: int, lpips_metric=None) -> dict:
        from ragsplat_core.train import Trainer, preset_config

        overrides = {"variant": variant, "seed": seed}
        if self.device is not None:
            overrides["device"] = self.device
        cfg = preset_config(preset, **overrides)
        out.mkdir(parents=True, exist_ok=True)
        try:
            trainer = Trainer(cfg, self.ds, out)  # resumes from out/ckpt.pt after a kill
        except ValueError as err:  # dataset/config/checkpoint problems, one line each
            raise UsageError(f"[{variant}] {err}") from None
        curve_file = out / "curve.json"
        curve = []
        if curve_file.is_file() and trainer.step > 0:  # points recorded before the kill, up to the checkpoint
            curve = [c for c in json.loads(curve_file.read_text()) if c["iteration"] <= trainer.step]
        curve_cfg = extract_config(preset, len(self.gt), seed, curve=True)
        eval_time = [0.0]

        def checkpoint(tr, step: int) -> None:
            t0 = time.perf_counter()
            app = evaluate_views(self._render(tr), self.ds.test)
            geo = evaluate_geometry(self._gaussians(tr), self.gt, self.ds.eval_region, curve_cfg)
            curve[:] = [c for c in curve if c["iteration"] != step]
            curve.append({"iteration": step, "time_s": tr.elapsed, "num_gaussians": tr.num_gaussians,
                          "psnr_refr": (app["refr"] or {}).get("psnr"), "psnr_dry": (app["dry"] or {}).get("psnr"),
                          "f1@0.1": geo["f1@0.1"], "chamfer": geo["chamfer"]})
            curve_file.write_text(json.dumps(_jsonable(curve), indent=1))
            eval_time[0] += time.perf_counter() - t0

        with tqdm(total=cfg.iterations, initial=trainer.step, desc=variant, unit="it", leave=False) as bar:
            def progress(tr) -> None:
                bar.update(1)
                bar.set_postfix(loss=f"{tr.last['loss']:.4f}", psnr=f"{tr.last['psnr']:.2f}", n=tr.num_gaussians,
                                refresh=False)

            sched = cfg.schedule
            steps = eval_steps(cfg.iterations, PRESETS[preset].checkpoints, sched.reset_every, sched.refine_stop_iter)
            stats = trainer.train(callbacks=[checkpoint], on_step=progress, eval_steps=steps)
        t0 = time.perf_counter()
        if lpips_metric is not None:
            lpips_metric.to(trainer.device)
        appearance = evaluate_views(self._render(trainer), self.ds.test, lpips_metric)
        t1 = time.perf_counter()
        geometry = evaluate_geometry(self._gaussians(trainer), self.gt, self.ds.eval_region,
                                     extract_config(preset, len(self.gt), seed))
        t2 = time.perf_counter()
        return {"config": cfg.to_dict(), "seed": seed, "train_stats": stats,
                "num_gaussians": stats["num_gaussians"], "train_time_s": stats["train_seconds"],
                "appearance": appearance, "geometry": geometry, "curve": sorted(curve, key=lambda c: c["iteration"]),
                "timings": {"train_s": stats["train_seconds"], "checkpoint_eval_s": eval_time[0],
                            "appearance_eval_s": t1 - t0, "geometry_eval_s": t2 - t1},
                "outputs": {"dir": str(out), "ply": str(out / "point_cloud.ply")}}


# ---------------------------------------------------------------- command line


def add_arguments(parser) -> None:
    parser.add_argument("--data", required=True, type=Path, help="dataset directory (transforms.json, gt/)")
    parser.add_argument("--out", required=True, type=Path, help="output directory (reused rows live here)")
    parser.add_argument("--preset", default="small", choices=list(PRESETS), help="training/eval size")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS, metavar="VARIANT",
                        help=f"subset of {', '.join(VARIANTS)} (default: all)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--vgg16", default=None,
                        help="torchvision's vgg16-397923af.pth for LPIPS (default: torch hub cache)")
    parser.add_argument("--device", default=None, help="torch device for training (default: the preset's)")


def run(args) -> int:
    if not (args.data / "transforms.json").is_file():
        raise UsageError(f"{args.data}: not a dataset directory (no transforms.json)")
    run_ablation(args.data, args.out, args.preset, args.variants, args.seed, TrainEval(args.data, args.device),
                 vgg16=args.vgg16)
    return 0
