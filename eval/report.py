"""The ablation's outputs: Tables 1 (appearance) and 2 (geometry) as Markdown with our values beside the
paper's published ones, the error-against-time plot, and results.json (`write_outputs`).

A variant's row is the dict the ablation runner stores per variant (see `eval/ablation.py`):
    {"appearance": {"refr": {"ssim", "psnr", "lpips"} | None, "dry": {...} | None},
     "num_gaussians": int, "train_time_s": float,
     "geometry": {"chamfer", "precision@0.1", "recall@0.1", "f1@0.1", ... "@0.3"} | None}
Geometry fractions are printed as percentages, like the paper. Our missing or non-finite values print as
`n/a`; a cell the paper leaves empty stays empty; a variant the paper does not have prints `-`.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ragsplat_core.outputs import atomic_path, write_bytes, write_json
from ragsplat_core.train.config import VARIANTS

PUBLISHED_FILE = Path(__file__).resolve().parent / "published_tables.json"

# (header, paper column in published_tables.json, how to read ours from a row, format)
T1_COLUMNS = [
    ("SSIM refr", "ssim_refr", ("appearance", "refr", "ssim"), "{:.3f}"),
    ("PSNR refr", "psnr_refr", ("appearance", "refr", "psnr"), "{:.2f}"),
    ("LPIPS refr", "lpips_refr", ("appearance", "refr", "lpips"), "{:.3f}"),
    ("SSIM dry", "ssim_dry", ("appearance", "dry", "ssim"), "{:.3f}"),
    ("PSNR dry", "psnr_dry", ("appearance", "dry", "psnr"), "{:.2f}"),
    ("LPIPS dry", "lpips_dry", ("appearance", "dry", "lpips"), "{:.3f}"),
    ("Gaussians (K)", "gaussians_k", ("num_gaussians",), "{:.1f}"),
    ("Time (min)", "time_min", ("train_time_s",), "{:.1f}"),
]
T2_COLUMNS = [
    ("CD (m)", "cd_m", ("geometry", "chamfer"), "{:.3f}"),
    ("P@10cm (%)", "precision_10cm", ("geometry", "precision@0.1"), "{:.2f}"),
    ("R@10cm (%)", "recall_10cm", ("geometry", "recall@0.1"), "{:.2f}"),
    ("F1@10cm (%)", "f1_10cm", ("geometry", "f1@0.1"), "{:.2f}"),
    ("P@30cm (%)", "precision_30cm", ("geometry", "precision@0.3"), "{:.2f}"),
    ("R@30cm (%)", "recall_30cm", ("geometry", "recall@0.3"), "{:.2f}"),
    ("F1@30cm (%)", "f1_30cm", ("geometry", "f1@0.3"), "{:.2f}"),
]
# ours -> the paper's unit
_UNIT = {"num_gaussians": 1e-3, "train_time_s": 1 / 60}
_PERCENT = {"precision", "recall", "f1"}


def load_published(path: Path = PUBLISHED_FILE) -> dict:
    return json.loads(Path(path).read_text())


def _ours(row: dict | None, keys: tuple[str, ...]) -> float | None:
    value = row
    for k in keys:
        if not isinstance(value, dict) or value.get(k) is None:
            return None
        value = value[k]
    value = float(value) * _UNIT.get(keys[-1], 1.0)
    if keys[-1].split("@")[0] in _PERCENT:
        value *= 100.0
    return value


def _paper(published: dict, table: str, variant: str, column: str):
    """The paper's value, None when the paper left the cell empty, or '-' when it has no such row."""
    t = published[table]
    if variant not in t["rows"]:
        return "-"
    return t["rows"][variant][t["columns"].index(column)]


def _fmt(value, fmt: str, missing: str = "n/a") -> str:
    if isinstance(value, str):
        return value
    if value is None or not math.isfinite(value):
        return missing
    return fmt.format(value)


def _table(rows: dict[str, dict], published: dict, table: str, columns) -> str:
    head = ["Variant"]
    for name, _, _, _ in columns:
        head += [name, "paper"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for variant in [v for v in VARIANTS if v in rows] + [v for v in rows if v not in VARIANTS]:
        cells = [variant]
        for _, pcol, keys, fmt in columns:
            cells += [_fmt(_ours(rows[variant], keys), fmt), _fmt(_paper(published, table, variant, pcol), fmt, "")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def table1(rows: dict[str, dict], published: dict, notes: list[str] = ()) -> str:
    """Appearance. `refr` = rendered through the interface vs the with-water test images, `dry` = the true
    Gaussians rendered without it vs the dry test images."""
    text = "### Table 1: appearance on held-out views (ours | paper)\n\n"
    text += _table(rows, published, "table1_appearance", T1_COLUMNS)
    return text + "".join(f"\n- {n}" for n in notes) + ("\n" if notes else "")


def table2(rows: dict[str, dict], published: dict, notes: list[str] = ()) -> str:
    """Geometry against the GT 5 cm grid inside the evaluation region."""
    text = "### Table 2: geometry vs ground-truth bed grid (ours | paper)\n\n"
    text += _table(rows, published, "table2_geometry", T2_COLUMNS)
    return text + "".join(f"\n- {n}" for n in notes) + ("\n" if notes else "")


PANELS = (("psnr_refr", "PSNR refr (dB)"), ("psnr_dry", "PSNR dry (dB)"), ("f1@0.1", "F1 @ 10 cm (%)"))


def error_vs_time(curves: dict[str, list[dict]], path: str | Path, title: str = "") -> Path:
    """PSNR (both conditions) and F1@10cm against training wall-clock time, one curve per variant, as a
    three-panel PNG at `path`. A curve is the list the ablation records at its evaluation points,
    [{"iteration", "time_s", "psnr_refr", "psnr_dry", "f1@0.1"}]; `time_s` is training time only
    (evaluation pauses the clock), so curves of different variants compare. Points with a None value are
    left out of that panel."""
    import matplotlib

    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2), constrained_layout=True)
    colors = {v: plt.cm.tab10(i % 10) for i, v in enumerate(curves)}  # one colour per variant in every panel
    legend = {}
    for ax, (key, label) in zip(axes, PANELS):
        for variant, curve in curves.items():
            pts = [(c["time_s"] / 60, c[key]) for c in curve if c.get(key) is not None]
            if not pts:
                continue
            x, y = zip(*pts)
            if key == "f1@0.1":
                y = [100 * v for v in y]
            legend[variant] = ax.plot(x, y, marker="o", ms=3, color=colors[variant], label=variant)[0]
        ax.set_xlabel("training wall-clock time (min)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    if legend:
        fig.legend(list(legend.values()), list(legend), loc="outside right center")
    if title:
        fig.suptitle(title)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return Path(path)


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
    write_bytes(out / "table1.md", t1.encode())
    write_bytes(out / "table2.md", t2.encode())
    curves = {v: r.get("curve", []) for v, r in ordered.items()}
    error_vs_time(curves, out / "error_vs_time.png", title=f"error vs training time ({header.get('preset', '')})")
    results = {**header, "lpips": {"available": not lpips_reason, "reason": lpips_reason or None},
               "published": published, "variants": ordered}
    write_json(out / "results.json", jsonable(results), indent=1)
    return t1 + "\n" + t2


def jsonable(x):
    """Non-finite floats -> None (strict JSON), numpy scalars -> Python numbers."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
