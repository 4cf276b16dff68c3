"""Fit the per-cell TVU95 model on development seeds, calibrate it on another (docs/uncertainty.md).

    python -m tools.fit_uncertainty --fit RUN [RUN ...] --calibrate RUN [RUN ...] --out MODEL.json
        [--truth RUN=DATA ...] [--features one geometry depth spread filled] [--bed evaluation|export]

Each RUN is a finished training run (`ragsplat train`, an ablation row's seed<S>/ folder) whose dataset has
its ground truth (as `ragsplat score RUN` scores it; `--truth RUN=DATA`: another dataset's, in the same frame,
as `ragsplat score --truth`). Its wet cells (`ragsplat.eval.tvu_cells`: the evaluation's bed, or with --bed
export the DEM `ragsplat export` writes, its features, its errors) are pooled: the --fit runs' fit the weights
(`uncertainty.fit`, Gaussian likelihood), the --calibrate runs' give the conformal scale
(`uncertainty.calibrate`) so that the 95 % interval covers 95 % of their cells. Refused: a run on the
evaluation (dataset seed 0) or untouched (7) reach, a dataset seed both fitted and calibrated on, a run in
both lists. The model JSON records the features, weights, scale, the dataset seeds of both steps, the runs,
the commit and the code digest; `ragsplat export` / `ragsplat survey --uncertainty MODEL.json` then write the
DEM's TVU95 band.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from ragsplat.errors import ConfigError, RagsplatError
from ragsplat.eval.tvu_cells import BEDS, truth_map
from ragsplat.uncertainty import FEATURES


def sources(fit_runs: list[Path], calibration_runs: list[Path], truths: dict[Path, Path]):
    """(the fit runs' `RunSource`s, the calibration runs'), every protocol check done before any work: no
    held-out reach (`tvu_cells.check_development`), no run in both lists, no dataset seed in both steps.
    Raises ConfigError, OutputError."""
    from ragsplat.eval.tvu_cells import check_development, run_source

    fit_runs, calibration_runs = [Path(r) for r in fit_runs], [Path(r) for r in calibration_runs]
    both = {r.resolve() for r in fit_runs} & {r.resolve() for r in calibration_runs}
    if both:
        raise ConfigError(f"{', '.join(sorted(map(str, both)))}: in both --fit and --calibrate; the "
                          "conformal step needs cells the fit did not see")
    unknown = set(truths) - {r.resolve() for r in fit_runs + calibration_runs}
    if unknown:
        raise ConfigError(f"--truth names {', '.join(sorted(map(str, unknown)))}, not among the runs")
    fit = [run_source(r, truths.get(r.resolve())) for r in fit_runs]
    cal = [run_source(r, truths.get(r.resolve())) for r in calibration_runs]
    for s in fit + cal:
        check_development(s)
    shared = {s.truth_seed for s in fit} & {s.truth_seed for s in cal} - {None}
    if shared:
        raise ConfigError(f"dataset seed(s) {sorted(shared)} both fitted and calibrated on: calibrate on "
                          "another development seed than the fit's (cells of one seed share its poses' and "
                          "water's errors)")
    return fit, cal


def _seeds(srcs) -> list:  # the dataset seeds of the runs, each once, in order (None: not recorded)
    return list(dict.fromkeys(s.truth_seed for s in srcs))


def fit_model(fit_sources, calibration_sources, names=FEATURES, log=lambda line: None,
              bed: str = "evaluation"):
    """The model fitted on `fit_sources`' wet cells of the bed `bed` (`tvu_cells.BEDS`) and calibrated on
    `calibration_sources`' (module docstring), with the bed, runs, code and each calibration run's coverage in
    its stats."""
    from ragsplat.eval.ablation import CODE
    from ragsplat.eval.calibration import coverage
    from ragsplat.eval.tvu_cells import pooled, run_cells
    from ragsplat.outputs import git_commit, source_digest
    from ragsplat.uncertainty import calibrate, fit, sigma

    def cells_of(srcs, what):
        out = []
        for s in srcs:
            c = run_cells(s, bed=bed)
            log(f"{what}: {s.run} (dataset seed {s.truth_seed}): {len(c.errors)} wet cells, |dz| median "
                f"{100 * np.median(np.abs(c.errors)):.2f} cm")
            out.append(c)
        return out

    fitted, calibrating = cells_of(fit_sources, "fit"), cells_of(calibration_sources, "calibrate")
    F, e, _ = pooled(fitted)
    model = fit(F, e, names, seeds=_seeds(fit_sources), commit=git_commit())
    Fc, ec, _ = pooled(calibrating)
    model = calibrate(model, Fc, ec, seeds=_seeds(calibration_sources))
    per_run = {str(c.source.run): coverage(sigma(model, c.features), c.errors) for c in calibrating}

    def record(s):
        return {"run": str(s.run), "data": str(s.data), "truth": str(s.truth), "preset": s.preset,
                "training_seed": s.seed, "dataset_seed": s.truth_seed}

    return replace(model, stats={**model.stats, "bed": bed, "fit_runs": [record(s) for s in fit_sources],
                                 "calibration_runs": [record(s) for s in calibration_sources],
                                 "calibration_coverage_per_run": per_run,
                                 "code_digest": source_digest(*CODE)})


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.fit_uncertainty", description=__doc__.splitlines()[0])
    ap.add_argument("--fit", type=Path, nargs="+", required=True, metavar="RUN",
                    help="finished runs on development seeds whose wet cells fit the weights")
    ap.add_argument("--calibrate", type=Path, nargs="+", required=True, metavar="RUN",
                    help="finished runs on another development seed whose wet cells give the conformal scale")
    ap.add_argument("--truth", action="append", default=[], metavar="RUN=DATA",
                    help="score RUN against DATA's ground truth (default: the dataset RUN trained on)")
    ap.add_argument("--features", nargs="+", default=list(FEATURES), metavar="NAME",
                    help=f"the model's features (default: {' '.join(FEATURES)})")
    ap.add_argument("--bed", choices=BEDS, default="evaluation",
                    help="the cells: the evaluation's bed (default) or the DEM `ragsplat export` writes")
    ap.add_argument("--out", type=Path, required=True, metavar="MODEL.json", help="the model to write")
    args = ap.parse_args(argv)
    from ragsplat.outputs import write_bytes

    try:
        fit_sources, calibration_sources = sources(args.fit, args.calibrate, truth_map(args.truth))
        model = fit_model(fit_sources, calibration_sources, tuple(args.features), log=print, bed=args.bed)
    except RagsplatError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    write_bytes(args.out, (model.to_json() + "\n").encode())
    weights = ", ".join(f"{n} {w:.4g}" for n, w in zip(model.features, model.weights))
    print(f"weights: {weights}; conformal scale {model.scale:.4g} (rank {model.stats['conformal_rank']} of "
          f"{model.stats['calibration_cells']} cells); fitted on dataset seeds {list(model.fit_seeds)}, "
          f"calibrated on {list(model.calibration_seeds)}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
