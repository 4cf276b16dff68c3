"""The ablation's outputs from its rows: Tables 1 (appearance), 2 (geometry, reference rows first) and 3 (the
surveyor's figures) as Markdown, our values as mean +- standard deviation over the training seeds beside the
paper's published ones, the error-against-time plot, per-row depth-error maps, results.json, and all of them
on one self-contained page, report.html (`ragsplat.pages`).

Rows come as {name: [row per seed]} (see `eval/ablation.py`); a trained row has "appearance", "time",
"num_gaussians", "geometry" (the volume extraction), "geometry_fused" (the fused one) and "curve", a
reference row only "geometry" (and its "extraction" label). Tables 2 and 3 print a row once per extraction
it has, labelled in their "bed" column. Geometry fractions print as percentages, like the paper. The
paper's geometry is compared only on the depth-scaled thresholds: its 10 / 30 cm are 1 % / 3 % of its 10 m
depth; our absolute 10 / 30 cm columns stand alone. Our missing values print as `n/a`; a cell the paper
leaves empty stays empty; a row the paper does not have prints `-`.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ragsplat.dataset.layout import GT_GRID_STEP
from ragsplat.outputs import atomic_path, jsonable, write_bytes, write_json
from ragsplat.scoring import IHO_ORDERS
from ragsplat.train.config import VARIANTS

PUBLISHED_FILE = Path(__file__).resolve().parent / "published_tables.json"
# (header, paper column in published_tables.json or None, how to read ours from a row, format, scale)
T1_COLUMNS = [
    ("SSIM refr", "ssim_refr", ("appearance", "refr", "ssim"), "{:.3f}", 1),
    ("PSNR refr", "psnr_refr", ("appearance", "refr", "psnr"), "{:.2f}", 1),
    ("LPIPS refr", "lpips_refr", ("appearance", "refr", "lpips"), "{:.3f}", 1),
    ("SSIM dry", "ssim_dry", ("appearance", "dry", "ssim"), "{:.3f}", 1),
    ("PSNR dry", "psnr_dry", ("appearance", "dry", "psnr"), "{:.2f}", 1),
    ("LPIPS dry", "lpips_dry", ("appearance", "dry", "lpips"), "{:.3f}", 1),
    ("Gaussians (K)", "gaussians_k", ("num_gaussians",), "{:.1f}", 1e-3),
    ("Time (min)", "time_min", ("time", "wall_s"), "{:.1f}", 1 / 60),
    ("CPU (min)", None, ("time", "cpu_s"), "{:.1f}", 1 / 60),
    ("s/it (median)", None, ("time", "median_step_s"), "{:.3f}", 1),
]
T2_COLUMNS = [
    ("CD (m)", None, ("geometry", "chamfer"), "{:.3f}", 1),
    ("F1@10cm (%)", None, ("geometry", "f1", "10cm"), "{:.1f}", 100),
    ("F1@30cm (%)", None, ("geometry", "f1", "30cm"), "{:.1f}", 100),
    ("P@1% (%)", "precision_10cm", ("geometry", "precision", "1%"), "{:.1f}", 100),
    ("R@1% (%)", "recall_10cm", ("geometry", "recall", "1%"), "{:.1f}", 100),
    ("F1@1% (%)", "f1_10cm", ("geometry", "f1", "1%"), "{:.1f}", 100),
    ("P@3% (%)", "precision_30cm", ("geometry", "precision", "3%"), "{:.1f}", 100),
    ("R@3% (%)", "recall_30cm", ("geometry", "recall", "3%"), "{:.1f}", 100),
    ("F1@3% (%)", "f1_30cm", ("geometry", "f1", "3%"), "{:.1f}", 100),
]
T3_COLUMNS = [
    ("wet cover (%)", None, ("geometry", "survey", "coverage"), "{:.1f}", 100),
    ("bias (cm)", None, ("geometry", "survey", "wet", "bias"), "{:+.1f}", 100),
    ("RMSE (cm)", None, ("geometry", "survey", "wet", "rmse"), "{:.1f}", 100),
    ("p95 (cm)", None, ("geometry", "survey", "wet", "p95"), "{:.1f}", 100),
    ("within 3 cm (%)", None, ("geometry", "survey", "wet", "within", "3cm"), "{:.1f}", 100),
    ("within 5 cm (%)", None, ("geometry", "survey", "wet", "within", "5cm"), "{:.1f}", 100),
    *[(f"IHO {order} (%)", None, ("geometry", "survey", "wet", "iho", order), "{:.1f}", 100)
      for order in reversed(IHO_ORDERS)],  # the strictest first
    ("RMSE shallow", None, ("geometry", "survey", "shallow", "rmse"), "{:.1f}", 100),
    ("RMSE middle", None, ("geometry", "survey", "middle", "rmse"), "{:.1f}", 100),
    ("RMSE deep", None, ("geometry", "survey", "deep", "rmse"), "{:.1f}", 100),
    ("banks bias (cm)", None, ("geometry", "survey", "banks", "bias"), "{:+.1f}", 100),
    ("banks RMSE (cm)", None, ("geometry", "survey", "banks", "rmse"), "{:.1f}", 100),
]
# with a fitted uncertainty model (`ragsplat ablation --uncertainty`): the rows' TVU95 band (`band_rows`)
T3_TVU_COLUMNS = [
    ("TVU95 covers (%)", None, ("geometry", "survey", "tvu", "coverage", "0.95"), "{:.1f}", 100),
    ("median TVU95 (cm)", None, ("geometry", "survey", "tvu", "median_tvu95"), "{:.2f}", 100),
    ("TVU95 / oracle", None, ("geometry", "survey", "tvu", "sharpness_vs_oracle"), "{:.2f}", 1),
    ("TVU95 / constant", None, ("geometry", "survey", "tvu", "sharpness_vs_constant"), "{:.2f}", 1),
    ("z variance", None, ("geometry", "survey", "tvu", "z_variance"), "{:.2f}", 1),
]
PAPER_NAMES = {"3dgs": "3dgs", "position": "position", "position+scale": "position+scale",
               "position+opacity": "position+opacity", "full": "full"}


def load_published(path: Path = PUBLISHED_FILE) -> dict:
    return json.loads(Path(path).read_text())


def values(rows: list[dict], keys: tuple[str | int, ...], scale: float = 1.0) -> list[float]:
    """The finite values at `keys` of each seed's row, times `scale` (an int key indexes a list)."""
    out = []
    for row in rows:
        value = row
        for k in keys:
            if isinstance(k, int):
                value = value[k] if isinstance(value, list) and k < len(value) else None
            else:
                value = value.get(k) if isinstance(value, dict) else None
        if isinstance(value, (int, float)) and math.isfinite(value):
            out.append(float(value) * scale)
    return out


