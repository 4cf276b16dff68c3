"""How far a survey's recovered poses (a COLMAP model in the dataset's frame, e.g. `ragsplat survey`'s
RUN/model or RUN/sfm/model) are from the synthetic truth: camera centre (m) and rotation (degrees) per
image, matched by file name stem, with medians and 95th percentiles overall and by the view's tilt."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ragsplat.errors import DatasetError

TILT_BANDS = ((0, 10), (10, 30), (30, 50), (50, 90))  # degrees of the true optical axis from the vertical


def pose_errors(model: Path, truth: Path, similarity: dict | None = None) -> dict:
    """{"per_image": {name: {"centre_m", "rotation_deg", "tilt_deg"}}, "centre_m", "rotation_deg": {"median",
    "p95"}, "by_tilt": {band: {...}}} for the registered images of `model` against the cameras of the dataset
    `truth`; `similarity` ({"scale", "R", "t"}, georef.json) first maps a model that is not yet in the
    frame."""
    import pycolmap

    from ragsplat.dataset.load import load_dataset
    from ragsplat.eval.score_file import survey_geotags

    views = load_dataset(truth, splits=("train", "test"), load_dry=False)
    cams = {Path(v.file_path).stem: v.camera for v in [*views.train, *views.test]}
    rec = pycolmap.Reconstruction(str(model))
    # a survey run from the synthetic photos' geotags is in their CRS: the scene's frame plus origin_metric
    geotags = survey_geotags(truth)
    centres = np.array([rec.images[i].projection_center() for i in rec.reg_image_ids()]).reshape(-1, 3)
    far = geotags is not None and similarity is None and len(centres) and np.abs(centres[:, :2]).min() > 1e4
    offset = np.asarray(geotags.offset) if far else np.zeros(3)
    per = {}
    for i in rec.reg_image_ids():
        im = rec.images[i]
        cam = cams.get(Path(im.name).stem)
        if cam is None:
            continue
        R, C = im.cam_from_world().rotation.matrix(), im.projection_center() - offset
        if similarity is not None:
            S = np.asarray(similarity["R"])
            R, C = R @ S.T, similarity["scale"] * S @ C + np.asarray(similarity["t"])
        M = R @ cam.R.T
        per[im.name] = {"centre_m": float(np.linalg.norm(C - cam.camera_center)),
                        "rotation_deg": float(np.degrees(np.arccos(np.clip((np.trace(M) - 1) / 2, -1, 1)))),
                        "tilt_deg": float(np.degrees(np.arccos(np.clip(-cam.R[2, 2], -1, 1))))}
    if not per:
        raise DatasetError(f"{model}: no image named like a view of {truth}")

    def stats(rows):
        out = {"images": len(rows)}
        for key in ("centre_m", "rotation_deg"):
            vals = np.array([r[key] for r in rows])
            out[key] = ({"median": float(np.median(vals)), "p95": float(np.percentile(vals, 95))}
                        if len(vals) else None)
        return out

    rows = list(per.values())
    return {**stats(rows), "per_image": per,
            "by_tilt": {f"{lo}-{hi}": stats([r for r in rows if lo <= r["tilt_deg"] < hi])
                        for lo, hi in TILT_BANDS
                        if any(lo <= r["tilt_deg"] < hi for r in rows)}}


def summary(errors: dict) -> str:
    """One line: centre and rotation error, median / p95."""
    c, r = errors["centre_m"], errors["rotation_deg"]
    return (f"{errors['images']} images: centre {100 * c['median']:.2f} / {100 * c['p95']:.2f} cm, rotation "
            f"{r['median']:.3f} / {r['p95']:.3f} deg (median / p95)")
