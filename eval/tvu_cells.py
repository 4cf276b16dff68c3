"""A finished run's bed cells with their uncertainty features and true errors: what the TVU95 model
is fitted and calibrated on (`python -m tools.fit_uncertainty`, docs/uncertainty.md).

- the bed (`BEDS`): the evaluation's (`ablation.extract_config` of the run's preset and seed, on the ground
  truth's nodes inside its region: the bed `ragsplat score` scores and the ablation writes as the row's
  bed.npy), or the product's (`export.extract_bed` at `ragsplat export`'s and the survey's default 5 cm over
  the dataset's region: the DEM whose band 3 a surveyor reads), with the extraction's per-cell record
  (`surface.extract_surface(..., cells=True)`);
- the features: `uncertainty.cell_features` of those cells from the run's training views through the water
  the run ended with (`runs.run_water`);
- the errors: `evaluate.height_error` against the ground truth (predicted - true bed height);
- only the wet cells (true depth > 0) are kept.

The protocol's seeds (`ablation.DATASET_SEEDS`): the evaluation reach (dataset seed 0) and the untouched one
(7) are only scored, never fitted or calibrated on (`check_development`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ragsplat.errors import ConfigError, DatasetError, OutputError
from ragsplat.eval.ablation import DATASET_SEEDS, PRESETS, dataset_seed, extract_config
from ragsplat.uncertainty import CellFeatures

# The dataset seeds no uncertainty model may be fitted or calibrated on: the reaches the tables are scored on
HELD_OUT = {DATASET_SEEDS["evaluation"]: "evaluation", DATASET_SEEDS["untouched"]: "untouched"}
BEDS = ("evaluation", "export")  # which extraction's cells (module docstring)
PRODUCT_CELL = 0.05  # metres: `ragsplat export`'s and `ragsplat survey`'s default DEM cell


@dataclass(frozen=True)
class RunSource:
    """Where a finished run's cells come from, read from its config.json alone (no dataset loaded)."""

    run: Path
    data: Path  # the dataset it trained on
    truth: Path  # the dataset whose ground truth scores it (`data`, or another in the same frame)
    preset: str
    seed: int  # the training seed (also the extraction's)
    data_seed: int | None  # dataset seeds (`ablation.dataset_seed`; None: not rendered by the generator)
    truth_seed: int | None


@dataclass(frozen=True)
class RunCells:
    """A run's wet cells: their features, errors (m), true depths (m), and centres xy [N, 2] (m) on the
    extraction's grid of `cell` m (the oracle's smoothing needs them)."""

    source: RunSource
    features: CellFeatures
    errors: np.ndarray
    depth: np.ndarray
    xy: np.ndarray
    cell: float


def run_source(run: Path, truth: Path | None = None) -> RunSource:
    """The run's datasets, preset and seeds from RUN/config.json. Raises OutputError (not a finished run's
    config)."""
    run = Path(run)
    try:
        meta = json.loads((run / "config.json").read_text())
        data, preset, seed = Path(meta["dataset"]), str(meta["config"]["preset"]), int(meta["config"]["seed"])
    except (OSError, ValueError, KeyError, TypeError):
        raise OutputError(f"{run}: not a finished training run (no config.json naming its dataset, preset "
                          "and seed)") from None
    truth = data if truth is None else Path(truth)
    return RunSource(run, data, truth, preset, seed, dataset_seed(data), dataset_seed(truth))


def check_development(source: RunSource) -> None:
    """Raises ConfigError where the run trained on, or would be scored against, a held-out reach (`HELD_OUT`):
    fitting or calibrating there would tune the uncertainty on the test."""
    for what, root, seed in (("trained on", source.data, source.data_seed),
                             ("scored against", source.truth, source.truth_seed)):
        if seed in HELD_OUT:
            raise ConfigError(f"{source.run}: {what} {root}, dataset seed {seed}, the {HELD_OUT[seed]} "
                              "reach: an uncertainty model is fitted and calibrated on development seeds "
                              f"only (not {', '.join(str(s) for s in sorted(HELD_OUT))}); see "
                              "docs/uncertainty.md")


