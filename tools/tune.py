"""Choose a training hyperparameter on a development dataset (never the evaluation one):
`python -m tools.tune --data DEV_DIR --out DIR [--preset small]
[--param lr_means | densify.max_gaussians | ...] [--values ...] [--variants full] [--seed 0]
[--set PARAM=VALUE ...] [--true-ripples]` trains each variant at each value (a number, or a word for a
choice such as `--param surfel_depth --values ray centre`) (the `--set` parameters held fixed), scores the
bed like the ablation and prints F1 at 1 % / 3 % of depth, wet RMSE, p95 and cover and the training time
per value (and a trained attenuation over the scene's extinction), and the value with the best mean F1 at
3 % over the variants. `--true-ripples`: every training render through its photo's own rippled surface,
read from the scene (`Trainer.view_ripples`): a bound on what modelling the ripples could buy, not a method.
The choice is recorded by hand in ragsplat_core/tuning/small.json (or small_field.json: the values,
figures, command, commit and dataset seed), which every results.json repeats.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from ragsplat.errors import ConfigError
from ragsplat.eval.ablation import PRESETS, TrainEval, extract_config, scene_conditions
from ragsplat.eval.rows import save_row, start_row
from ragsplat.outputs import claim, versions, write_json
from ragsplat.train.settings import PARAMS, WORDS, parse, typed, with_value


def held(parser: argparse.ArgumentParser, items: list[str]) -> dict[str, str | float]:
    """`--set PARAM=VALUE ...` as {param: value} (`settings.parse`); a parser error for an unknown or empty
    one."""
    try:
        return parse(items)
    except ConfigError as e:
        parser.error(str(e))


def label(param: str, value: str | float) -> str:
    return str(value) if param in WORDS else f"{float(value):g}"


def cm(x: float | None) -> str:
    """x x 100 to one decimal (cm from m, % from a share); n/a where the bed gives none (p95 with more than
    5 % of the wet cells holes, every figure of an empty bed)."""
    return "n/a" if x is None else f"{100 * x:.1f}"


def true_ripples(data: Path):
    """`Trainer.view_ripples` of the surfaces the photos of the dataset `data` were rendered through (its
    scene.json's spec, `ragsplat.datagen.conditions`), without their fade over the bed's border (beyond the
    scored region). Raises ValueError for a dataset rendered without ripples, or not rendered here."""
    from ragsplat.datagen.conditions import ripple_gradient, ripple_phases, ripple_waves
    from ragsplat.datagen.spec import SceneSpec
    from ragsplat.dataset import layout

    scene = data / layout.SCENE
    if not scene.is_file():
        raise ValueError(f"{scene}: no such file (the spec of a dataset the generator rendered)")
    spec = SceneSpec.from_dict(json.loads(scene.read_text())["spec"])
    c = spec.conditions
    if c is None or not c.rippled:
        raise ValueError(f"{data}: rendered without ripples")
    k, amplitude = ripple_waves(c, spec.seed)

    def gradient(name: str, xy: torch.Tensor) -> torch.Tensor:  # [M, 2] at xy [M, 2], photo `name`'s phases
        g = ripple_gradient(xy.detach().cpu().double().numpy(), k, amplitude,
                            ripple_phases(c, spec.seed, int(name)))
        return torch.as_tensor(g, dtype=xy.dtype, device=xy.device)
    return gradient


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.tune", description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--preset", default="small")
    parser.add_argument("--param", default="lr_means", choices=PARAMS)
    parser.add_argument("--values", nargs="+", default=["1.6e-4", "5e-4", "1.6e-3", "5e-3"])
    parser.add_argument("--variants", nargs="+", default=["full"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", nargs="+", default=[], metavar="PARAM=VALUE",
                        help="other parameters held at these values in every run (e.g. iterations=3000)")
    parser.add_argument("--true-ripples", action="store_true",
                        help="train through each photo's true rippled surface (a bound, read from the scene)")
    args = parser.parse_args(argv)
    fixed = held(parser, args.set)
    values = [typed(args.param, v) for v in args.values]
    try:
        ripples = true_ripples(args.data) if args.true_ripples else None
    except ValueError as err:
        parser.error(str(err))
    runner = TrainEval(args.data)
    extinction = (scene_conditions(args.data) or {}).get("extinction_per_m")  # the water's, per channel
    claim(args.out, "tuning")
    results = []
    for value in values:
        for variant in args.variants:
            cfg = runner.config(variant, args.preset, args.seed)
            for name, value_held in fixed.items():
                cfg = with_value(cfg, name, value_held)
            cfg = with_value(cfg, args.param, value)
            folder = args.out / (f"{variant}-{args.param}-{label(args.param, value)}"
                                 + "-true-ripples" * (ripples is not None))
            done = folder / "row.json"
            if done.is_file():
                row = json.loads(done.read_text())
            else:
                start_row(folder, {"dataset": runner.fingerprint, "train": cfg.to_dict()})
                ecfg = extract_config(cfg, len(runner.truth.nodes), runner.gsd)
                row, grid, fused = runner.train(cfg, folder, ecfg, PRESETS[args.preset].fuse, checkpoints=1,
                                                view_ripples=ripples)
                row = save_row(folder, {**row, "name": variant, "seed": args.seed,
                                        "true_ripples": ripples is not None}, grid, runner.truth, fused)
            g = row["geometry"]
            c = (row.get("train_stats") or {}).get("attenuation")  # a variant that trains the attenuation
            ratio = None if c is None or not extinction else [a / e for a, e in zip(c, extinction)]
            results.append({"variant": variant, "value": value, "f1_1%": g["f1"]["1%"],
                            "f1_3%": g["f1"]["3%"],
                            "rmse_wet": g["survey"]["wet"]["rmse"], "p95_wet": g["survey"]["wet"]["p95"],
                            "cover_wet": g["survey"]["coverage"], "train_s": row["time"]["wall_s"],
                            "attenuation": c, "attenuation_over_scene": ratio})
            optics = "" if ratio is None else "  c/scene " + " ".join(f"{r:.2f}" for r in ratio)
            print(f"{variant} {args.param}={label(args.param, value)}: F1@1% {cm(g['f1']['1%'])}  "
                  f"F1@3% {cm(g['f1']['3%'])}  "
                  f"wet RMSE {cm(g['survey']['wet']['rmse'])} cm  p95 {cm(g['survey']['wet']['p95'])} cm  "
                  f"cover {cm(g['survey']['coverage'])} %  {row['time']['wall_s']:.0f} s{optics}", flush=True)
    score = {v: np.mean([r["f1_3%"] for r in results if r["value"] == v]) for v in values}
    best = max(score, key=score.get)
    write_json(args.out / "tune.json", {"data": str(args.data.resolve()), "dataset_seed": runner.dataset_seed,
                                        "param": args.param, "fixed": fixed, "results": results,
                                        "true_ripples": args.true_ripples,
                                        "chosen": best,
                                        "rule": "max mean F1@3% over the variants",
                                        "versions": versions("torch")})
    print(f"chosen {args.param} = {label(args.param, best)} (mean F1@3% {100 * score[best]:.1f} over "
          f"{', '.join(args.variants)}) on dataset seed {runner.dataset_seed}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