def summary(vals: list[float]) -> dict | None:
    """mean, sample standard deviation (None for one value) and count."""
    if not vals:
        return None
    return {"mean": float(np.mean(vals)), "std": float(np.std(vals, ddof=1)) if len(vals) > 1 else None,
            "n": len(vals)}


def _cell(vals: list[float], fmt: str) -> str:
    return summary_text(summary(vals), fmt)


def summary_text(s: dict | None, fmt: str) -> str:
    """A `summary` as a table cell: "mean ± std" in `fmt` (the std unsigned), the mean alone for one value,
    n/a for none."""
    if s is None or s.get("mean") is None:
        return "n/a"
    text = fmt.format(s["mean"])
    return text if s.get("std") is None else f"{text} ± {fmt.format(s['std']).lstrip('+')}"


def _paper(published: dict, table: str, name: str, column: str, fmt: str) -> str:
    t = published[table]
    if name not in t["rows"]:
        return "-"
    value = t["rows"][name][t["columns"].index(column)]
    return "" if value is None else fmt.format(value)


def ordered(rows: dict[str, list[dict]]) -> list[str]:
    from ragsplat.eval.references import REFERENCES

    return [n for n in REFERENCES if n in rows] + [v for v in VARIANTS if v in rows] + \
        [n for n in rows if n not in REFERENCES and n not in VARIANTS]


