"""Score a finished training run against its dataset's ground truth without retraining (`ragsplat score RUN`).

Everything comes from the ablation's own code: the dataset and ground truth as
`ragsplat.eval.ablation.TrainEval` loads them, the extraction settings of the run's preset (`extract_config`,
seeded with the run's seed, and the preset's fusion settings), the measures of `ragsplat.eval.evaluate` (the
bed extracted both ways: volume sampling and fused depth) and the reference answers of
`ragsplat.eval.references` (`init`: the run's own initial Gaussians; `oracle plane`). A run the ablation
trained therefore scores exactly as its row.json.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from ragsplat.dataset import layout
from ragsplat.errors import ConfigError, DatasetError
from ragsplat.eval import metrics
from ragsplat.eval.ablation import CODE, PRESETS, TrainEval, extract_config
from ragsplat.eval.evaluate import evaluate_fused, evaluate_geometry, evaluate_views, score_grid
from ragsplat.eval.references import USES_GROUND_TRUTH, oracle_grids, start_extraction
from ragsplat.eval.report import T2_COLUMNS, T3_COLUMNS, geometry_table, water_notes
from ragsplat.outputs import source_digest, versions
from ragsplat.runs import load_model

# The short table: the ablation's CD and F1 columns (Table 2) and the wet and banks bias and errors (Table 3)
COLUMNS = [c for c in T2_COLUMNS if c[0].startswith(("CD", "F1"))] + \
    [c for c in T3_COLUMNS if c[0] in ("bias (cm)", "RMSE (cm)", "p95 (cm)", "banks bias (cm)")]


def score_run(run: Path, data: Path | None = None, vgg16: str | None = None, download: bool = True,
              log: Callable[[str], None] = lambda line: None, truth: Path | None = None,
              dem: Path | None = None, extract: dict | None = None) -> dict:
    """The run's appearance on the held-out views (`evaluate_views`: PSNR, SSIM, LPIPS when its weights are
    found or, with `download`, fetched) and its bed's geometry (`evaluate_geometry`; `evaluate_fused` of its
    training views under "geometry_fused"), with the reference answers' geometry under "references". `data`:
    the run's dataset moved elsewhere. `truth`: score against another dataset's ground truth and held-out
    views, in the same frame (a survey imported from a synthetic dataset's COLMAP model). `dem`: also score
    that DEM GeoTIFF (`ragsplat export`) under "dem". `extract`: ExtractConfig fields to change for the volume
    bed (e.g. {"max_scale_gsd": math.inf}). Raises OutputError (not a finished run), DatasetError (dataset
    missing, changed, without ground truth or held-out views, in another frame), ConfigError (a preset the
    harness does not know)."""
    model, ds = load_model(run, data, splits=("train",))  # the training cameras: the views fusion reads
    cfg = model.cfg
    if cfg.preset not in PRESETS:
        raise ConfigError(f"{run}: preset {cfg.preset!r} has no evaluation settings; known: "
                          f"{', '.join(PRESETS)}")
    runner = TrainEval(ds.root if truth is None else truth)
    if runner.ds.georef.offset != ds.georef.offset:
        raise DatasetError(f"{runner.ds.root} is in another frame than {ds.root} (offsets "
                           f"{runner.ds.georef.offset} and {ds.georef.offset})")
    truth = runner.truth
    ecfg = replace(extract_config(cfg, len(truth.nodes), ds.gsd), **(extract or {}))
    lpips_metric, lpips_reason = metrics.load_lpips(vgg16, download=download, log=log)
    if lpips_reason:
        log(f"LPIPS n/a: {lpips_reason}")
    else:
        lpips_metric.to(model.device)
    appearance = evaluate_views(lambda view, interface: model.render(view.camera, interface)[0],
                                runner.ds.test, lpips_metric)
    geometry, _ = evaluate_geometry(model.gaussians(), truth, ecfg)
    fused, _ = evaluate_fused(model.median_depth, ds.train, truth, PRESETS[cfg.preset].fuse, ecfg.cell)
    initial = runner.initial(replace(cfg, device=str(model.device), backend=model.backend))
    return {"run": str(run), "data": str(Path(ds.root).resolve()), "dataset_fingerprint": ds.fingerprint,
            "dataset_seed": runner.dataset_seed, "variant": cfg.variant, "preset": cfg.preset,
            "seed": cfg.seed,
            "harness_preset": asdict(PRESETS[cfg.preset]), "water": layout.water_json(model.water),
            "truth_water": layout.water_json(truth.water), "max_depth_m": truth.max_depth,
            "lpips": {"available": not lpips_reason, "reason": lpips_reason or None},
            "lpips_network": getattr(lpips_metric, "network", None), "versions": versions("torch", "scipy"),
            "code_digest": source_digest(*CODE), "num_gaussians": int(model.splats["means"].shape[0]),
            "appearance": appearance, "geometry": geometry, "geometry_fused": fused,
            "references": {"init": evaluate_geometry(initial, truth, start_extraction(ecfg))[0],
                           **{name: score_grid(grid, truth) for name, grid in oracle_grids(truth).items()},
                           **{name: score_grid(grid, truth)
                              for name, grid in runner.track_grids(log).items()}},
            "uses_ground_truth": list(USES_GROUND_TRUTH),
            **({} if dem is None else {"dem": _score_dem(dem, ds.georef, truth)})}


def _score_dem(path: Path, georef, truth) -> dict:
    """The DEM read at the ground truth's nodes as `ragsplat score` reads it (`score_file.read_bed`: the same
    cells as every row; a DEM's own cells off that lattice would add their horizontal offset to every F1
    distance) and scored like an extracted bed, its error map written beside it (NAME_error.png)."""
    from ragsplat.eval.report import depth_error_map
    from ragsplat.eval.score_file import read_bed

    grid, _ = read_bed(path, truth, georef)
    figure = depth_error_map(grid, truth, Path(path).with_name(Path(path).stem + "_error.png"),
                             Path(path).name)
    return {"file": str(path), "error_map": str(figure), **score_grid(grid, truth)}


def dem_points(path: Path, georef) -> np.ndarray:
    """[P, 3] the covered cells of a DEM GeoTIFF's band 1 (bed elevation) as cell-centre points in the
    dataset's frame (`georef`'s offset taken off). Raises DatasetError for a file rasterio cannot read."""
    import rasterio

    try:
        with rasterio.open(path) as tif:
            z = tif.read(1, masked=True)
            rows, cols = np.nonzero(~np.ma.getmaskarray(z))
            xs, ys = rasterio.transform.xy(tif.transform, rows, cols)
    except rasterio.errors.RasterioIOError as err:
        raise DatasetError(f"{path}: not a readable GeoTIFF ({err})") from None
    return np.column_stack([xs, ys, z.data[rows, cols]]).astype(np.float64) - np.asarray(georef.offset)


def table(result: dict) -> str:
    """The run's geometry beside the reference answers' as a Markdown table, then its appearance."""
    rows = [(f"{name} (uses GT)" if name in USES_GROUND_TRUTH else name, geometry)
            for name, geometry in result["references"].items()]
    rows += [(f"{result['variant']} (this run), volume", result["geometry"]),
             (f"{result['variant']} (this run), fused", result["geometry_fused"])]
    if "dem" in result:
        rows.append((f"its DEM ({Path(result['dem']['file']).name})", result["dem"]))
    lines = [geometry_table(["Row"], [([name], geometry) for name, geometry in rows], COLUMNS)]
    depth = result["max_depth_m"]
    lines += ["", (f"- F1 at 10 / 30 cm and at 1 % / 3 % of the maximum depth ({depth:g} m); dz = predicted "
                   "- true bed height: p95 of |dz| over every wet cell (a hole counts as a miss), bias and "
                   "RMSE over the covered wet cells, banks bias over the emerged ground."),
              ("- volume: volume sampling of the Gaussians; fused: TSDF fusion of the true Gaussians' median "
               "depth maps of the training views.")]
    lines += [f"- {note}" for note in water_notes({"water": result.get("truth_water")})]  # a sloping surface
    app = result["appearance"]
    for cond, what in (("refr", "through the water vs the with-water images"),
                       ("dry", "without it vs the dry images")):
        if app[cond] is not None:
            a = app[cond]
            lpips = "n/a" if a["lpips"] is None else f"{a['lpips']:.3f}"
            lines.append(f"- {len(app['per_view'])} held-out views, {what}: PSNR {a['psnr']:.2f} dB, "
                         f"SSIM {a['ssim']:.3f}, LPIPS {lpips}")
    return "\n".join(lines)
