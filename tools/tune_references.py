"""The references' own settings chosen on the development reach by the rule the method's were chosen by
(the rule of ragsplat_core/tuning/small.json: the best F1 at 1 % of depth among the settings within 0.5
point of the best F1 at 3 %), so that the field's practice gets the care the method got:

1. the outlier filter of the tracks before their TIN (`tracks.track_filter`: radius, tolerance; or none),
   chosen on `triangulation (refracted)`, the best reference, and then used for every tracks' reference;
2. Dietrich's per-camera angle filter and reduction (pyBathySfM's 35 degrees and mean the starting point),
   chosen on `dietrich (tracks)` with the filter of 1;
3. with `--bed BED.npy` (the development reach's `3dgs` row's volume bed, `ragsplat ablation --data
   data/small-dev --variants 3dgs --seeds 0`), the same two on `dietrich (3dgs)`, the rule on a dense cloud.

`python -m tools.tune_references DATA [OUT.json] [--bed BED.npy]`: DATA is the development reach
(`data/small-dev`, dataset seed 1); prints one Markdown table per step with the chosen row marked, and writes
every figure as JSON. The chosen values go into `ragsplat.eval.references` (`TIN_FILTER`, `DIETRICH_TRACKS`,
`DIETRICH_MAX_ANGLE`, `DIETRICH_DENSE_REDUCE`) by hand, with the tables in docs/lab/history.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from ragsplat.eval.evaluate import score_grid
from ragsplat.eval.references import dietrich_grid, gridded, track_clouds
from ragsplat.tracks import TRACK_MIN_NEIGHBOURS

TIN_FILTERS = [None] + [{"radius": r, "tol": t, "min_neighbours": TRACK_MIN_NEIGHBOURS}
                        for r in (0.5, 1.0, 2.0) for t in (0.05, 0.1, 0.2, 0.3, 0.5)]
DIETRICH_SETTINGS = [{"max_angle_deg": a, "reduce": r}
                     for a in (None, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0, 50.0)
                     for r in ("mean", "median")]
MARGIN_3PCT = 0.005  # the rule's 0.5 point


def figures(grid, truth) -> dict:
    """The rule's two figures and the surveyor's, as fractions and metres."""
    s = score_grid(grid, truth)
    wet = s["survey"]["wet"]
    return {"f1_1pct": s["f1"]["1%"], "f1_3pct": s["f1"]["3%"], "cover": s["survey"]["coverage"],
            "bias": wet["bias"], "p95": wet["p95"]}


def choose(rows: list[dict]) -> int:
    """The index of the rule's choice among rows with "f1_1pct" and "f1_3pct"."""
    best3 = max(r["f1_3pct"] for r in rows)
    near = [k for k, r in enumerate(rows) if r["f1_3pct"] >= best3 - MARGIN_3PCT]
    return max(near, key=lambda k: rows[k]["f1_1pct"])


def table(rows: list[dict], chosen: int, label) -> str:
    lines = ["| setting | F1@1% (%) | F1@3% (%) | wet cover (%) | bias (cm) | p95 (cm) | |", "|---" * 7 + "|"]
    for k, r in enumerate(rows):
        p95 = "n/a" if r["p95"] is None else f"{100 * r['p95']:.1f}"
        lines.append(f"| {label(r['setting'])} | {100 * r['f1_1pct']:.1f} | {100 * r['f1_3pct']:.1f} | "
                     f"{100 * r['cover']:.1f} | {100 * r['bias']:+.1f} | {p95} | "
                     f"{'chosen' if k == chosen else ''} |")
    return "\n".join(lines)


def tune(data: Path, bed: Path | None = None) -> dict:
    """The steps on the dataset `data`: {"tin_filter": {...}, "dietrich": {...}, "dietrich_dense": {...} with
    `bed`} with every setting's figures and the choice."""
    from ragsplat.eval.ablation import TrainEval

    runner = TrainEval(data)
    ds, truth = runner.ds, runner.truth
    cameras = {v.file_path: v.camera for v in ds.train}
    refracted = track_clouds(ds.root, ds.fingerprint, cameras, ds.water)["triangulation (refracted)"]
    tin_rows = [{"setting": f, **figures(gridded(refracted, truth.nodes, f), truth)} for f in TIN_FILTERS]
    tin_choice = choose(tin_rows)
    chosen_filter = tin_rows[tin_choice]["setting"]
    die_rows = []
    for setting in DIETRICH_SETTINGS:
        cloud = track_clouds(ds.root, ds.fingerprint, cameras, ds.water, setting)["dietrich (tracks)"]
        die_rows.append({"setting": setting, **figures(gridded(cloud, truth.nodes, chosen_filter), truth)})
    out = {"data": str(Path(data).resolve()), "dataset_seed": runner.dataset_seed,
           "fingerprint": ds.fingerprint,
           "rule": "max F1@1% among settings within 0.5 point of the best F1@3%",
           "tin_filter": {"rows": tin_rows, "chosen": chosen_filter},
           "dietrich": {"rows": die_rows, "chosen": die_rows[choose(die_rows)]["setting"]}}
    if bed is not None:
        apparent = np.load(bed)
        views = [v.camera for v in ds.train]
        dense = [{"setting": d, **figures(dietrich_grid(apparent, views, ds.water, d["max_angle_deg"],
                                                        d["reduce"]),
                                          truth)} for d in DIETRICH_SETTINGS]
        out["dietrich_dense"] = {"bed": str(bed), "rows": dense, "chosen": dense[choose(dense)]["setting"]}
    return out


def main(argv: list[str]) -> int:
    bed = None
    if "--bed" in argv[:-1]:
        k = argv.index("--bed")
        bed, argv = Path(argv[k + 1]), argv[:k] + argv[k + 2:]
    if len(argv) not in (1, 2):
        print("usage: python -m tools.tune_references DATA [OUT.json] [--bed BED.npy]", file=sys.stderr)
        return 2
    from ragsplat.outputs import jsonable, write_json

    result = tune(Path(argv[0]), bed)
    tin_rows, die_rows = result["tin_filter"]["rows"], result["dietrich"]["rows"]
    print(f"dataset seed {result['dataset_seed']}: the tracks' outlier filter, on triangulation (refracted)")
    print(table(tin_rows, choose(tin_rows), lambda f: "none" if f is None else
                f"radius {f['radius']:g} m, tol {f['tol']:g} m"))
    print(f"\nDietrich's rule on the tracks, with that filter ({result['tin_filter']['chosen']})")
    def angle(d):
        return (f"{d['reduce']}, "
                + ("every camera" if d["max_angle_deg"] is None else f"<= {d['max_angle_deg']:g} deg"))

    print(table(die_rows, choose(die_rows), angle))
    if "dietrich_dense" in result:
        dense = result["dietrich_dense"]["rows"]
        print(f"\nDietrich's rule on the dense 3dgs bed {bed}")
        print(table(dense, choose(dense), angle))
    if len(argv) == 2:
        write_json(Path(argv[1]), jsonable(result), indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