def tabled(rows: dict[str, list[dict]]) -> list[str]:
    """The rows the tables show (`ordered`, less the references kept only in results.json)."""
    from ragsplat.eval.references import NOT_IN_TABLES

    return [n for n in ordered(rows) if n not in NOT_IN_TABLES]


def _label(name: str, rows: list[dict]) -> str:
    return f"{name} (uses GT)" if rows and rows[0].get("uses_ground_truth") else name


def extractions(rows: list[dict]) -> list[tuple[str, list[dict]]]:
    """(label, the seeds' rows with that extraction's scores under "geometry") per bed extraction a row has:
    its own ("volume" unless the row says otherwise), then "fused" when it has fused scores."""
    out = [(rows[0].get("extraction", "volume") if rows else "volume", rows)]
    if any("geometry_fused" in r for r in rows):
        out.append(("fused", [{**r, "geometry": r.get("geometry_fused")} for r in rows]))
    return out


def _table(rows: dict[str, list[dict]], published: dict, table: str | None, columns, names,
           by_extraction: bool = False) -> str:
    head = ["Row", "seeds"] + (["bed"] if by_extraction else [])
    for name, pcol, _, _, _ in columns:
        head += [name] + (["paper"] if pcol and table else [])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    entries = [(name, label, found) for name in names
               for label, found in (extractions(rows[name]) if by_extraction else [(None, rows[name])])]
    for name, label, found in entries:
        seeds = [r.get("seed") for r in found]
        cells = ([_label(name, found), "-" if seeds == [None] else str(len(seeds))]
                 + ([label] if label else []))
        for _, pcol, keys, fmt, scale in columns:
            cells.append(_cell(values(found, keys, scale), fmt))
            if pcol and table:
                cells.append(_paper(published, table, PAPER_NAMES.get(name, name), pcol, fmt))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def geometry_table(head: list[str], rows: list[tuple[list[str], dict]], columns) -> str:
    """A Markdown table of single beds (no seeds): per row its leading cells (under `head`) and its geometry
    scores (`score_grid`'s), in `columns` (entries of T2_COLUMNS / T3_COLUMNS); a missing value prints n/a."""
    lines = ["| " + " | ".join(head + [c[0] for c in columns]) + " |",
             "|" + "---|" * (len(head) + len(columns))]
    for lead, geometry in rows:
        cells = list(lead)
        for _, _, keys, fmt, scale in columns:
            found = values([{"geometry": geometry}], keys, scale)
            cells.append(fmt.format(found[0]) if found else "n/a")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _notes(notes) -> str:
    return "".join(f"\n- {n}" for n in notes) + ("\n" if notes else "")


def table1(rows: dict[str, list[dict]], published: dict, notes: list[str] = ()) -> str:
    """Appearance of the trained rows on held-out views. `refr` = rendered through the interface vs the
    with-water test images, `dry` = the true Gaussians rendered without it vs the dry test images."""
    names = [n for n in tabled(rows) if any("appearance" in r for r in rows[n])]
    text = "### Table 1: appearance on held-out views (ours, mean ± std over seeds | paper)\n\n"
    return text + _table(rows, published, "table1_appearance", T1_COLUMNS, names) + _notes(notes)


def table2(rows: dict[str, list[dict]], published: dict, notes: list[str] = ()) -> str:
    """Geometry against the ground-truth bed grid: reference rows first, then the variants."""
    text = ("### Table 2: geometry vs the ground-truth bed (ours, mean ± std over seeds | paper at "
            "1 % / 3 % of depth = its 10 / 30 cm)\n\n")
    return text + _table(rows, published, "table2_geometry", T2_COLUMNS, tabled(rows), True) + _notes(notes)


