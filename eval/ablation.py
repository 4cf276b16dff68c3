"""The ablation: train every variant, evaluate it, and regenerate the paper's Tables 1 and 2.

Per variant (a row): train with evaluation points (PSNR in both conditions and F1@10cm against training
wall-clock time), then evaluate on the held-out views (PSNR, SSIM, LPIPS; `refr` = rendered through the
interface vs the with-water images, `dry` = true Gaussians without it vs the dry images) and the geometry
(extraction + Chamfer / F1 against the dataset's ground-truth grid inside `eval_region`). Each finished
row is written to `OUT/<variant>/row.json` at once, so a rerun (after a kill) reuses it and trains only
what is missing. Then `eval.report` (re)writes `OUT/results.json`, `table1.md`, `table2.md` and
`error_vs_time.png` from all rows. The `ragsplat ablation` command is `eval.cli`.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from eval import metrics
from eval.evaluate import evaluate_geometry, evaluate_views, model_gaussians, model_renderer
from eval.geometry import ExtractConfig
from eval.report import jsonable, write_outputs
from ragsplat_core.dataset import layout
from ragsplat_core.errors import ConfigError, DatasetError, OutputError
from ragsplat_core.outputs import claim, versions, write_json
from ragsplat_core.train.config import VARIANTS


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


# ---------------------------------------------------------------- rows on disk (resume)


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
        raise OutputError(f"{path}: unreadable finished row ({err}); delete it to recompute") from None
    if row.get("key") != key:
        raise OutputError(f"{path} was made with {row.get('key')}, not {key}; use another --out or delete it")
    return row


def save_row(out: Path, variant: str, row: dict) -> None:
    # atomic: a kill never leaves a half-written row that looks finished
    write_json(row_path(out, variant), jsonable(row), indent=1)


def run_ablation(data: Path, out: Path, preset: str, variants: list[str], seed: int,
                 train_and_evaluate: Callable[..., dict], vgg16: str | None = None,
                 log: Callable[[str], None] = lambda line: None) -> dict[str, dict]:
    """Rows for `variants` (reused from `out` when finished there, else trained via `train_and_evaluate`),
    then all outputs. `train_and_evaluate(variant=, data=, out=, preset=, seed=, lpips_metric=)` returns a row.
    `log(line)` receives progress lines and, at the end, the tables.
    """
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise ConfigError(f"unknown variant {unknown[0]!r}; choose from {', '.join(VARIANTS)}")
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    key = {"data": str(data.resolve()), "fingerprint": layout.fingerprint(data), "preset": preset, "seed": seed}
    claim(out, "ablation", legacy=("results.json", "*/row.json", "*/ckpt.pt"))
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
              "harness_preset": asdict(PRESETS[preset]), "versions": versions("torch", "scipy"),
              "command": sys.argv,
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

    The dataset (with its dry images) and the ground truth are loaded once for all variants.
    `training_bar(total, desc, initial) -> (bar, on_step)` shows training progress (None: nothing shown).
    """

    def __init__(self, data: Path, device: str | None = None, training_bar: Callable | None = None):
        from ragsplat_core.dataset.load import load_dataset

        self.ds = load_dataset(data, ground_truth=True)
        if not self.ds.test:
            raise DatasetError(f"{data / layout.TRANSFORMS}: no frame has split 'test' "
                               "(held-out views are needed)")
        self.gt = self.ds.ground_truth.grid
        self.device = device
        self.training_bar = training_bar

    def __call__(self, variant: str, data: Path, out: Path, preset: str, seed: int, lpips_metric=None) -> dict:
        from ragsplat_core.train import Trainer, preset_config

        overrides = {"variant": variant, "seed": seed}
        if self.device is not None:
            overrides["device"] = self.device
        cfg = preset_config(preset, **overrides)
        out.mkdir(parents=True, exist_ok=True)
        trainer = Trainer(cfg, self.ds, out)  # resumes from out/ckpt.pt after a kill
        curve_file = out / "curve.json"
        curve = []
        if curve_file.is_file() and trainer.step > 0:  # points recorded before the kill, up to the checkpoint
            curve = [c for c in json.loads(curve_file.read_text()) if c["iteration"] <= trainer.step]
        curve_cfg = extract_config(preset, len(self.gt), seed, curve=True)
        eval_time = [0.0]

        def checkpoint(tr, step: int) -> None:
            t0 = time.perf_counter()
            app = evaluate_views(model_renderer(tr), self.ds.test)
            geo = evaluate_geometry(model_gaussians(tr), self.gt, self.ds.eval_region, curve_cfg)
            curve[:] = [c for c in curve if c["iteration"] != step]
            curve.append({"iteration": step, "time_s": tr.elapsed, "num_gaussians": tr.num_gaussians,
                          "psnr_refr": (app["refr"] or {}).get("psnr"), "psnr_dry": (app["dry"] or {}).get("psnr"),
                          "f1@0.1": geo["f1@0.1"], "chamfer": geo["chamfer"]})
            write_json(curve_file, jsonable(curve), indent=1)
            eval_time[0] += time.perf_counter() - t0

        sched = cfg.schedule
        steps = eval_steps(cfg.iterations, PRESETS[preset].checkpoints, sched.reset_every, sched.refine_stop_iter)
        bar, on_step = (None, None) if self.training_bar is None else \
            self.training_bar(cfg.iterations, variant, trainer.step)
        try:
            stats = trainer.train(callbacks=[checkpoint], on_step=on_step, eval_steps=steps)
        finally:
            if bar is not None:
                bar.close()
        t0 = time.perf_counter()
        if lpips_metric is not None:
            lpips_metric.to(trainer.device)
        appearance = evaluate_views(model_renderer(trainer), self.ds.test, lpips_metric)
        t1 = time.perf_counter()
        geometry = evaluate_geometry(model_gaussians(trainer), self.gt, self.ds.eval_region,
                                     extract_config(preset, len(self.gt), seed))
        t2 = time.perf_counter()
        return {"config": cfg.to_dict(), "seed": seed, "train_stats": stats,
                "num_gaussians": stats["num_gaussians"], "train_time_s": stats["train_seconds"],
                "appearance": appearance, "geometry": geometry, "curve": sorted(curve, key=lambda c: c["iteration"]),
                "timings": {"train_s": stats["train_seconds"], "checkpoint_eval_s": eval_time[0],
                            "appearance_eval_s": t1 - t0, "geometry_eval_s": t2 - t1},
                "outputs": {"dir": str(out), "ply": str(out / "point_cloud.ply")}}
