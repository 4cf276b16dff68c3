"""`ragsplat sweep --data DIR --out DIR [--turbidity T ...] [--preset small-field] [--seed S] [--variants ...]
[--seeds S ...] [--jobs N | --scheduler ADDRESS]`: the turbidity sweep. Each level is the dataset of
`ragsplat generate --preset PRESET --seed S --turbidity T --out DIR/turbidity-T` less its lens photos
(rendered once, resumable; the dry and depth images, which never see the water, rendered at the first level
only and linked into the others) and `ragsplat ablation --data DIR/turbidity-T --out OUT/turbidity-T` (its
rows and every reference, resumable), then
`ragsplat.eval.sweep.report` writes OUT/sweep.json, sweep.md and sweep.png: the method (the first of
--variants) and the best reference at each level, against the water's Secchi-like depth.
"""

from __future__ import annotations

import argparse

from ragsplat.cli.args import count, non_negative_float, out_dir, positive_int


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ragsplat.eval.ablation import SEEDS
    from ragsplat.eval.sweep import LEVELS
    from ragsplat.train.config import VARIANTS
    from ragsplat.train.defaults import survey_variant

    method = survey_variant("small-field")
    parser.add_argument("--data", required=True, type=out_dir,
                        help="where each level's dataset is rendered (DIR/turbidity-T)")
    parser.add_argument("--out", required=True, type=out_dir,
                        help="where each level's ablation and the sweep's report go")
    parser.add_argument("--turbidity", type=non_negative_float, nargs="+", default=list(LEVELS), metavar="T",
                        help="the levels: the field water's absorption and scattering times T (default: "
                             f"{' '.join(f'{t:g}' for t in LEVELS)})")
    parser.add_argument("--preset", default="small-field", choices=["small-field", "smoke-field"],
                        help="the reach and its training preset (default small-field; smoke-field: CI size)")
    parser.add_argument("--seed", type=count, default=0,
                        help="the dataset seed, the same at every level (default 0, the evaluation seed)")
    parser.add_argument("--variants", nargs="+", default=[method, "2dgs+full"], choices=list(VARIANTS),
                        metavar="VARIANT",
                        help=f"the trained rows, the method first (default: {method} 2dgs+full)")
    parser.add_argument("--seeds", type=count, nargs="+", default=list(SEEDS), metavar="SEED",
                        help=f"training seeds (default: {' '.join(map(str, SEEDS))})")
    parser.add_argument("--jobs", type=positive_int, metavar="N", help="`ragsplat ablation --jobs`")
    parser.add_argument("--scheduler", metavar="ADDRESS", help="`ragsplat ablation --scheduler`")
    parser.add_argument("--no-download", action="store_true", help="`ragsplat ablation --no-download`")


def level_spec(name: str, seed: int, turbidity: float):
    """A level's scene: the preset's reach with the water's turbidity set, and no lens photos (the sweep
    ablates; it does not survey)."""
    from dataclasses import replace

    from ragsplat.datagen.spec import preset, with_conditions

    spec = with_conditions(preset(name, seed=seed), turbidity=turbidity)
    return replace(spec, render=replace(spec.render, lens=False))


def run(args: argparse.Namespace) -> int:
    from ragsplat.cli.generate import render_progress
    from ragsplat.cli.main import command
    from ragsplat.datagen.build import generate
    from ragsplat.eval.sweep import level_name, report

    train_preset = {"small-field": "small-field", "smoke-field": "smoke"}[args.preset]
    first = None  # the first level rendered: its dry and depth images serve every level
    for t in args.turbidity:
        data, out = args.data / level_name(t), args.out / level_name(t)
        progress, bars = render_progress(f"turbidity {t:g}")
        try:
            done = generate(level_spec(args.preset, args.seed, t), data, progress=progress, share=first)
        finally:
            for b in bars:
                b.close()
        print(f"turbidity {t:g}: {data} ({done['rendered']} images rendered in {done['wall_s']:.0f} s, "
              f"{done['skipped']} present), {out}", flush=True)
        first = first or data
        module, sub = command("ablation", [
            "--data", str(data), "--out", str(out), "--preset", train_preset, "--variants", *args.variants,
            "--seeds", *map(str, args.seeds), *(["--jobs", str(args.jobs)] if args.jobs else []),
            *(["--scheduler", args.scheduler] if args.scheduler else []),
            *(["--no-download"] if args.no_download else [])])
        status = module.run(sub)
        if status:
            return status
    print(report(args.out, args.turbidity, args.variants))
    return 0
