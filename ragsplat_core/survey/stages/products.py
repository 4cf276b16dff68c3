"""Stage 5, the products of a trained survey (`export`: the DEM, the LAZ, the depth map, the
orthophotos), with the TVU95 band where an uncertainty model is given.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:

    from ragsplat.survey.stages.base import Progress, Stamps, SurveyConfig
    from ragsplat.survey.stages.water import Water

from ragsplat.outputs import digest
from ragsplat.survey.stages.water import level_sigma


def export(cfg: SurveyConfig, water: Water, trained: Path, products: list[Path], stamps: Stamps,
           progress: Progress) -> None:
    """The products of the training in `trained` (`export.export_run`, with the TVU95 band where
    `cfg.uncertainty` names a model), kept while its checkpoint, the uncertainty's settings and the culls
    are."""
    band = uncertainty_settings(cfg)
    key = bed_key(digest(water.key, (trained / "point_cloud.ply").stat().st_mtime_ns, cfg.resolution), band,
                   cfg.culls)
    t0 = time.perf_counter()
    if not stamps.done("export", key, *products):
        from ragsplat.export import export_run, run_orthophotos

        dem, las, png, ortho, apparent = products
        b, on_block = progress.count("[export] bed", "block")
        with b:
            bed = export_run(trained, dem, cfg.resolution, las, None, png, on_block=on_block,
                             **uncertainty_kwargs(band), **cfg.culls)
        progress.say("export", f"{len(bed.grid)} cells of {cfg.resolution:g} m{tvu_words(bed)}", t0)
        t1 = time.perf_counter()
        grid = run_orthophotos(trained, bed, ortho, apparent)
        stamps.mark("export", key)
        progress.say("ortho", f"the bed without the water and the photos' mosaic, {grid.width} x "
                     f"{grid.height} cells", t1)


def uncertainty_settings(cfg: SurveyConfig) -> dict | None:
    """What the TVU95 band is made with (None: no band): the model (its JSON), the level's standard deviation
    (`cfg.level_sigma`, else the adjustment's where it estimated the level, RUN/water.json, as the water
    stage reports it; else 0: a given level is taken as exact) and n's (`cfg.n_sigma`)."""
    if cfg.uncertainty is None:
        return None
    from ragsplat.export import read_uncertainty

    level = cfg.level_sigma
    if level is None:
        check = json.loads((cfg.out / "water.json").read_text())
        est = check.get("estimated")
        level = 0.0 if est is None else level_sigma(est)[0]
    return {"model": read_uncertainty(cfg.uncertainty).to_json(), "level_sigma": level,
            "n_sigma": float(cfg.n_sigma)}


def uncertainty_kwargs(band: dict | None) -> dict:  # `export_run`'s arguments for the band
    if band is None:
        return {}
    from ragsplat.uncertainty import UncertaintyModel

    return {"uncertainty": UncertaintyModel.from_json(band["model"]), "level_sigma": band["level_sigma"],
            "n_sigma": band["n_sigma"]}


def tvu_words(bed) -> str:
    if bed.tvu95 is None:
        return ""
    import numpy as np

    return f"; TVU95 (band 3) median {100 * float(np.median(bed.tvu95)):.1f} cm"


def bed_key(key: str, band: dict | None, culls: dict) -> str:
    """The key of a bed extracted from the trainings of `key`: the uncertainty's settings and the culls
    added where given (a rerun with other culls extracts again without training again)."""
    extra = [*([] if band is None else [band]), *([culls] if culls else [])]
    return digest(key, *extra) if extra else key
