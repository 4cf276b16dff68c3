"""Stage 2, georeferencing (`georeference`): the similarity that takes the model to the
positions or the ground control points (`survey.georef`) -> RUN/georef.json.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

    from ragsplat.survey.georef import Similarity
    from ragsplat.survey.sfm import Tracks
    from ragsplat.survey.stages.base import Progress, Stamps
    from ragsplat.survey.stages.inputs import Survey
    from ragsplat.survey.stages.structure import Structure

from ragsplat.outputs import digest
from ragsplat.survey.stages.inputs import check_above


@dataclass(frozen=True)
class Correspondences:
    """The model's camera centres, or its triangulated targets, paired with their known positions."""

    src: np.ndarray  # [K, 3] in the model's frame
    dst: np.ndarray  # [K, 3] known, in the local frame
    labels: list[str]  # the photos' or the targets' names
    what: str  # in words
    tol: float | np.ndarray  # 10 sigma of each position (one for all, or [K])
    noise: dict  # georef.json's account of the positions' noise
    have: list[int] | None = None  # the tracks' cameras with a position (positions)
    rtk: np.ndarray | None = None  # [K] bool: RTK fixed (positions from the photos)
    gcp: dict | None = None  # target -> (model xyz, observations) (ground control)
    usable: list[str] | None = None  # the targets placed in the model (ground control)


@dataclass(frozen=True)
class Georeferenced:
    """Stage 2: the similarity from the model to the local frame, and what it was fitted to."""

    key: str
    given: str  # the positions' fingerprint (with their accuracy, where each photo has its own)
    tracks: Tracks
    sim: Similarity
    pairs: Correspondences


def georeference(survey: Survey, structure: Structure, stamps: Stamps, progress: Progress) -> Georeferenced:
    """Stage 2: the similarity (RANSAC, `survey.georef`) that takes the model's camera centres to their
    positions, or its triangulated targets to their surveyed positions; its report in RUN/georef.json.
    DatasetError where too few correspond, or the cameras then do not look down."""
    import numpy as np

    from ragsplat.dataset import layout
    from ragsplat.errors import DatasetError
    from ragsplat.outputs import write_json
    from ragsplat.survey import georef, sfm

    cfg, where, names = survey.cfg, survey.where, survey.names
    given = layout.file_digest(where.source) if where.tagged is None else digest(
        {n: where.positions[n].tolist() for n in names}, {n: where.sigma[n].tolist() for n in names}, cfg.crs)
    key = digest(structure.key, given, None if where.control is None else layout.file_digest(cfg.gcp),
                  survey.origin.tolist())
    trk = sfm.tracks(structure.rec)
    if where.control is None:
        pairs = _camera_pairs(survey, trk)
    else:
        pairs = _control_pairs(survey, structure.rec, trk)
    threshold = np.maximum(0.2, pairs.tol)  # 10 sigma, at least 20 cm: only gross errors are left out
    sim, inliers = georef.ransac_similarity(pairs.src, pairs.dst, threshold=threshold)
    looks = (trk.R[:, 2, :].numpy() @ sim.R.T)[:, 2]  # the optical axes' z in the positions' frame
    if np.median(looks) > -0.2:
        raise DatasetError(f"{where.source}: after alignment the cameras do not look down (median optical "
                           f"axis z {np.median(looks):+.2f}): are the coordinates metres with z up?")
    if survey.water is not None:
        check_above(survey.water, sim.apply(trk.C.numpy()))
    report = _georef_report(survey, pairs, sim, inliers, threshold)
    write_json(cfg.out / "georef.json", report)
    progress.say("georef", f"similarity to {pairs.what}: scale {sim.scale:.4g}, {int(inliers.sum())} of "
                 f"{len(pairs.labels)} inliers, rms {100 * report['rms_m']:.1f} cm (each one's: "
                 f"{cfg.out / 'georef.json'})")
    if "scale_uncertainty" in report:
        scale = report["scale_uncertainty"]
        progress.say("georef", "the scale comes from consumer GPS: depths and heights may be off by up to "
                     f"about {100 * scale['relative']:.0f} % (rms {report['rms_m']:.2f} m over the flight's "
                     f"{scale['extent_m']:.0f} m); for depths to 1 %, give ground control (--gcp, "
                     "--gcp-pixels) or fly with RTK")
    stamps.mark("georef", key)
    return Georeferenced(key, given, trk, sim, pairs)


def _camera_pairs(survey: Survey, trk: Tracks) -> Correspondences:
    """The registered cameras' centres and their positions, each position's threshold from its source."""
    import numpy as np

    from ragsplat.errors import DatasetError

    where = survey.where
    have = [k for k, n in enumerate(trk.names) if n in where.positions]
    if len(have) < 3:
        raise DatasetError(f"{survey.cfg.positions}: only {len(have)} registered photos have a position; 3 "
                           "are needed")
    src = trk.C[have].numpy()
    dst = np.array([where.positions[trk.names[k]] for k in have]) - survey.origin
    labels = [trk.names[k] for k in have]
    if where.tagged is None:
        return Correspondences(src, dst, labels, f"{len(have)} RTK positions", 10 * survey.rtk_sigma[1],
                               {"model": "RTK", "sigma_m": list(survey.rtk_sigma)}, have)
    # the threshold follows each position's source: consumer GPS scatter is no outlier
    ours = np.array([where.sigma[n] for n in labels])
    is_fixed = {p.name: p.rtk_fixed for p in where.tagged}
    rtk = np.array([is_fixed[n] for n in labels])
    what = (f"{len(have)} positions from the photos ({int(rtk.sum())} RTK fixed, {int((~rtk).sum())} "
            "consumer GPS)")
    noise = _noise_model(where.tagged, where.sigma, labels)
    return Correspondences(src, dst, labels, what, 10 * ours.max(1), noise, have, rtk)


