"""The turbidity sweep's report: one reach rendered at several turbidities (the field water's
coefficients scaled, `ragsplat generate --turbidity T`), each level's ablation run as `ragsplat ablation` runs
it (`ragsplat sweep` does both), then, from each level's results.json, the method's rows and the best
reference's against the water's Secchi-like depth (`datagen.conditions.secchi_depth`, green channel, the one
a Secchi disk is read in): sweep.json, sweep.md and sweep.png.

The best reference is chosen at each level, by its F1 at 3 % of depth, among the references that do not read
the ground truth (`references.USES_GROUND_TRUTH`), the untrained start left out: the field's best answer at
that turbidity, whichever it is."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ragsplat.datagen.conditions import CONTRAST_SHARE, secchi_depth
from ragsplat.errors import OutputError
from ragsplat.eval.references import NOT_IN_TABLES, REFERENCES, USES_GROUND_TRUTH
from ragsplat.eval.report import summary_text
from ragsplat.outputs import write_bytes, write_json

LEVELS = (0.0, 0.5, 1.0, 2.0, 4.0)  # the sweep's turbidities (1: the `small-field` water)
GREEN = 1
# (results.json's summary column, the sweep's key)
COLUMNS = (("F1@1% (%)", "f1_1"), ("F1@3% (%)", "f1_3"), ("p95 (cm)", "p95_cm"), ("wet cover (%)", "cover"))
CANDIDATES = tuple(r for r in REFERENCES if r not in USES_GROUND_TRUTH and r not in NOT_IN_TABLES)


def level_name(turbidity: float) -> str:  # each level's folder under the sweep's data and out
    return f"turbidity-{turbidity:g}"


def _figures(summary: dict) -> dict:  # a row's summary columns -> {key: {"mean", "std", "n"}}
    return {key: summary.get(col) for col, key in COLUMNS}


def level_row(turbidity: float, results: dict, methods: list[str]) -> dict:
    """One level of the sweep from its ablation's results.json: the water's extinction and Secchi-like depth
    (per channel; None: clear), the methods' figures and the best reference's (name and figures)."""
    conditions = results.get("conditions") or {}
    extinction = conditions.get("extinction_per_m", [0.0, 0.0, 0.0])
    secchi = secchi_depth(extinction, conditions.get("sun_elevation_deg", 90.0))
    summary = results["summary"]
    missing = [m for m in methods if m not in summary]
    if missing:
        raise OutputError(f"turbidity {turbidity:g}: no row of {', '.join(missing)} in its results.json")
    scored = [(summary[r]["F1@3% (%)"]["mean"], r) for r in CANDIDATES
              if r in summary and (summary[r].get("F1@3% (%)") or {}).get("mean") is not None]
    best = max(scored)[1] if scored else None
    return {"turbidity": turbidity, "extinction_per_m": extinction,
            "secchi_like_depth_m": [float(v) if math.isfinite(v) else None for v in secchi],
            "dataset_fingerprint": results.get("dataset_fingerprint"), "seeds": results.get("seeds"),
            "methods": {m: _figures(summary[m]) for m in methods},
            "best_reference": best, "reference": None if best is None else _figures(summary[best])}


def _cell(figure: dict | None) -> str:
    return summary_text(figure, "{:.1f}")


def _depth(row: dict) -> str:
    v = row["secchi_like_depth_m"][GREEN]
    return "clear" if v is None else f"{v:.2f}"


def table(rows: list[dict]) -> str:
    """The sweep as a markdown table: per level the methods' F1 at 1 % / 3 % of depth, wet p95 and cover
    (mean ± std over the training seeds), then the best reference's, then the lead at 3 %."""
    methods = list(rows[0]["methods"])
    head = ["turbidity", "Secchi-like depth (m)"]
    for name in [*methods, "best reference"]:
        head += [f"{name}: F1@1% / F1@3%", "p95 (cm)", "wet cover (%)"]
    head += [f"{methods[0]} lead at 3 %"]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for row in rows:
        cells = [f"{row['turbidity']:g}", _depth(row)]
        for fig in [*row["methods"].values(), row["reference"]]:
            fig = fig or {}
            cells += [f"{_cell(fig.get('f1_1'))} / {_cell(fig.get('f1_3'))}", _cell(fig.get("p95_cm")),
                      _cell(fig.get("cover"))]
        ours = (next(iter(row["methods"].values())).get("f1_3") or {}).get("mean")
        theirs = ((row["reference"] or {}).get("f1_3") or {}).get("mean")
        cells.append("n/a" if ours is None or theirs is None else f"{ours - theirs:+.1f}")
        lines.append("| " + " | ".join(cells) + " |")
    names = sorted({r["best_reference"] for r in rows if r["best_reference"]})
    lines += ["", (f"Secchi-like depth: where the bed's contrast seen from above falls to "
                   f"{100 * CONTRAST_SHARE:g} % (green channel; the sun's path down and the view's up, "
                   "scattered light left out). Best reference at each level by F1@3% among "
                   f"{', '.join(CANDIDATES)}: {', '.join(names) or 'none'}.")]
    return "\n".join(lines) + "\n"


def figure(rows: list[dict], path: Path) -> Path:
    """F1 at 1 % and 3 % of depth against the Secchi-like depth (log axis; clear water drawn at the right
    edge), the methods and the best reference, bars the training seeds' standard deviation."""
    from ragsplat.pages import pyplot

    plt = pyplot()

    finite = [r["secchi_like_depth_m"][GREEN] for r in rows if r["secchi_like_depth_m"][GREEN] is not None]
    clear = 2 * max(finite) if finite else 1.0
    x = [clear if r["secchi_like_depth_m"][GREEN] is None else r["secchi_like_depth_m"][GREEN] for r in rows]
    order = np.argsort(x)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), constrained_layout=True)
    series = {m: [r["methods"][m] for r in rows] for m in rows[0]["methods"]}
    series["best reference"] = [r["reference"] or {} for r in rows]
    for ax, (key, label) in zip(axes, (("f1_1", "F1 @ 1 % of depth (%)"), ("f1_3", "F1 @ 3 % of depth (%)"))):
        for name, figs in series.items():
            y = [(f.get(key) or {}).get("mean") for f in figs]
            e = [(f.get(key) or {}).get("std") or 0.0 for f in figs]
            keep = [i for i in order if y[i] is not None]
            ax.errorbar([x[i] for i in keep], [y[i] for i in keep], yerr=[e[i] for i in keep], marker="o",
                        capsize=3, label=name, linestyle="--" if name == "best reference" else "-")
        ax.set_xscale("log")
        ax.set_xticks(x, ["clear" if r["secchi_like_depth_m"][GREEN] is None else f"{v:.2g}"
                          for r, v in zip(rows, x)])
        ax.minorticks_off()
        ax.set_xlabel("Secchi-like depth (m, green)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def report(out: Path, levels: list[float], methods: list[str]) -> str:
    """sweep.json, sweep.md and sweep.png in `out` from each level's OUT/turbidity-T/results.json; returns
    the table. Raises OutputError for a level without its results."""
    rows = []
    for t in levels:
        path = out / level_name(t) / "results.json"
        if not path.is_file():
            raise OutputError(f"{path}: no results for turbidity {t:g} (run its ablation first)")
        rows.append(level_row(t, json.loads(path.read_text()), methods))
    text = table(rows)
    write_json(out / "sweep.json", {"levels": rows, "methods": methods, "candidates": list(CANDIDATES),
                                    "contrast_share": CONTRAST_SHARE})
    write_bytes(out / "sweep.md", text.encode())
    figure(rows, out / "sweep.png")
    return text
