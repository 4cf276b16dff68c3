"""The ablation: train every variant for every seed, evaluate it, score the reference answers, and
regenerate the paper's Tables 1 and 2 (plus the surveyor's table) as mean +- standard deviation over seeds.

Per variant and seed (a row, `OUT/<variant>/seed<S>/`): train with evaluation points (step 0 included;
PSNR in both conditions and the geometry at every threshold against training time, with the table's
extraction settings), then evaluate on the held-out views (PSNR, SSIM, LPIPS; `refr` = rendered through
the interface vs the with-water images, `dry` = true Gaussians without it vs the dry images) and the bed,
extracted twice and each scored by `ragsplat.eval.evaluate.score_grid`: "volume" (`geometry`: volume sampling
of the Gaussians, `ragsplat.surface`) and "fused" (`geometry_fused`: TSDF fusion of the true Gaussians' median
depth maps of the training views, `ragsplat.fusion`). The reference rows (`ragsplat.eval.references`) are
height grids scored the same way (no fused variant). Every row writes `row.json`, the extracted bed
(`bed.npy`, `bed.tif`) and its depth-error map (`depth_error.png`); a trained row also the fused bed
(`bed_fused.npy`, `bed_fused.tif`, `bed_fused.ply`: the height grid as a triangle mesh,
`depth_error_fused.png`).

A row is reused only when its key matches: the dataset's content fingerprint (images and ground truth),
the resolved training and extraction configs, the harness preset and the source digest of the code that
computes it (`ROW_CODE`: ragsplat_core and the harness's training and scoring; a reference row also its
settings and `eval/references.py`), so a change to the tables or the references alone retrains nothing. A
killed row resumes from its checkpoint only under the same key (`key.json`, written before training starts);
otherwise it starts over. Then `ragsplat.eval.report` (re)writes `OUT/results.json`, the tables and
`error_vs_time.png` from the rows of this run's variants and seeds only. The command is
`ragsplat.cli.ablation`.

The water. Every row is scored against the ground truth's own surface (`GroundTruth.water`, a river's sloping
plane included: depths below it). What the method and the references are given is the dataset's surface, or,
with one level (`--one-level`, `one_level_water`), one flat level at the mean height of the water's edge
points a surveyor measured (`EDGE_POINTS`): what a flat-water tool does on a sloping river. That choice is
part of every row key and of results.json ("one_level").
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from ragsplat.dataset import layout
from ragsplat.errors import ConfigError, DatasetError
from ragsplat.eval import metrics
from ragsplat.eval.evaluate import (
    evaluate_fused,
    evaluate_geometry,
    evaluate_views,
    model_depth,
    model_gaussians,
    model_renderer,
    score_grid,
)
from ragsplat.eval.references import (
    DIETRICH_DENSE_REDUCE,
    DIETRICH_MAX_ANGLE,
    DIETRICH_TRACKS,
    EXTRACTION,
    REFERENCES,
    REFERENCES_CODE,
    SEEDLESS,
    TIN_FILTER,
    USES_GROUND_TRUTH,
    depth_times_n,
    dietrich_grid,
    oracle_grids,
    start_extraction,
    track_grids,
)
from ragsplat.eval.report import write_outputs
from ragsplat.eval.rows import cached_row, claim_out, row_dir, save_row, slug, start_row
from ragsplat.fusion import FuseConfig
from ragsplat.outputs import jsonable, source_digest, versions, write_json
from ragsplat.surface import EXTRACT_TUNING, ExtractConfig, size_cap_m
from ragsplat.train.config import FIELD_TUNING, INIT, LONG_TUNING, SURFELS, TUNING, VARIANTS, TrainConfig
from ragsplat.train.defaults import JOBS
from ragsplat.water_surface import WaterSurface


@dataclass(frozen=True)
class AblationPreset:
    """What the harness itself varies by preset (training sizes come from the trainer's preset)."""

    name: str
    checkpoints: int  # evaluation intervals along training: points at step 0, k * iterations / this, the end
    # extraction samples per ground-truth node of the region (wet and banks), table and curves
    samples_per_cell: int
    fuse: FuseConfig = field(default_factory=FuseConfig)  # the fused extraction, table and curves


PRESETS = {
    "smoke": AblationPreset("smoke", checkpoints=8, samples_per_cell=4),
    "small": AblationPreset("small", checkpoints=8, samples_per_cell=16),
    "paper": AblationPreset("paper", checkpoints=8, samples_per_cell=16),
}
PRESETS["small-field"] = replace(PRESETS["small"], name="small-field")
PRESETS["small-3dgs"] = replace(PRESETS["small"], name="small-3dgs")
PRESETS["long"] = replace(PRESETS["small"], name="long")
CODE = ("ragsplat_core", "eval")  # the sources whose digest stamps results.json
# The sources a row's numbers come from, whose digest is part of every row key: training, extraction and
# scoring (the references' own code joins a reference row's key; the tables are written anew every run).
ROW_CODE = ("ragsplat_core", "eval/ablation.py", "eval/rows.py", "eval/evaluate.py", "eval/metrics.py")
# The protocol's reach seeds (dataset seeds of `small`): hyperparameters and the references' settings chosen
# on the development reach; the evaluation reach measured after every tuning round until the presets were
# frozen (so partly a validation set); the untouched reach rendered and measured once, with the presets
# frozen (results.json: "dataset_role").
DATASET_SEEDS = {"development": 1, "evaluation": 0, "untouched": 7}
# The main job's defaults, here only (`ragsplat ablation` takes them; the Makefile passes nothing unless
# told): every row starts from the refracted tracks (`INIT`, the training's own default start, shared with
# `ragsplat survey`), the clear-water variants (`CLEAR_VARIANTS`), three training seeds (tables: mean +- std),
# and on the CPU `JOBS` processes of cores / JOBS threads (`train.defaults`, shared with the survey's tiles).
# On CUDA six processes per GPU: one `small` row leaves a GPU mostly idle (launch-bound), six at once keep it
# busy (docs/lab/performance.md, "On a GPU").
SEEDS = (0, 1, 2)
# The water's edge as a surveyor measures it (header x,y,z; the generator writes it into every reach dataset):
# where one level (`--one-level`) is taken from.
EDGE_POINTS = layout.SURVEY_EDGE
JOBS_PER_GPU = 6


def visible_gpus(device: str | None) -> list[str]:
    """The GPUs `--jobs`' processes are shared out over (each sees one as "cuda"): every visible one when
    training goes to CUDA without an index (None: the presets' "auto", CUDA when available); none (the
    environment as it is) otherwise."""
    import torch

    if device not in (None, "auto", "cuda") or not torch.cuda.is_available():
        return []
    listed = os.environ.get("CUDA_VISIBLE_DEVICES")
    return listed.split(",") if listed else [str(k) for k in range(torch.cuda.device_count())]


def trains_on_cuda(device: str | None) -> bool:
    """Whether the rows train on CUDA: a "cuda" device, or the presets' "auto" (None) where CUDA is there."""
    import torch

    return str(device).startswith("cuda") or (device in (None, "auto") and torch.cuda.is_available())


def default_jobs(device: str | None) -> int:
    """`--jobs`' default for training on `device`: JOBS_PER_GPU on each GPU it shares out over, or on the
    one GPU it names ("cuda:1", or "cuda" where none is visible), else JOBS."""
    gpus = visible_gpus(device)
    if gpus:
        return JOBS_PER_GPU * len(gpus)
    return JOBS_PER_GPU if trains_on_cuda(device) else JOBS


def _scene(data: Path) -> dict:  # the dataset's scene.json ({} for one the generator did not render)
    scene = Path(data) / layout.SCENE
    return json.loads(scene.read_text()) if scene.is_file() else {}


def dataset_seed(data: Path) -> int | None:
    """The seed the dataset `data` was rendered with (its scene.json), None for one that was not rendered."""
    return _scene(data).get("seed")


def scene_conditions(data: Path) -> dict | None:
    """The field conditions the dataset `data` was rendered with (its scene.json's "conditions": the water
    body's coefficients, reflection, ripples), None for a clear scene or one that was not rendered."""
    return _scene(data).get("conditions")


def one_level_water(data: Path, water: WaterSurface | None) -> tuple[WaterSurface, dict]:
    """(the flat surface, its record) that a flat-water tool puts on the dataset `data` with the surface
    `water`: one level, the mean height of the water's edge points a surveyor measured (`EDGE_POINTS`), with
    the dataset's n. Raises DatasetError (no such file, or not an x,y,z CSV of finite points) or ConfigError
    (a dataset without water)."""
    path = Path(data) / EDGE_POINTS
    if water is None:
        raise ConfigError(f"{data}: no water, so no level to give (--one-level)")
    if not path.is_file():
        raise DatasetError(f"{path}: no such file; one level (--one-level) is the mean height of the water's "
                           "edge points as surveyed (a CSV with header x,y,z)")
    pts = layout.read_points(path)
    if not len(pts):
        raise DatasetError(f"{path}: no points; one level (--one-level) is the mean height of the water's "
                           "edge")
    level = float(pts[:, 2].mean())
    flat = WaterSurface(level, float(water.n))
    # the file as the dataset names it: a moved dataset keeps its rows' keys
    return flat, {"level": level, "n": float(water.n), "edge_points": len(pts), "edge_file": EDGE_POINTS}


def dataset_role(seed: int | None, preset: str) -> str:
    """What the protocol uses the reach of dataset seed `seed` for (`DATASET_SEEDS`; the `small` family's)."""
    if not preset.startswith("small"):
        return "other"
    return next((role for role, s in DATASET_SEEDS.items() if s == seed), "other")


def extract_config(train: TrainConfig, n_nodes: int, gsd: float | None) -> ExtractConfig:
    """The table's extraction of a model trained under `train` (its preset's samples, its seed, the size cap
    of its surfels' depth: `surface.size_cap_m`) over a region of `n_nodes` ground-truth nodes
    (`GroundTruth.nodes`: wet and banks, the cells `ragsplat export` counts over the same region) with views
    of `gsd` m per pixel (`Dataset.gsd`)."""
    return replace(ExtractConfig(), n_samples=PRESETS[train.preset].samples_per_cell * n_nodes,
                   max_scale_m=size_cap_m(train), seed=train.seed, gsd=gsd)


def eval_steps(iterations: int, checkpoints: int, reset_every: int = 0, reset_stop: int = 0) -> list[int]:
    """Evenly spaced evaluation steps strictly between 0 and the end (the harness adds both).

    A step within half a reset period after an opacity reset (every `reset_every` steps before
    `reset_stop`) moves to the step before that reset: right after a reset every opacity sits below the
    extraction's cull threshold, so the curve would show the reset, not the state of training.
    """
    steps = set()
    for k in range(1, checkpoints):
        step = round(k * iterations / checkpoints)
        if reset_every:
            last_reset = step // reset_every * reset_every
            if 0 < last_reset < reset_stop and step - last_reset < reset_every / 2:
                step = last_reset - 1
        steps.add(step)
    return sorted(steps - {0, iterations})


# ---------------------------------------------------------------- the run


def run_ablation(data: Path, out: Path, preset: str, variants: list[str], seeds: list[int], runner,
                 vgg16: str | None = None, download: bool = True,
                 log: Callable[[str], None] = lambda line: None, code: str | None = None,
                 rows_only: bool = False, band: Callable | None = None,
                 geotiffs: bool = True) -> dict[str, list[dict]]:
    """Rows for `variants` x `seeds` and the reference rows, reused from `out` when their key matches, else
    computed with `runner` (a `TrainEval`, or anything with its `truth`, `fingerprint`, `dataset_seed`, `gsd`,
    `config`, `initial` and `train`); then all outputs. Returns {name: [row per seed]}.
    `download`: fetch missing LPIPS weights (`metrics.load_lpips`). `log(line)` receives progress lines and,
    at the end, the tables. `rows_only`: the trained rows and nothing else (a Dask task's part, `train_row`;
    a run without it then reuses those rows and writes the rest).
    `code`: the source digest the command started with; ConfigError if the sources are no longer those (an
    edit during a long run would otherwise key its rows to two versions of the code).
    `band`: with a fitted uncertainty model, `band(out, data, rows)` adds each trained row's TVU95 band before
    the tables are written and returns what results.json records of the model (`tvu_cells.band_rows`).
    `geotiffs`: False writes no row's bed.tif (a machine without rasterio); a later run with it, reusing the
    rows, writes them from their bed arrays (`rows.cached_row`).
    """
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise ConfigError(f"unknown variant {unknown[0]!r}; choose from {', '.join(VARIANTS)}")
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    if not seeds or len(set(seeds)) != len(seeds):
        raise ConfigError(f"seeds must be distinct and at least one, got {seeds}")
    claim_out(out)
    stamp = versions("torch", "scipy")  # the code that runs now, not the checkout at the end of a long run
    truth = runner.truth
    live = source_digest(*ROW_CODE)
    if code is not None and code != live:
        raise ConfigError(f"the sources of {', '.join(ROW_CODE)} changed since this command started "
                          f"(digest {code}, now {live}); rerun it")
    base = {"dataset": runner.fingerprint, "code": live, "harness": asdict(PRESETS[preset])}
    one_level = getattr(runner, "one_level", None)  # the flat water the method and the references are given
    if one_level is not None:  # keyed apart: rows with and without it never mix in one folder
        base["one_level"] = one_level
    lpips_metric, lpips_reason = metrics.load_lpips(vgg16, download=download, log=log)
    if lpips_reason:
        log(f"LPIPS n/a: {lpips_reason}")
    rows: dict[str, list[dict]] = {}

    def trained_row(seed: int, variant: str) -> dict:
        cfg = runner.config(variant, preset, seed)
        ecfg = extract_config(cfg, len(truth.nodes), runner.gsd)
        key = {**base, "train": cfg.to_dict(), "extract": ecfg.to_dict()}
        folder = row_dir(out, variant, seed)
        row = cached_row(folder, key, log, geotiffs)
        if row is not None:
            log(f"[{variant} seed {seed}] reusing the finished row in {folder}")
            return row
        log(f"[{variant} seed {seed}] training ...")
        start_row(folder, key)
        t0 = time.perf_counter()
        row, grid, fused = runner.train(cfg, folder, ecfg, PRESETS[preset].fuse, PRESETS[preset].checkpoints,
                                        lpips_metric)
        row = {**row, "name": variant, "seed": seed, "key": key, "lpips_reason": lpips_reason or None,
               "timings": {**row.get("timings", {}), "row_total_s": time.perf_counter() - t0}}
        return save_row(folder, row, grid, truth, fused, geotiffs)

    for seed in seeds:
        for variant in variants:
            rows.setdefault(variant, []).append(trained_row(seed, variant))
        if rows_only:
            continue
        for name, row in reference_rows(out, runner, preset, seed, base, rows, log, geotiffs).items():
            rows.setdefault(name, []).append(row)
    if rows_only:
        return rows
    banded = None if band is None else band(out, data, rows)
    header = {"data": str(Path(data).resolve()), "dataset_fingerprint": runner.fingerprint,
              "dataset_seed": runner.dataset_seed, "dataset_seeds": DATASET_SEEDS,
              "dataset_role": dataset_role(runner.dataset_seed, preset), "tuning": TUNING,
              **({"field_tuning": FIELD_TUNING} if preset == "small-field" else {}),
              **({"long_tuning": LONG_TUNING} if preset == "long" else {}),
              "extract_tuning": EXTRACT_TUNING, "preset": preset, "seeds": list(seeds),
              "init": getattr(runner, "init", "grid"),
              "harness_preset": asdict(PRESETS[preset]), "code_digest": source_digest(*CODE),
              "row_code_digest": base["code"],
              "versions": stamp, "command": sys.argv,
              "conditions": scene_conditions(data),
              "max_depth_m": truth.max_depth, "water": layout.water_json(truth.water), "one_level": one_level,
              "lpips_network": getattr(lpips_metric, "network", None),
              "uncertainty": banded,
              "references": {"names": list(REFERENCES), "use_ground_truth": list(USES_GROUND_TRUTH),
                             "tin_filter": TIN_FILTER, "dietrich_tracks": DIETRICH_TRACKS,
                             "dietrich_3dgs_max_angle_deg": DIETRICH_MAX_ANGLE,
                             "dietrich_3dgs_reduce": DIETRICH_DENSE_REDUCE}}
    log(write_outputs(out, rows, header, lpips_reason))
    return rows


def reference_rows(out: Path, runner, preset: str, seed: int, base: dict, rows: dict[str, list[dict]],
                   log, geotiffs: bool = True) -> dict[str, dict]:
    """The reference rows of one seed (the oracle plane, which has no seed, with the first); `geotiffs` as
    in `run_ablation`."""
    truth, found = runner.truth, {}
    base = {**base, "references_code": REFERENCES_CODE}
    cfg = runner.config("3dgs", preset, seed)  # the initialisation does not depend on the variant
    ecfg = extract_config(cfg, len(truth.nodes), runner.gsd)
    init_key = {**base, "init": {k: v for k, v in cfg.to_dict().items() if k.startswith("init") or k in
                                 ("seed", "sh_degree", "preset")}, "extract": ecfg.to_dict()}
    todo = [("init", row_dir(out, "init", seed), init_key,
             lambda: evaluate_geometry(runner.initial(cfg), truth, start_extraction(ecfg)))]
    if rows.get("3dgs") and rows["3dgs"][-1]["seed"] == seed:
        src = rows["3dgs"][-1]
        water = getattr(runner, "water", None) or truth.water  # what the references are given
        n = float(water.n)

        def corrected():
            grid = depth_times_n(np.load(row_dir(out, "3dgs", seed) / "bed.npy"), water)
            return score_grid(grid, truth), grid

        todo.append(("3dgs x n", row_dir(out, "3dgs x n", seed), {**base, "from": src["key"], "n": n},
                     corrected))
        if hasattr(runner, "dietrich_grid"):
            def dietrich_3dgs():
                grid = runner.dietrich_grid(np.load(row_dir(out, "3dgs", seed) / "bed.npy"))
                return score_grid(grid, truth), grid

            todo.append(("dietrich (3dgs)", row_dir(out, "dietrich (3dgs)", seed),
                         {**base, "from": src["key"], "n": n, "max_angle_deg": DIETRICH_MAX_ANGLE,
                          "reduce": DIETRICH_DENSE_REDUCE}, dietrich_3dgs))
    if not rows.get("oracle plane"):
        for name, plane in oracle_grids(truth).items():
            todo.append((name, row_dir(out, name, None), {**base, "reference": name},
                         lambda plane=plane: (score_grid(plane, truth), plane)))
        if hasattr(runner, "track_grids"):  # seedless, like the planes: made once
            grids = runner.track_grids(log)
            key = {**base, "tracks": {"tin_filter": TIN_FILTER, "dietrich": DIETRICH_TRACKS}}
            for name, grid in grids.items():
                todo.append((name, row_dir(out, name, None), {**key, "reference": name},
                             lambda grid=grid: (score_grid(grid, truth), grid)))
    for name, folder, key, compute in todo:
        row = cached_row(folder, key, log, geotiffs)
        if row is None:
            geometry, grid = compute()
            row = save_row(folder, {"name": name, "seed": None if name in SEEDLESS else seed, "key": key,
                                    "geometry": geometry, "uses_ground_truth": name in USES_GROUND_TRUTH,
                                    "extraction": EXTRACTION[name]}, grid, truth, geotiffs=geotiffs)
        found[name] = row
    return found


# ---------------------------------------------------------------- the trainer integration


@dataclass(frozen=True)
class RowJob:
    """What a Dask worker needs to train rows of one `ragsplat ablation` command (`train_row`)."""

    data: str
    out: str
    preset: str
    init: str
    one_level: bool
    device: str | None
    vgg16: str | None
    code: str  # the sources' digest when the command started: rows keyed to the code it started with
    gpus: tuple[str, ...] = ()  # local workers' GPUs, shared out (`worker_gpu`); none: the worker's own
    geotiffs: bool = True  # as in `run_ablation`


def row_order(variants: list[str], seeds: list[int]) -> list[tuple[str, int]]:
    """The rows to train, (variant, seed), the surfel rows first: the longest start first, so that no worker
    idles at the end while another has two long rows left."""
    return sorted(((v, s) for s in seeds for v in variants), key=lambda row: row[0] not in SURFELS)


def row_log(out: Path, variant: str, seed: int) -> Path:
    """Where a worker's row writes its progress lines (`train_row`)."""
    return Path(out) / "logs" / f"{slug(variant)}-seed{seed}.log"


def worker_gpu(gpus: tuple[str, ...], worker) -> str:
    """The one GPU local worker `worker` (its name: 0, 1, ...) sees: GPU k mod their count."""
    return gpus[int(worker) % len(gpus)]


_RUNNERS: dict[tuple, TrainEval] = {}  # per worker process: each dataset loaded once for all its rows


def train_row(job: RowJob, variant: str, seed: int) -> str:
    """One trained row, in a Dask worker: `run_ablation` of that row alone (`rows_only`), resuming from its
    checkpoint when an earlier try left one (a worker that died: Dask runs the task again elsewhere); its
    lines go to `row_log`. Returns the log's path."""
    if job.gpus:  # before CUDA starts in this worker process
        from distributed import get_worker

        os.environ["CUDA_VISIBLE_DEVICES"] = worker_gpu(job.gpus, get_worker().name)
    spec = (job.data, job.device, job.init, job.one_level)
    if spec not in _RUNNERS:
        _RUNNERS[spec] = TrainEval(Path(job.data), job.device, None, job.init, job.one_level)
    path = row_log(Path(job.out), variant, seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        say = lambda line: print(line, file=f, flush=True)
        say(f"[{variant} seed {seed}] worker process {os.getpid()}")
        run_ablation(Path(job.data), Path(job.out), job.preset, [variant], [seed], _RUNNERS[spec],
                     vgg16=job.vgg16, download=False, log=say, code=job.code, rows_only=True,
                     geotiffs=job.geotiffs)
    return str(path)


class TrainEval:
    """The `runner` of `run_ablation` on a dataset directory, with `ragsplat.train`.

    The dataset (with its dry images) and the ground truth are loaded once for all variants.
    `training_bar(total, desc, initial) -> (bar, on_step)` shows training progress (None: nothing shown).
    `one_level`: every row and reference is given one flat level at the mean of the surveyed edge points
    instead of the dataset's surface (`one_level_water`; `water` is what they are given, `one_level` its
    record or None); the scoring keeps the ground truth's surface. `held_out`: refuse a dataset without test
    views (the rows score them); False for the tracks' reference rows alone (`track_grids`), which read the
    training views only (a stretch of the long reach has no test views).
    """

    def __init__(self, data: Path, device: str | None = None, training_bar: Callable | None = None,
                 init: str = INIT, one_level: bool = False, held_out: bool = True):
        from ragsplat.dataset.load import load_dataset

        self.ds = load_dataset(data, ground_truth=True)
        if held_out and not self.ds.test:
            raise DatasetError(f"{data / layout.TRANSFORMS}: no frame has split 'test' "
                               "(held-out views are needed)")
        self.truth = self.ds.ground_truth
        self.fingerprint = self.ds.fingerprint
        self.water, self.one_level = (one_level_water(data, self.ds.water) if one_level
                                      else (self.ds.water, None))
        self.gsd = self.ds.gsd
        self.dataset_seed = dataset_seed(data)
        self.device = device
        self.training_bar = training_bar
        self.init = init  # TrainConfig.init of every row

    def config(self, variant: str, preset: str, seed: int):
        from ragsplat.train import preset_config

        overrides = {"variant": variant, "seed": seed, "init": self.init}
        if self.one_level is not None:  # what a flat-water tool is given: one level, no slope
            overrides.update(water_level=self.one_level["level"], water_slope=(0.0, 0.0))
        if self.device is not None:
            overrides["device"] = self.device
        return preset_config(preset, **overrides)

    def track_grids(self, log: Callable[[str], None]) -> dict[str, np.ndarray]:
        """The tracks' reference grids (`references.track_grids`, through the water the references are given:
        `water`), or none with the reason logged (a dataset without water, or whose images give no tracks)."""
        try:
            if self.ds.water is None:
                raise DatasetError(f"{self.ds.root}: no water, no refraction to correct")
            return track_grids(self.ds.root, self.fingerprint, {v.file_path: v.camera for v in self.ds.train},
                               self.water, self.truth.nodes)
        except DatasetError as err:
            log(f"the tracks' reference rows n/a: {err}")
            return {}

    def dietrich_grid(self, bed: np.ndarray) -> np.ndarray:
        """Dietrich's correction of an apparent bed grid [G, 3] by the training cameras through the water the
        references are given (`water`)."""
        return dietrich_grid(bed, [v.camera for v in self.ds.train], self.water)

    def initial(self, cfg) -> dict:
        """The activated Gaussians training would start from (nothing is written)."""
        from ragsplat.train import Trainer

        return model_gaussians(Trainer(cfg, self.ds, None))

    def train(self, cfg, out: Path, ecfg: ExtractConfig, fcfg: FuseConfig, checkpoints: int,
              lpips_metric=None, view_ripples: Callable | None = None) -> tuple[dict, np.ndarray, np.ndarray]:
        """Train `cfg` in `out` (resuming its checkpoint), with the curve's evaluation points; returns the
        row and the two extracted bed grids (volume, fused). `view_ripples`: the `Trainer`'s."""
        from ragsplat.train import Trainer

        trainer = Trainer(cfg, self.ds, out, view_ripples=view_ripples)
        curve_file = out / "curve.json"
        curve = []
        if curve_file.is_file() and trainer.step > 0:  # points recorded before the kill, up to the checkpoint
            curve = [c for c in json.loads(curve_file.read_text()) if c["iteration"] <= trainer.step]
        eval_time = [0.0]

        def checkpoint(tr, step: int) -> None:
            t0 = time.perf_counter()
            app = evaluate_views(model_renderer(tr), self.ds.test, psnr_only=True)
            geo, _ = evaluate_geometry(model_gaussians(tr), self.truth, ecfg)
            curve[:] = [c for c in curve if c["iteration"] != step]
            curve.append({"iteration": step, "time_s": tr.elapsed, "cpu_s": tr.cpu_elapsed,
                          "num_gaussians": tr.num_gaussians, "psnr_refr": (app["refr"] or {}).get("psnr"),
                          "psnr_dry": (app["dry"] or {}).get("psnr"), "f1": geo["f1"],
                          "chamfer": geo["chamfer"]})
            # the fused bed only at the end: rendering 87 depth maps and fusing them costs ~100 s a point
            write_json(curve_file, jsonable(curve), indent=1)
            eval_time[0] += time.perf_counter() - t0

        sched = cfg.schedule
        steps = eval_steps(cfg.iterations, checkpoints, sched.reset_every, sched.refine_stop_iter)
        if trainer.step == 0:
            checkpoint(trainer, 0)
        bar, on_step = (None, None) if self.training_bar is None else \
            self.training_bar(cfg.iterations, cfg.variant, trainer.step)
        try:
            stats = trainer.train(callbacks=[checkpoint], on_step=on_step, eval_steps=steps)
        finally:
            if bar is not None:
                bar.close()
        t0 = time.perf_counter()
        if lpips_metric is not None:
            lpips_metric.to(trainer.device)
        appearance = evaluate_views(model_renderer(trainer), self.ds.test, lpips_metric)
        t1 = time.perf_counter()
        geometry, grid = evaluate_geometry(model_gaussians(trainer), self.truth, ecfg)
        t2 = time.perf_counter()
        fused_geometry, fused = evaluate_fused(model_depth(trainer), self.ds.train, self.truth, fcfg,
                                               ecfg.cell)
        t3 = time.perf_counter()
        row = {"config": cfg.to_dict(), "train_stats": stats, "num_gaussians": stats["num_gaussians"],
               "time": {"wall_s": stats["train_seconds"], "cpu_s": stats["train_cpu_seconds"],
                        "median_step_s": stats["median_step_seconds"]},
               "appearance": appearance, "geometry": geometry, "geometry_fused": fused_geometry,
               "curve": sorted(curve, key=lambda c: c["iteration"]),
               "timings": {"checkpoint_eval_s": eval_time[0], "appearance_eval_s": t1 - t0,
                           "geometry_eval_s": t2 - t1, "fused_eval_s": t3 - t2},
               "outputs": {"dir": str(out), "ply": str(out / "point_cloud.ply")}}
        return row, grid, fused

