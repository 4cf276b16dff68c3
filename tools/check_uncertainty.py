"""How well a fitted TVU95 model covers the true errors of held-out runs (docs/uncertainty.md).

    python -m tools.check_uncertainty MODEL.json RUN [RUN ...] [--truth RUN=DATA ...] [--out REPORT.json]
        [--figure RELIABILITY.png] [--bed evaluation|export]

Each RUN is a finished training run, as for `python -m tools.fit_uncertainty`; its wet cells are those of the
bed the model was fitted on (`ragsplat.eval.tvu_cells`; --bed: another) with the model's TVU95. Every figure
of `ragsplat.eval.calibration.calibration_report` over the runs pooled: a dataset seed is the unit of the
spread (several training runs on one reach count as one seed), the oracle smooths each run's bed on its own.
Refused: a run on a dataset seed the model was fitted or calibrated on. Held-out reaches (0, 7) are what this
is for. Prints one line per run and the pooled figures; --out writes them with the model and runs, --figure
the reliability diagram.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from ragsplat.errors import ConfigError, RagsplatError
from ragsplat.eval.tvu_cells import BEDS, truth_map


def check(model, sources, log=lambda line: None, bed: str | None = None) -> tuple[dict, tuple]:
    """(the report: the pooled `calibration_report`, per run's coverage and median; the arrays TVU95, errors,
    dataset seeds for the figure) of `model` on the runs `sources` (`tvu_cells.RunSource`), on the bed `bed`
    (None: the one the model was fitted on). Raises ConfigError for a run on a seed the model saw."""
    from ragsplat.eval.calibration import calibration_report, coverage
    from ragsplat.eval.tvu_cells import check_held_out, pooled, run_cells
    from ragsplat.uncertainty import Z95, tvu95

    for s in sources:
        try:
            check_held_out(model, s.truth_seed)
        except ConfigError as err:
            raise ConfigError(f"{s.run}: {err}") from None
    bed = bed or model.stats.get("bed", "evaluation")
    cells = [run_cells(s, bed=bed) for s in sources]
    if len({c.cell for c in cells}) != 1:
        raise ConfigError(f"the runs' beds are on different grids ({sorted({c.cell for c in cells})} m)")
    per_run, each = {}, []
    for c in cells:
        t = tvu95(model, c.features)
        each.append(t)
        row = {"dataset_seed": c.source.truth_seed, "training_seed": c.source.seed, "cells": len(c.errors),
               "coverage_95": coverage(t / Z95, c.errors), "median_tvu95": float(np.median(t))}
        per_run[str(c.source.run)] = row
        log(f"{c.source.run} (dataset seed {c.source.truth_seed}, training seed {c.source.seed}): "
            f"{len(c.errors)} wet cells, 95 % coverage {100 * row['coverage_95']:.1f} %, median TVU95 "
            f"{100 * row['median_tvu95']:.2f} cm")
    features, errors, seeds = pooled(cells)
    t = np.concatenate(each)  # pooled in the same order
    beds = np.concatenate([np.full(len(c.errors), k) for k, c in enumerate(cells)])
    report = calibration_report(t, errors, seeds, np.concatenate([c.depth for c in cells]), features.views,
                                np.concatenate([c.xy for c in cells]), cells[0].cell, beds=beds)
    return {**report, "bed": bed, "runs": per_run}, (t, errors, seeds)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.check_uncertainty",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("model", type=Path, metavar="MODEL.json|small|small-field",
                    help="a fitted model (tools.fit_uncertainty), or a shipped one ('small', 'small-field')")
    ap.add_argument("runs", type=Path, nargs="+", metavar="RUN", help="finished runs on held-out seeds")
    ap.add_argument("--truth", action="append", default=[], metavar="RUN=DATA",
                    help="score RUN against DATA's ground truth (default: the dataset RUN trained on)")
    ap.add_argument("--out", type=Path, metavar="REPORT.json", help="write the figures as JSON")
    ap.add_argument("--figure", type=Path, metavar="PNG", help="write the reliability diagram")
    ap.add_argument("--bed", choices=BEDS, default=None,
                    help="the cells: the evaluation's bed or the DEM `ragsplat export` writes (default: the "
                         "bed the model was fitted on)")
    args = ap.parse_args(argv)
    from ragsplat.eval.calibration import reliability_figure
    from ragsplat.eval.tvu_cells import run_source
    from ragsplat.export import read_uncertainty
    from ragsplat.outputs import write_bytes

    try:
        truths = truth_map(args.truth)
        model = read_uncertainty(args.model)
        report, (t, errors, seeds) = check(model, [run_source(r, truths.get(r.resolve())) for r in args.runs],
                                           log=print, bed=args.bed)
    except RagsplatError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    cov, spread = report["coverage"], report["coverage_seed_spread"]["0.95"]
    print(f"pooled ({report['bed']} bed), {report['cells']} wet cells of {spread['seeds']} dataset seed(s): "
          "coverage 50/80/95 % "
          f"{100 * cov['0.5']:.1f} / {100 * cov['0.8']:.1f} / {100 * cov['0.95']:.1f} % (95 % per seed "
          f"{100 * spread['min']:.1f}-{100 * spread['max']:.1f}); worst depth third "
          f"{100 * report['worst_depth_third']['worst']:.1f} %, worst view-count bin "
          f"{100 * report['worst_view_bin']['worst']:.1f} %; ENCE {report['ence']:.3f}; z-score variance "
          f"{report['z_variance']:.3f}; Spearman {report['spearman']:.3f}")
    r = report
    print(f"sharpness: median TVU95 {100 * r['median_tvu95']:.2f} cm, {r['sharpness_vs_oracle']:.2f}x the "
          f"oracle's ({100 * r['oracle_median_tvu95']:.2f} cm), {r['sharpness_vs_constant']:.2f}x the "
          f"constant width at the same coverage ({100 * r['constant_width']:.2f} cm)")
    if args.out:
        write_bytes(args.out, (json.dumps({"model": str(args.model), "model_seeds": {
            "fit": list(model.fit_seeds), "calibration": list(model.calibration_seeds)}, **report},
            indent=1) + "\n").encode())
        print(f"wrote {args.out}")
    if args.figure:
        import matplotlib.pyplot as plt

        fig = reliability_figure(t, errors, seeds, title=f"TVU95 of {args.model.name} on dataset seed(s) "
                                                         f"{sorted({int(s) for s in seeds})}")
        args.figure.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(args.figure, dpi=110)
        plt.close(fig)
        print(f"wrote {args.figure}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