def run_cells(source: RunSource, level_sigma: float = 0.0, n_sigma: float = 0.0,
              bed: str = "evaluation") -> RunCells:
    """The wet cells of the run `source` on the bed `bed` (`BEDS`, module docstring); `level_sigma` (m) and
    `n_sigma`: the systematic term's standard deviations (0: the development seeds render with the true
    water). Raises OutputError, DatasetError (a dataset missing, changed, without ground truth, or in another
    frame), ConfigError (a preset without evaluation settings, an unknown bed)."""
    from ragsplat.dataset.load import load_dataset
    from ragsplat.eval.evaluate import height_error
    from ragsplat.export import extract_bed
    from ragsplat.runs import load_run, run_water
    from ragsplat.surface import extract_surface, size_cap_m
    from ragsplat.train.config import TrainConfig
    from ragsplat.uncertainty import cell_features

    if bed not in BEDS:
        raise ConfigError(f"unknown bed {bed!r}; choose one of {', '.join(BEDS)}")
    if source.preset not in PRESETS:
        raise ConfigError(f"{source.run}: preset {source.preset!r} has no evaluation settings; known: "
                          f"{', '.join(PRESETS)}")
    gaussians, ds, seed = load_run(source.run)
    tds = load_dataset(source.truth, splits=(), ground_truth=True)
    if tds.georef.offset != ds.georef.offset:
        raise DatasetError(f"{source.truth} is in another frame than {ds.root} (offsets {tds.georef.offset} "
                           f"and {ds.georef.offset})")
    truth = tds.ground_truth
    meta = json.loads((Path(source.run) / "config.json").read_text())
    water, train = run_water(meta, ds), TrainConfig.from_dict(meta["config"])
    if bed == "evaluation":
        cfg = extract_config(train, len(truth.nodes), ds.gsd)
        grid, stats = extract_surface(gaussians["means"], gaussians["scales"], gaussians["quats"],
                                      gaussians["opacities"], cfg, truth.region,
                                      tuple(truth.grid[:, :2].min(0)), cells=True)
        record, cell = stats["cells"], cfg.cell
    else:
        product = extract_bed(gaussians, PRODUCT_CELL, water, ds.eval_region, ds.georef, seed, ds.gsd,
                              cells=True, max_scale_m=size_cap_m(train))
        grid, record, cell = product.grid, product.cells, product.resolution
    features = cell_features(grid, ds.train_cameras, water, record, level_sigma, n_sigma)
    dz, depth = height_error(grid, truth)
    wet = depth > 0
    return RunCells(source, features.select(wet), dz[wet], depth[wet], grid[wet, :2], cell)


def truth_seeds(cells: RunCells) -> np.ndarray:
    """[N] the dataset seed of the truth each of the run's cells is scored against (-1: none recorded)."""
    return np.full(len(cells.errors), -1 if cells.source.truth_seed is None else cells.source.truth_seed)


def pooled(cells: list[RunCells]) -> tuple[CellFeatures, np.ndarray, np.ndarray]:
    """(the features, errors [N] and truth dataset seeds [N] (`truth_seeds`) of every run's cells, in
    order)."""
    from dataclasses import fields

    features = CellFeatures(**{f.name: np.concatenate([getattr(c.features, f.name) for c in cells])
                               for f in fields(CellFeatures)})
    seeds = np.concatenate([truth_seeds(c) for c in cells])
    return features, np.concatenate([c.errors for c in cells]), seeds


def check_held_out(model, seed: int | None) -> None:
    """Raises ConfigError where the dataset (its seed `seed`) is not held out from the uncertainty model: a
    band scored on the cells it was fitted or calibrated on says nothing of its coverage."""
    seen = set(model.fit_seeds) | set(model.calibration_seeds)
    if seed is None or seed in seen:
        raise ConfigError(f"the dataset (seed {seed}) is not held out from the uncertainty model (fitted on "
                          f"{list(model.fit_seeds)}, calibrated on {list(model.calibration_seeds)})")


def band_rows(out: Path, data: Path, rows: dict[str, list[dict]], model, log=lambda line: None) -> dict:
    """Each trained row's TVU95 band from the fitted `model` (docs/uncertainty.md): over the wet cells of its
    volume bed (`tvu_cells.run_cells`, the extraction Table 3 scores), written as `tvu95.tif` in the row's
    folder (one float32 band, the cells' TVU95 in m, on the bed's grid) and scored against the truth
    (`calibration.calibration_report`, the row's cells one seed and one bed) under
    row["geometry"]["survey"]["tvu"], which Table 3 shows. Computed each time from the finished rows (an
    extraction and the cells' view geometry per row), not kept in row.json: the model is not part of a row's
    key. Returns what results.json records of the model. `run_ablation(band=...)` calls it."""
    from ragsplat.dataset import rasters
    from ragsplat.eval.calibration import calibration_report
    from ragsplat.eval.rows import row_dir
    from ragsplat.export import TVU_BAND
    from ragsplat.train.config import VARIANTS
    from ragsplat.uncertainty import tvu95

    for name, found in rows.items():
        if name not in VARIANTS:
            continue
        for k, row in enumerate(found):
            folder = row_dir(out, name, row["seed"])
            cells = run_cells(run_source(folder, data))
            t = tvu95(model, cells.features)
            report = calibration_report(t, cells.errors, truth_seeds(cells), cells.depth,
                                        cells.features.views, cells.xy, cells.cell)
            rasters.write_raster(folder / "tvu95.tif", cells.xy, [(t, TVU_BAND)], cells.cell)
            survey = {**row["geometry"].get("survey", {}), "tvu": report}
            found[k] = {**row, "geometry": {**row["geometry"], "survey": survey},
                        "outputs": {**row.get("outputs", {}), "tvu95": str(folder / "tvu95.tif")}}
            log(f"[{name} seed {row['seed']}] TVU95 band: {100 * report['coverage']['0.95']:.1f} % of "
                f"{report['cells']} wet cells within it, median {100 * report['median_tvu95']:.2f} cm")
    return {"fit_seeds": list(model.fit_seeds), "calibration_seeds": list(model.calibration_seeds),
            "features": list(model.features), "weights": list(model.weights), "scale": model.scale,
            "commit": model.commit}


def truth_map(pairs: list[str]) -> dict[Path, Path]:
    """{RUN: DATA} of --truth RUN=DATA options (paths resolved). Raises ConfigError for a malformed one."""
    out = {}
    for pair in pairs:
        run, sep, data = pair.partition("=")
        if not sep or not run or not data:
            raise ConfigError(f"--truth {pair!r}: expected RUN=DATA")
        out[Path(run).resolve()] = Path(data)
    return out
