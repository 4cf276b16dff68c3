"""Stage 1, structure from motion (`structure_from_motion`, `survey.sfm`) -> RUN/sfm/.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import pycolmap

    from ragsplat.survey.stages.base import Progress, Stamps
    from ragsplat.survey.stages.inputs import Survey

from ragsplat.outputs import digest
from ragsplat.survey.stages.base import fresh_folder


@dataclass(frozen=True)
class Structure:
    """Stage 1's model (RUN/sfm/model) and the key it was made with."""

    key: str
    rec: pycolmap.Reconstruction


def structure_from_motion(survey: Survey, stamps: Stamps, progress: Progress) -> Structure:
    """Stage 1: the photos' model by pycolmap (`survey.sfm`) in RUN/sfm/, every pair matched, or each photo
    with its nearest where the survey is large and every photo has a position; kept while the photos are the
    same."""
    import numpy as np
    import pycolmap

    from ragsplat.dataset import layout
    from ragsplat.outputs import write_json
    from ragsplat.survey import sfm

    cfg, photos, names, positions = survey.cfg, survey.photos, survey.names, survey.where.positions
    key = digest({p.name: layout.file_digest(p) for p in photos}, sfm.CAMERA_MODEL, sfm.FEATURE_MAX_SIZE,
                 sfm.DOUBLED_MAX)
    work = cfg.out / "sfm"
    t0 = time.perf_counter()
    if not stamps.done("sfm", key, work / "model"):
        pairs = None
        if len(names) > sfm.EXHAUSTIVE_MAX and (positions is not None and all(n in positions for n in names)):
            pairs = sfm.neighbour_pairs(np.array([positions[n] for n in names]), sfm.NEIGHBOURS)
        how = ("every pair matched" if pairs is None
               else f"each photo matched with its {sfm.NEIGHBOURS} nearest")
        progress.say("sfm", f"structure from motion of {len(photos)} photos (pycolmap SIFT, {how}, "
                     "incremental mapping; CPU) ...")
        timings = {}
        rec = sfm.reconstruct(cfg.images, names, work, pairs=pairs, timings=timings,
                              progress=lambda desc, total, unit: progress.bar(total, f"[sfm] {desc}", unit))
        rec.write_text(str(fresh_folder(work / "model")))
        write_json(work / "timings.json", timings)
        progress.say("sfm", f"features {timings['features_s']:.0f} s, {timings['pairs']} pairs matched in "
                     f"{timings['matching_s']:.0f} s, mapping {timings['mapping_s']:.0f} s")
        stamps.mark("sfm", key)
    rec = pycolmap.Reconstruction(str(work / "model"))
    progress.say("sfm", f"{rec.num_reg_images()} of {len(photos)} photos registered, {rec.num_points3D()} "
                 f"points, reprojection error {rec.compute_mean_reprojection_error():.2f} px", t0)
    return Structure(key, rec)