def _control_pairs(survey: Survey, rec, trk: Tracks) -> Correspondences:
    """The ground control points triangulated in the model from their pixels, and their surveyed positions."""
    import numpy as np

    from ragsplat.errors import DatasetError
    from ragsplat.survey import sfm

    cfg, control = survey.cfg, survey.where.control
    gcp = sfm.control_points(rec, trk, survey.where.pixels)  # name -> (model xyz, observations)
    usable = [n for n, (xyz, obs) in gcp.items() if np.isfinite(xyz).all()]
    if len(usable) < 3:
        seen = ", ".join(f"{n} ({len(gcp[n][1]) if n in gcp else 0} photos)" for n in sorted(control))
        raise DatasetError(f"{cfg.gcp_pixels}: only {len(usable)} ground control points are seen in 2 or "
                           f"more registered photos from different places; 3 are needed ({seen})")
    src = np.array([gcp[n][0] for n in usable])
    dst = np.array([control[n] for n in usable]) - survey.origin
    return Correspondences(src, dst, usable, f"{len(usable)} ground control points", 10 * cfg.gcp_sigma,
                           {"model": "ground control", "sigma_m": cfg.gcp_sigma}, gcp=gcp, usable=usable)


def _georef_report(survey: Survey, pairs: Correspondences, sim: Similarity, inliers: np.ndarray,
                   threshold) -> dict:
    """RUN/georef.json: the similarity, each correspondence's residual, the positions and their noise."""
    import numpy as np

    cfg, origin, tagged, sigma = survey.cfg, survey.origin, survey.where.tagged, survey.where.sigma
    res = sim.apply(pairs.src) - pairs.dst
    report = {"to": pairs.what, "scale": sim.scale, "R": sim.R.tolist(), "t": (sim.t + origin).tolist(),
              "origin": origin.tolist(), "inliers": int(inliers.sum()), "count": len(pairs.labels),
              "residual_m": {name: r.tolist() for name, r in zip(pairs.labels, res)},
              "rms_m": float(np.sqrt((res[inliers] ** 2).sum(1).mean())),
              "positions": {"source": "the photos' EXIF GPS and DJI XMP" if tagged is not None
                            else str(survey.where.source), "crs": cfg.crs},
              "noise": {**pairs.noise, "threshold_m": _rounded(threshold),
                        "fit": "similarity (7 parameters), RANSAC on 3 correspondences then refitted to the "
                        "inliers; a correspondence whose residual exceeds the threshold is an outlier"}}
    if tagged is not None:
        rtk = pairs.rtk
        report["positions"] |= {"heights": sorted({p.altitude_source for p in tagged}), "photos": {
            p.name: {"lat": p.lat, "lon": p.lon, "altitude": p.altitude, "rtk_flag": p.rtk_flag,
                     "sigma_m": sigma[p.name].tolist(), "gimbal_ypr_deg": p.gimbal} for p in tagged}}
        report["noise"]["rms_m_by_source"] = {
            kind: float(np.sqrt((res[inliers & pick] ** 2).sum(1).mean())) if (inliers & pick).any() else None
            for kind, pick in (("rtk_fixed", rtk), ("consumer_gps", ~rtk))}
        if (inliers & rtk).sum() < 3:  # the scale is consumer GPS's: say how far depths can be off
            extent = float(np.ptp(pairs.dst[inliers, :2], axis=0).max())
            report["scale_uncertainty"] = {
                "relative": report["rms_m"] / extent, "extent_m": extent,
                "from": "the positions' rms residual over the flight's longest horizontal side: consumer "
                        "GPS fixes the scale no better (its errors are shared along a flight line, so the "
                        "fit's own standard error would understate them); depths and heights are scaled with "
                        "it"}
    return report


def _noise_model(tagged, sigma: dict, labels: list[str]) -> dict:
    """georef.json's account of the noise model of positions from the photos (`dataset.exif.sigmas`)."""
    import numpy as np

    used = set(labels)
    fixed = [p.name for p in tagged if p.name in used and p.rtk_fixed]
    other = [p.name for p in tagged if p.name in used and not p.rtk_fixed]
    out = {"model": "by source: RTK fixed (DJI RtkFlag 50) to centimetres, anything else (no RTK flag, or a "
                    "single-point or float solution) as consumer GPS to metres"}
    if fixed:
        own = [p.std_horizontal is not None for p in tagged if p.name in fixed]
        out["rtk_fixed"] = {"count": len(fixed),
                            "sigma_m_median": np.median([sigma[n] for n in fixed], 0).tolist(),
                            "from": f"the photos' RtkStdLon / RtkStdLat / RtkStdHgt ({sum(own)} of "
                                    f"{len(fixed)})"
                                    if any(own) else "--rtk-sigma (or its 2 / 3 cm default)"}
    if other:
        out["consumer_gps"] = {
            "count": len(other), "sigma_m": sigma[other[0]].tolist(),
            "bias": "consumer GPS drifts by metres and each flight line can be 1-1.5 m off the others; no "
                    "per-line bias is estimated: the similarity is fitted to every position within the "
                    "threshold (10 sigma), so their scatter leaves no camera out, and a line's bias shows in "
                    "residual_m as residuals of one sign along it; the adjustment holds these cameras only "
                    "to metres (--gps-sigma), the photos decide their relative positions"}
    return out


def _rounded(threshold):
    """A threshold (one or per correspondence) for georef.json: one number when all are the same."""
    import numpy as np

    values = np.atleast_1d(np.asarray(threshold, float))
    return float(values[0]) if np.ptp(values) == 0 else [round(float(v), 4) for v in values]
