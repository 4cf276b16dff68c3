"""How well a survey's frame and water level came out against the synthetic truth, as a consumer-GPS survey
is judged: its cameras (RUN/model, after the adjustment through the water) fitted to the true ones by a
similarity, whose tilt (degrees), scale error and remaining centre error say what the positions left wrong;
and the estimated surface (RUN/water.json) carried through that similarity against the true one: the
level under the flight's middle, the slope (dz/dx, dz/dy) and the surface's height over the true wet area
(gt/bed_grid's points): the errors that the depths take; and the depths' common offset, the estimated
level less the model's submerged points (carried alike) against the true depth at theirs, which is what
the level's sigma relative to the bed (water.json's sigma_to_bed_m) states. The absolute offset of a
consumer GPS frame (metres) is left out: it moves the bed and the water alike.

    python -m tools.frame_error RUN DATA          # DATA: the dataset (or its stretch) the photos came from
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np


def frame_error(run: Path, truth: Path) -> dict:
    import pycolmap
    from scipy.spatial import cKDTree

    from ragsplat.dataset.load import load_dataset
    from ragsplat.eval.score_file import survey_geotags
    from ragsplat.survey.georef import fit_similarity

    views = load_dataset(truth, splits=("train",), load_dry=False)
    cams = {Path(v.file_path).stem: v.camera for v in views.train}
    rec = pycolmap.Reconstruction(str(run / "model"))
    geotags = survey_geotags(truth)
    offset = np.asarray(geotags.offset) if geotags is not None else np.zeros(3)
    names = [rec.images[i].name for i in rec.reg_image_ids() if Path(rec.images[i].name).stem in cams]
    model = np.array([rec.images[i].projection_center() for i in rec.reg_image_ids()
                      if Path(rec.images[i].name).stem in cams]) - offset
    true = np.array([cams[Path(n).stem].camera_center for n in names])
    fit = fit_similarity(model, true)
    fitted = fit.apply(model)
    tilt = float(np.degrees(np.arccos(np.clip(fit.R[2, 2], -1, 1))))
    water = json.loads((run / "water.json").read_text())["surface"]
    slope = np.asarray(water.get("slope", [0.0, 0.0]), float)  # the CRS's: level at CRS x = y = 0
    middle = model[:, :2].mean(0)
    level = float(water["level"]) + slope @ (middle + offset[:2]) - offset[2]
    centre = np.array([*middle, level])  # the surface under the flight's middle
    scene = json.loads((truth / "scene.json").read_text())
    w = scene["water"]
    at = fit.apply(centre[None])[0]
    true_slope = np.asarray(w.get("slope", [0.0, 0.0]), float)
    true_level = w["level"] + true_slope @ at[:2]
    normal = fit.R @ np.array([-slope[0], -slope[1], 1.0])  # the surface's normal carried to the truth
    carried = -normal[:2] / normal[2]
    bed = np.load(truth / "gt" / "bed_grid.npy")
    wet = bed[:, :2]
    off = np.abs(at[2] + (wet - at[:2]) @ carried - (w["level"] + wet @ true_slope))
    points = fit.apply(np.array([p.xyz for p in rec.points3D.values()]) - offset)
    surface = at[2] + (points[:, :2] - at[:2]) @ carried  # the estimated surface over each point
    dist, near = cKDTree(wet).query(points[:, :2])
    true_depth = w["level"] + points[:, :2] @ true_slope - bed[near, 2]
    # wet by the truth, a waterline's width in: selected by the estimated surface, the shallow points
    # below it would be those whose noise put them deep
    sub = (dist < 0.1) & (true_depth > 0.1)
    offset_of = (surface - points[:, 2]) - true_depth  # the estimated depth less the true one
    bank = np.load(truth / "gt" / "bank_grid.npy")
    dist_dry, near_dry = cKDTree(bank[:, :2]).query(points[:, :2])
    dry = (dist_dry < 0.05) & (dist >= 0.1)
    bands = [0.1, 0.5, 1.0, 2.0, np.inf]
    in_band = {f"{lo:g}-{hi:g} m": sub & (true_depth >= lo) & (true_depth < hi)
               for lo, hi in itertools.pairwise(bands)}
    by_band = {name: float(offset_of[s].mean()) for name, s in in_band.items() if s.any()}
    wet_less_bed = float((points[sub, 2] - bed[near[sub], 2]).mean())
    dry_less_bank = float((points[dry, 2] - bank[near_dry[dry], 2]).mean())
    return {"photos": len(names), "tilt_deg": tilt, "scale_error": fit.scale - 1.0,
            "centre_rms_after_similarity_m": float(np.sqrt(((fitted - true) ** 2).sum(1).mean())),
            "centre_median_m": float(np.median(np.linalg.norm(model - true, axis=1))),
            "level_error_m": float(at[2] - true_level),
            "slope_error": (carried - true_slope).tolist(),
            "surface_error_over_the_wet_area_m": {"median": float(np.median(off)),
                                                  "p95": float(np.percentile(off, 95)),
                                                  "max": float(off.max())},
            "depth_offset_m": {"points": int(sub.sum()), "mean": float(offset_of[sub].mean()),
                               "median": float(np.median(offset_of[sub])), "by_true_depth": by_band,
                               "submerged_points_less_the_bed": wet_less_bed,
                               "dry_points_less_the_bank": dry_less_bank}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("data", type=Path)
    args = parser.parse_args()
    print(json.dumps(frame_error(args.run, args.data), indent=1))


if __name__ == "__main__":
    main()