def table3(rows: dict[str, list[dict]], notes: list[str] = ()) -> str:
    """The surveyor's figures: dz = predicted - true bed height at each reconstructed cell's centre."""
    text = "### Table 3: vertical error of the bed, the surveyor's figures (cm, mean ± std over seeds)\n\n"
    return text + _table(rows, {}, None, t3_columns(rows), tabled(rows), True) + _notes(notes)


def t3_columns(rows: dict[str, list[dict]]) -> list:
    """Table 3's columns: the TVU95 band's too where a row has one."""
    banded = any(values(found, T3_TVU_COLUMNS[0][2]) for found in rows.values())
    return T3_COLUMNS + (T3_TVU_COLUMNS if banded else [])


def table4(rows: dict[str, list[dict]], conditions: dict | None) -> str:
    """The water's optics the rows trained, against the scene's: the attenuation c per linear RGB
    channel (1/m) and its ratio to the scene's extinction (absorption + scattering, scene.json's
    "conditions"), and the backscatter's veil B_inf and coefficient c_b. Empty when no row trained a term."""
    def trained(r: dict) -> bool:
        stats = r.get("train_stats") or {}
        return bool(stats.get("attenuation") or stats.get("backscatter"))

    names = [n for n in tabled(rows) if any(trained(r) for r in rows[n])]
    if not names:
        return ""
    scene = (conditions or {}).get("extinction_per_m")
    rgb = ("R", "G", "B")
    head = ["Row", "seeds", *[f"c {k} (1/m)" for k in rgb], *[f"c/scene {k}" for k in rgb],
            *[f"B_inf {k}" for k in rgb], *[f"c_b {k} (1/m)" for k in rgb]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name in names:
        found = rows[name]
        cells = [name, str(len(found))]
        cells += [_cell(values(found, ("train_stats", "attenuation", i)), "{:.3f}") for i in range(3)]
        cells += [_cell(values(found, ("train_stats", "attenuation", i), 1 / scene[i]), "{:.2f}")
                  if scene and scene[i] > 0 else "n/a" for i in range(3)]
        cells += [_cell(values(found, ("train_stats", "backscatter", "veil", i)), "{:.3f}") for i in range(3)]
        cells += [_cell(values(found, ("train_stats", "backscatter", "coefficients", i)), "{:.3f}")
                  for i in range(3)]
        lines.append("| " + " | ".join(cells) + " |")
    where = ("the scene's extinction (1/m, R G B): " + " / ".join(f"{c:.3f}" for c in scene) if scene
             else "the scene records no water body (scene.json has no conditions)")
    title = "### Table 4: the water's optics the rows trained, against the scene's (mean ± std over seeds)"
    return (title + "\n\n"
            + "\n".join(lines) + "\n" + _notes([where + "; c/scene 1.00 is the scene's value (the "
                                              "target: within 0.75-1.25 in every channel)."]))


PANELS = (("psnr_refr", "PSNR refr (dB)"), ("psnr_dry", "PSNR dry (dB)"), ("1%", "F1 @ 1 % of depth (%)"),
          ("3%", "F1 @ 3 % of depth (%)"))


def _curve_value(point: dict, key: str):
    return (point.get("f1") or {}).get(key) if key in ("1%", "3%") else point.get(key)


def error_vs_time(curves: dict[str, list[list[dict]]], path: str | Path, title: str = "",
                  lines: dict[str, dict] | None = None) -> Path:
    """PSNR (both conditions) and F1 at 1 % and 3 % of depth against training wall-clock time, one curve per
    variant (mean over seeds at each evaluation step, bars = standard deviation), as a four-panel PNG (the
    volume extraction: the fused bed is scored at the end only).
    `curves[variant]` is one list per seed of the points the ablation records ({"iteration", "time_s",
    "psnr_refr", "psnr_dry", "f1": {...}}); `time_s` is training time only (evaluation
    pauses the clock). `lines[name]` = {"1%": f1, "3%": f1} draws a reference row as a black horizontal line,
    dashed its own way."""
    from ragsplat.pages import pyplot

    plt = pyplot()

    fig, axes = plt.subplots(1, 4, figsize=(19, 4.2), constrained_layout=True)
    colors = {v: plt.cm.tab10(i % 10) for i, v in enumerate(curves)}
    # references in black, one dash pattern each: ten variants already use every tab10 colour
    dashes = {name: ("--", "-.", ":", (0, (5, 1, 1, 1, 1, 1)))[i % 4] for i, name in enumerate(lines or {})}
    legend = {}
    for ax, (key, label) in zip(axes, PANELS):
        scale = 100 if key in ("1%", "3%") else 1
        for variant, seeds in curves.items():
            steps = sorted({p["iteration"] for curve in seeds for p in curve})
            x, y, e = [], [], []
            for step in steps:
                pts = [p for curve in seeds for p in curve if p["iteration"] == step]
                vals = [scale * v for v in (_curve_value(p, key) for p in pts) if v is not None]
                if vals:
                    x.append(np.mean([p["time_s"] for p in pts]) / 60)
                    y.append(np.mean(vals))
                    e.append(np.std(vals, ddof=1) if len(vals) > 1 else 0.0)
            if x:
                legend[variant] = ax.errorbar(x, y, yerr=e, marker="o", ms=3, capsize=2,
                                              color=colors[variant], label=variant)[0]
        for name, ref in (lines or {}).items():
            if key in ref and ref[key] is not None:
                legend[name] = ax.axhline(scale * ref[key], ls=dashes[name], lw=1, color="k", label=name)
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


def depth_error_map(grid: np.ndarray, truth, path: str | Path, title: str = "") -> Path:
    """A map of dz = predicted - true bed height (cm) at each reconstructed cell (diverging colours,
    symmetric at 5 % of the maximum depth, saturating beyond), grey where nothing was reconstructed, the
    ground truth's wet cells outlined by their extent; with a colour bar."""
    from ragsplat.pages import pyplot

    plt = pyplot()

    from ragsplat.eval.evaluate import height_error

    dz, _ = height_error(grid, truth)
    step, nodes = GT_GRID_STEP, truth.nodes
    lo = nodes[:, :2].min(0)
    shape = np.round((nodes[:, :2].max(0) - lo) / step).astype(int) + 1
    img = np.full(shape[::-1], np.nan)
    known = np.zeros(shape[::-1], bool)
    ij = np.round((nodes[:, :2] - lo) / step).astype(int)
    known[ij[:, 1], ij[:, 0]] = True
    ij = np.round((grid[:, :2] - lo) / step).astype(int)
    inside = (ij >= 0).all(1) & (ij < shape).all(1)
    img[ij[inside, 1], ij[inside, 0]] = 100 * dz[inside]
    limit = 5.0 * truth.max_depth  # cm: 5 % of the maximum depth
    fig, ax = plt.subplots(figsize=(7, 5.5), constrained_layout=True)
    extent = (lo[0] - step / 2, lo[0] + (shape[0] - 0.5) * step, lo[1] - step / 2,
              lo[1] + (shape[1] - 0.5) * step)
    ax.imshow(np.where(known, 0.85, np.nan), origin="lower", extent=extent, cmap="gray", vmin=0, vmax=1)
    im = ax.imshow(img, origin="lower", extent=extent, cmap="RdBu_r", vmin=-limit, vmax=limit)
    wet = np.zeros(shape[::-1])
    g = np.round((truth.grid[:, :2] - lo) / step).astype(int)
    wet[g[:, 1], g[:, 0]] = 1
    ax.contour(np.arange(shape[0]) * step + lo[0], np.arange(shape[1]) * step + lo[1], wet, levels=[0.5],
               colors="k", linewidths=0.6)
    fig.colorbar(im, ax=ax, label="predicted - true bed height (cm); grey: not reconstructed", shrink=0.85)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal")
    ax.set_title(title + ("; " if title else "") + "black line: edge of the submerged ground truth")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    return Path(path)


def water_notes(header: dict) -> list[str]:
    """The water the rows were scored against when it slopes, and the one level they were given instead of
    it (`ragsplat ablation --one-level`), as the header records them ("water", "one_level")."""
    out, water, flat = [], header.get("water") or {}, header.get("one_level")
    if water.get("slope"):
        sx, sy = water["slope"]
        terms = "".join(f" {'-' if v < 0 else '+'} {abs(v):g} {axis}" for v, axis in ((sx, "x"), (sy, "y"))
                        if v)
        out.append(f"Water: a sloping surface, z = {water['level']:g}{terms} (a fall of "
                   f"{100 * math.hypot(sx, sy):.2g} %); every depth (the thresholds' maximum depth, the "
                   "bands, IHO) is the depth below it.")
    if flat:
        out.append("ONE LEVEL (--one-level): every variant and every reference was given one flat water "
                   f"level, {flat['level']:.3f} m (the mean of the {flat['edge_points']} surveyed edge "
                   f"points, {flat['edge_file']}), instead of the dataset's surface: what a flat-water tool "
                   "does. The scores are against the true surface and bed, as in every run.")
    return out


def notes(rows: dict[str, list[dict]], header: dict, lpips_reason: str) -> list[str]:
    out = water_notes(header)
    if lpips_reason:
        out.append(f"LPIPS n/a: {lpips_reason}")
    out.append("SSIM: the standard SSIM (Wang et al. 2004, Gaussian window 11, sigma 1.5, valid region: the "
               "value of scikit-image and torchmetrics); the 3DGS training SSIM is in results.json as "
               "ssim_3dgs.")
    if "3dgs" in rows:
        out.append("3dgs has no interface model: its `refr` values compare its plain render with the "
                   "with-water images (the paper leaves these cells empty).")
    out.append("Time: training wall clock (evaluation excluded), the process's CPU time and the median wall "
               "time of one iteration on this machine; the paper's is an RTX 3090 at 800 x 800, 30k "
               "iterations.")
    return out


def geometry_notes(header: dict) -> list[str]:
    depth, tuning = header.get("max_depth_m"), header.get("tuning") or {}
    thresholds = (f"Thresholds: absolute 10 / 30 cm, and 1 % / 3 % of the maximum depth ({depth:g} m: "
                  f"{10 * depth:g} / {30 * depth:g} mm); the paper's 10 / 30 cm are 1 % / 3 % of its 10 m, "
                  "so only the depth-scaled columns are compared with it.")
    out = [*water_notes(header), thresholds if depth else "Thresholds: absolute 10 / 30 cm.",
           ("CD in metres (mean of accuracy and completeness, unsquared); P/R/F1 in %, strict < threshold; "
            "mean ± sample standard deviation over the training seeds (the extraction seed is the training "
            "seed)."),
           references_note(header),
           bed_note(header)]
    if tuning:
        warn = " THIS IS THE DEVELOPMENT DATASET: these numbers are not an evaluation." \
            if header.get("dataset_seed") == tuning.get("dataset_seed") else ""
        out.append(f"Hyperparameters were chosen on dataset seed {tuning.get('dataset_seed')} (development); "
                  f"this dataset has seed {header.get('dataset_seed')}.{warn}")
    role = header.get("dataset_role")
    if role and role != "other":
        out.append(f"Protocol: dataset seeds {header.get('dataset_seeds')}; this is the {role} reach.")
    return out


def references_note(header: dict) -> str:
    """What the reference rows are, with their settings as the header records them."""
    refs = header.get("references") or {}
    tin, die = refs.get("tin_filter"), refs.get("dietrich_tracks") or {}
    cleaned = "not outlier-filtered" if tin is None else \
        (f"outlier-filtered (a point {tin['tol']:g} m from the median of its neighbours within "
         f"{tin['radius']:g} m dropped, given {tin['min_neighbours']})") if tin else "outlier-filtered"
    angle = die.get("max_angle_deg")
    cams = "every camera" if angle is None else f"the cameras within {angle:g} degrees of the vertical"
    dense = refs.get("dietrich_3dgs_max_angle_deg")
    return ("Reference rows, what a surveyor would do without ragsplat: triangulation (refracted) = the "
            "dataset's SIFT tracks intersected through the water; dietrich (tracks) = the straight-ray "
            f"tracks corrected by Dietrich's (2017) multi-camera rule ({die.get('reduce', 'median')} over "
            f"{cams}, each point below the water surface's height above it, pyBathySfM's per-point water "
            "surface elevation); triangulation x n = the straight-ray tracks with depths x n; each "
            f"{cleaned} and gridded by linear interpolation on its Delaunay triangulation (TIN), settings "
            "chosen on the development reach; dietrich (3dgs) = the rule applied to the 3dgs bed "
            f"({refs.get('dietrich_3dgs_reduce', 'median')} over the cameras that see a cell"
            + ("" if dense is None else f", within {dense:g} degrees of the vertical")
            + "). The trivial answers: 3dgs x n = the 3dgs bed with submerged depths "
            "multiplied by n (the classical correction); oracle plane = the least-squares tilted plane "
            "through the ground truth's submerged bed, oracle median plane = the flat plane at its median "
            "height (both read the ground truth). The untrained start (init) is in results.json only.")


def bed_note(header: dict) -> str:
    """What the "bed" column of Tables 2 and 3 means, with the fusion's settings when the header has them."""
    fuse = (header.get("harness_preset") or {}).get("fuse") or {}
    voxel = (f"{fuse['voxel']:g} m" if fuse.get("voxel")
            else f"{fuse['voxel_gsd']:g} x the views' ground sample "
            "distance") if fuse else "a few ground sample distances"
    trunc = f"{fuse['trunc_voxels']:g} voxels" if fuse else "a few voxels"
    return ("Bed: volume = volume sampling of the Gaussians, noise filter, median height per cell, "
            "despiking; fused = the "
            "true Gaussians' median depth maps of the training views (no water interface: straight rays) "
            f"fused in a TSDF (voxel {voxel}, truncation {trunc}), the topmost surface crossing per cell; "
            "for 3dgs both are its apparent bed. The reference rows have one bed each.")


def survey_notes(header: dict) -> list[str]:
    depth = header.get("max_depth_m") or 0
    out = [*water_notes(header),
           ("dz = predicted - true bed height at the centre of each reconstructed 5 cm cell (exact "
            f"surface); wet = true depth > 0; bands are thirds of the maximum depth ({depth:g} m); banks = "
            "emerged ground in the evaluation region; wet cover = wet cells reconstructed / wet "
            "ground-truth cells."),
           ("Holes count as misses: p95 (of |dz|), within 3 / 5 cm and the IHO columns are over every wet "
            "ground-truth cell, a cell the bed leaves empty counting as beyond every threshold (p95 n/a "
            "when more than 5 % are empty); bias and RMSE cannot count a hole and are over the covered "
            "cells, wet cover beside them. IHO: the share of wet cells within the IHO S-44 (2020) total "
            "vertical uncertainty at 95 %, sqrt(a^2 + (b d)^2) at the cell's true depth d: "
            + ", ".join(f"{k} ({a:g} m, {b:g})" for k, (a, b) in reversed(IHO_ORDERS.items()))
            + " (order 1: 1a and 1b).")]
    model = header.get("uncertainty")
    if model:
        from ragsplat.eval.calibration import ORACLE_BANDWIDTH

        out.append("TVU95 (docs/uncertainty.md): each trained row's band from the model fitted on dataset "
                   f"seeds {model['fit_seeds']} and calibrated on {model['calibration_seeds']}, over the "
                   "wet cells its volume bed covers (a hole has no error to cover); covers = the share with "
                   "|dz| <= TVU95 (target 95); / oracle: its median over that of the same conformal step on "
                   f"the row's own errors smoothed over {100 * ORACLE_BANDWIDTH:g} cm; / constant: over the "
                   "one width that covers as many cells; z variance of dz / (TVU95 / 1.96) (1 when "
                   "calibrated); per row in tvu95.tif.")
    return out


def write_outputs(out: Path, rows: dict[str, list[dict]], header: dict, lpips_reason: str) -> str:
    """results.json, table1.md, table2.md, table3.md (table4.md when a row trained the water's optics),
    error_vs_time.png and report.html from the rows; returns the tables."""
    published = load_published()
    t1 = table1(rows, published, notes(rows, header, lpips_reason))
    t2 = table2(rows, published, geometry_notes(header))
    t3 = table3(rows, survey_notes(header))
    t4 = table4(rows, header.get("conditions"))
    for name, text in (("table1.md", t1), ("table2.md", t2), ("table3.md", t3), ("table4.md", t4)):
        if text:
            write_bytes(out / name, text.encode())
    curves = {v: [r["curve"] for r in rows[v]] for v in ordered(rows) if v in VARIANTS}
    # the field's best, the trivial
    lines = {n: {k: (summary(values(rows[n], ("geometry", "f1", k))) or {}).get("mean") for k in ("1%", "3%")}
             for n in ("triangulation (refracted)", "oracle plane", "3dgs x n") if n in rows}
    error_vs_time(curves, out / "error_vs_time.png",
                  title=f"error vs training time ({header.get('preset', '')}, "
                  f"seeds {header.get('seeds', '')})", lines=lines)
    summaries = {name: {col: summary(values(rows[name], keys, scale))
                        for col, _, keys, _, scale in T1_COLUMNS + T2_COLUMNS + t3_columns(rows)}
                 for name in ordered(rows)}
    fused = {name: {col: summary(values(found, keys, scale))
                    for col, _, keys, _, scale in T2_COLUMNS + T3_COLUMNS}
             for name in ordered(rows) for label, found in extractions(rows[name]) if label == "fused"}
    results = {**header, "lpips": {"available": not lpips_reason, "reason": lpips_reason or None},
               "published": published, "summary": summaries, "summary_fused": fused,
               "rows": {n: rows[n] for n in ordered(rows)}}
    write_json(out / "results.json", jsonable(results), indent=1)
    report_page(out, header, [("Table 1: appearance", t1), ("Table 2: geometry", t2),
                             ("Table 3: the surveyor's figures", t3), ("Table 4: the water's optics", t4)])
    return t1 + "\n" + t2 + "\n" + t3 + ("\n" + t4 if t4 else "")


def report_page(out: Path, header: dict, tables: list[tuple[str, str]]) -> Path:
    """out/report.html: the tables (title, Markdown; empty ones left out), the error-against-time plot and
    each row's depth-error map of training seed 0, on one page."""
    from ragsplat.outputs import versions
    from ragsplat.pages import file_uri, markdown_blocks, write_page

    maps = [(folder.relative_to(out).parts[0], file_uri(folder / "depth_error.png"))
            for folder in sorted(out.glob("*/seed0")) if (folder / "depth_error.png").is_file()]
    maps += [(folder.name, file_uri(folder / "depth_error.png"))
             for folder in sorted(out.glob("*")) if (folder / "depth_error.png").is_file()]
    return write_page(out / "report.html", "ablation.html.j2",
                      title=f"ragsplat ablation: {header.get('preset', '')} on "
                            f"{Path(header.get('data', '')).name}",
                      data=header.get("data", ""), seeds=header.get("seeds", ""), versions=versions("torch"),
                      curve=file_uri(out / "error_vs_time.png"),
                      tables=[(name, markdown_blocks(text)) for name, text in tables if text], maps=maps)


