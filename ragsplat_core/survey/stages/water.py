"""Stage 3, the water (`adjust_through_water`): the bundle adjustment with the submerged tracks
projected through the water, the level given or estimated (the shoreline where the photos leave it
poorly determined) -> RUN/model/, RUN/water.json.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np
    import torch

    from ragsplat.survey.bundle import Bundle
    from ragsplat.survey.stages.base import Progress, Stamps
    from ragsplat.survey.stages.georeference import Georeferenced
    from ragsplat.survey.stages.inputs import Positions, Survey
    from ragsplat.survey.stages.structure import Structure
    from ragsplat.water_surface import WaterSurface

from ragsplat.outputs import digest
from ragsplat.survey.stages.base import AUTO, fresh_folder, points_box
from ragsplat.survey.stages.inputs import describe_surface

# With the level free, points that cross it as it moves make the cost slightly rough: on `small` (seed 7) it
# settles within 0.01 mm in 6-9 iterations and then creeps on by 1e-7 relative per step, so stop at 1e-7.
LEVEL_TOL = 1e-7


# An estimated level less certain than this is said to be poorly determined: on a flat bed with no dry ground
# the level can move far for little cost while its linearised uncertainty reads a few centimetres; with banks
# and pools it reads millimetres and is right to them (docs/survey.md, stage 3).
LEVEL_WARN = 0.02


# A lens estimated from photos that all look within this of straight down (degrees), with no ground control,
# is said to be open to doming: in a parallel nadir network a radial distortion error and a curved frame
# reproject alike (James and Robson, 2014), and only oblique views or control separate them.
NADIR_ONLY_DEG = 10.0


# Such a level is looked for at the shoreline within 3 of its sigmas, at least this far (m).
SHORE_SPAN = 0.2


# In a frame the positions hold level, the water's plane is tried with its slope free too and kept where the
# slope stands this many of its standard deviations from level and is no steeper than a river falls (m/m):
# lowland rivers fall well under 1 %, a mountain stream's pools and riffles a few per cent on average.
FALL_SIGNIFICANT = 4.0
MAX_FALL = 0.03


@dataclass(frozen=True)
class Problem:
    """The adjustment through the water's unknowns and observations in the local frame: the georeferenced
    cameras and points (the targets after the points, with ground control), and what holds the frame."""

    R: torch.Tensor  # [I, 3, 3] world -> camera
    C: torch.Tensor  # [I, 3]
    points: torch.Tensor  # [P (+ G), 3]
    point: torch.Tensor  # [M] index into points
    image: torch.Tensor  # [M] index into the cameras
    pixels: torch.Tensor  # [M, 2]
    held: dict  # `bundle.adjust`'s priors: the cameras at their positions, or the targets at theirs
    gcp_rows: torch.Tensor | None = None  # [G] the targets' rows in points


@dataclass(frozen=True)
class Adjusted:
    """The cameras and points after the adjustment through the water (or as georeferenced, without it)."""

    R: torch.Tensor
    C: torch.Tensor
    points: torch.Tensor  # [P, 3] the tracks' points (the targets' rows dropped)
    water: WaterSurface  # in the local frame: as given, or as estimated (and levelled)
    surface: WaterSurface  # the same in the CRS
    bundle: Bundle | None  # None: --no-water-adjustment
    estimated: dict | None = None  # water.json's account of the estimated water
    lens: dict | None = None  # water.json's account of the lens's distortion (--lens radial)
    gcp_residual: dict | None = None  # target -> adjusted minus surveyed position (m), with ground control


@dataclass(frozen=True)
class Water:
    """Stage 3: the adjusted model (RUN/model), the water's surface (CRS) and the model's points' box."""

    key: str
    model: Path
    surface: WaterSurface
    extent: np.ndarray  # [2, 2] the points' 1 and 99 % in x, y (CRS)


def adjust_through_water(survey: Survey, structure: Structure, geo: Georeferenced, stamps: Stamps,
                         progress: Progress) -> Water:
    """Stage 3: the bundle adjustment through the water (`_adjust`), the cameras held at their positions or
    the targets at theirs, the water estimated where not given; the adjusted model in RUN/model/, the
    water's report in RUN/water.json (a new one makes the training's folders stale)."""
    import numpy as np
    import torch

    from ragsplat.dataset import layout
    from ragsplat.outputs import write_json
    from ragsplat.survey import sfm
    from ragsplat.water_surface import WaterSurface

    cfg, water = survey.cfg, survey.water
    held_by = list(survey.rtk_sigma) if survey.where.sigma is None else geo.given  # one accuracy, or each's
    key = digest(geo.key, layout.water_json(water) if water is not None else [AUTO, cfg.n],
                  cfg.no_water_adjustment, held_by, cfg.gcp_sigma, cfg.lens, survey.held_lens)
    model = cfg.out / "model"
    t0 = time.perf_counter()
    if not stamps.done("water", key, model, cfg.out / "water.json"):
        fit = _adjust(survey, geo, _problem(survey, geo), progress)
        check = _water_report(survey, fit)
        origin = torch.as_tensor(survey.origin)
        sfm.set_poses(structure.rec, geo.tracks, fit.R, fit.C + origin, fit.points + origin,
                      None if fit.lens is None else fit.bundle.lens)
        structure.rec.write_text(str(fresh_folder(model)))
        write_json(cfg.out / "water.json", check)
        for stale in ("data", "train"):  # made from the previous poses
            shutil.rmtree(cfg.out / stale, ignore_errors=True)
        stamps.mark("water", key)
    check = json.loads((cfg.out / "water.json").read_text())
    surface = WaterSurface(**{**check["surface"], "n": cfg.n})  # as given, or as estimated
    _say_water(progress, surface, check, t0)
    return Water(key, model, surface, np.asarray(check["extent_m"]))


def _problem(survey: Survey, geo: Georeferenced) -> Problem:
    """The tracks georeferenced, and held: each camera at its position (RTK centimetres, or as its source
    allows), or the targets, joined to the points with their observations, at their surveyed positions."""
    import numpy as np
    import torch

    trk, sim, pairs, where = geo.tracks, geo.sim, geo.pairs, survey.where
    R = trk.R @ torch.as_tensor(sim.R.T)  # world = s R x + t: cam_from_world' = cam_from_world R^T
    C = torch.as_tensor(sim.apply(trk.C.numpy()))
    P = torch.as_tensor(sim.apply(trk.points.numpy()))
    point, image, pix = trk.point, trk.image, trk.pixels
    if where.control is None:
        prior = torch.full_like(C, float("nan"))
        prior[pairs.have] = torch.as_tensor(pairs.dst)
        if where.sigma is None:
            sigma = (survey.rtk_sigma[0],) * 2 + (survey.rtk_sigma[1],)
            return Problem(R, C, P, point, image, pix, {"prior_C": prior, "prior_sigma": sigma})
        # each camera held as its source allows (RTK centimetres, consumer GPS metres)
        each = torch.ones_like(C)
        each[pairs.have] = torch.as_tensor(np.array([where.sigma[trk.names[k]][[0, 0, 1]]
                                                     for k in pairs.have]))
        return Problem(R, C, P, point, image, pix, {"prior_C": prior, "prior_sigma": each})
    gcp_rows = torch.arange(len(P), len(P) + len(pairs.usable))
    obs = [(row, k, uv) for row, n in zip(gcp_rows.tolist(), pairs.usable) for k, uv in pairs.gcp[n][1]]
    point = torch.cat([point, torch.tensor([o[0] for o in obs])])
    image = torch.cat([image, torch.tensor([o[1] for o in obs])])
    pix = torch.cat([pix, torch.as_tensor(np.array([o[2] for o in obs]))])
    P = torch.cat([P, torch.as_tensor(sim.apply(pairs.src))])
    held = {"prior_points": (gcp_rows, torch.as_tensor(pairs.dst)), "point_sigma": survey.cfg.gcp_sigma}
    return Problem(R, C, P, point, image, pix, held, gcp_rows)


def _adjust(survey: Survey, geo: Georeferenced, problem: Problem, progress: Progress) -> Adjusted:
    """`problem` adjusted through the water (`survey.bundle`), with the lens's distortion (--lens radial) and,
    where none is given, the water (`_estimate_water`); as it is with --no-water-adjustment."""
    import torch

    from ragsplat.survey import bundle

    cfg, trk = survey.cfg, geo.tracks
    water, surface, adj, estimated, lens_record = survey.water, survey.given.surface, None, None, None
    R, C, P = problem.R, problem.C, problem.points
    if not cfg.no_water_adjustment:
        progress.say("water", f"bundle adjustment through the water ({len(problem.point)} observations of "
                     f"{len(P)} points, {len(C)} cameras) ...")
        with progress.bar(30, "[water] adjustment", "iteration") as b:
            def step(cost):
                b.update(1)
                b.set_postfix(cost=f"{cost:.4g}", refresh=False)

            lens = ("lens",) if cfg.lens == "radial" else ()
            if water is None:  # the level too, from a start among the model's points
                adj, water, estimated = _estimate_water(survey, geo, problem, lens, step)
                surface = water.shifted(-survey.origin)
            else:
                adj = bundle.adjust(R, C, trk.intrinsics, P, problem.point, problem.image, problem.pixels,
                                    water, free=lens, tol=LEVEL_TOL if lens else 1e-9, on_iteration=step,
                                    lens=survey.lens, **problem.held)
            if lens or survey.held_lens:
                lens_record = {"model": "RADIAL (COLMAP): x (1 + k1 r^2 + k2 r^4), normalised coordinates",
                               "k1": adj.lens[0], "k2": adj.lens[1]}
            if lens:
                lens_record["sigma"] = {k: adj.sigma[k] for k in ("k1", "k2")}
                off = _off_nadir_deg(adj.R)
                if off < NADIR_ONLY_DEG and problem.gcp_rows is None:
                    lens_record["nadir_only"] = {"off_nadir_max_deg": off}
            elif survey.held_lens:
                lens_record["held"] = cfg.lens
        R, C, P = adj.R, adj.C, adj.points
    gcp_residual = None
    if problem.gcp_rows is not None:
        dst = geo.pairs.dst
        gcp_residual = {n: (P[r] - torch.as_tensor(dst[k])).tolist() for k, (n, r) in
                        enumerate(zip(geo.pairs.usable, problem.gcp_rows.tolist()))}
        P = P[: len(trk.points)]
    return Adjusted(R, C, P, water, surface, adj, estimated, lens_record, gcp_residual)


def _estimate_water(survey: Survey, geo: Georeferenced, problem: Problem, lens: tuple[str, ...],
                    step) -> tuple[Bundle, WaterSurface, dict]:
    """(the adjustment, the water (local frame), water.json's account of it) with the level free, started
    among the model's points; where the positions fix no tilt (consumer GPS) the slope too, and then the
    frame levelled by the water's plane, unless that plane tilts more than the positions' heights leave open
    (`georef.tilt_allowed`): then the level alone, the frame as the positions hold it. Where they hold it,
    to centimetres, the water's fall as well where the photos show one (`_with_fall`)."""
    import torch

    from ragsplat.survey import bundle, georef
    from ragsplat.survey import water as water_fit
    from ragsplat.water_surface import WaterSurface

    cfg, trk, origin, P = survey.cfg, geo.tracks, survey.origin, problem.points
    start = water_fit.start_level(P[: len(trk.points)].numpy())
    # positions that fix no tilt (consumer GPS heights): the water's slope too, then the frame levelled by it
    free = ("level",) if survey.where.holds_tilt else ("level", "slope")

    def adjusted(free: tuple[str, ...], level: float = start) -> Bundle:
        return bundle.adjust(problem.R, problem.C, trk.intrinsics, P, problem.point, problem.image,
                             problem.pixels, WaterSurface(level, cfg.n), free=free + lens, tol=LEVEL_TOL,
                             on_iteration=step, lens=survey.lens, **problem.held)

    adj = adjusted(free)
    estimated = {"free": list(free), "start_m": start + origin[2], **_sigmas(adj),
                 "frame": "consumer GPS (metres)" if "slope" in free else _frame_holder(survey.where),
                 # the frame's height a consumer drone's, to metres: the level matters relative to the model
                 "relative_level": survey.where.tagged is not None and not survey.where.rtk_fixed}
    water = adj.water
    if water.tilted:  # the frame levelled by the water's plane, unless the positions' heights forbid the turn
        allowed = _tilt_left_open(problem)
        if math.hypot(*water.slope) > allowed:
            estimated["slope_refused"] = {"slope": list(water.slope), "allowed": allowed}
            adj = adjusted(("level",))
            estimated.update(free=["level"], **_sigmas(adj))
            return _by_shoreline(P[: len(trk.points)].numpy(), cfg.n, adj, estimated, adjusted)
        level = georef.levelling(water)
        adj = replace(adj, R=adj.R @ torch.as_tensor(level.R.T), C=torch.as_tensor(level.apply(adj.C)),
                      points=torch.as_tensor(level.apply(adj.points)))
        estimated["levelled_deg"] = math.degrees(math.atan(math.hypot(*water.slope)))
        estimated["slope_before_levelling"] = list(water.slope)
        water = WaterSurface(water.level, cfg.n)
        return adj, water, estimated
    if not estimated["relative_level"]:  # a frame held to centimetres: RTK, ground control, given positions
        falling = _with_fall(adjusted, estimated, _tilt_left_open(problem))
        if falling is not None:
            return falling, falling.water, estimated
    return _by_shoreline(P[: len(trk.points)].numpy(), cfg.n, adj, estimated, adjusted)


def _tilt_left_open(problem: Problem) -> float:
    """The frame's tilt (rise over run) that what holds it leaves open (`georef.tilt_allowed`): the cameras'
    heights at their accuracy, or the targets' at theirs."""
    import numpy as np
    import torch

    from ragsplat.survey import georef

    held = problem.held
    if "prior_C" not in held:
        rows, xyz = held["prior_points"]
        return georef.tilt_allowed(xyz[:, :2].numpy(), np.full(len(rows), held["point_sigma"]))
    known = ~torch.isnan(held["prior_C"][:, 0])
    sigma = torch.as_tensor(held["prior_sigma"], dtype=held["prior_C"].dtype).expand_as(held["prior_C"])
    return georef.tilt_allowed(held["prior_C"][known, :2].numpy(), sigma[known, 2].numpy())


def _sigmas(adj: Bundle) -> dict:
    """water.json's standard deviations of the adjustment `adj`'s water (the lens's go to "lens"): its own,
    with the cameras held, and the level's relative to the submerged points (the depths' common offset)."""
    def of_water(sigma):
        return {k: v for k, v in sigma.items() if k not in ("k1", "k2")}

    return {"sigma_m": of_water(adj.sigma), "sigma_given_cameras_m": of_water(adj.sigma_given_cameras),
            "sigma_to_bed_m": adj.sigma_level_to_bed}


def _with_fall(adjusted, estimated: dict, allowed: float) -> Bundle | None:
    """In a frame the positions hold level to centimetres, the adjustment again with the water's slope free
    (`adjusted(free)`): kept, the frame as it is and the water a plane falling in it, where the slope stands
    FALL_SIGNIFICANT standard deviations from level (each component by its own), more than the positions
    leave the frame's tilt open (`allowed`: else the plane may be the frame's own tilt) and no more than
    MAX_FALL; else None, the level alone. `estimated` records the trial either way. In a frame held by a
    barometer the slope would follow its drift between flight lines; there level water holds the tilt
    better, and a river's fall is levelled out of the frame with it."""
    fit = adjusted(("level", "slope"))
    slope = fit.water.slope
    spread = (fit.sigma["slope_x"], fit.sigma["slope_y"])
    trial = {"slope": list(slope), "sigma": list(spread),
             "standard_deviations": math.hypot(slope[0] / spread[0], slope[1] / spread[1]),
             "tilt_left_open": allowed, "kept": False}
    fall = math.hypot(*slope)
    if trial["standard_deviations"] < FALL_SIGNIFICANT or not allowed < fall <= MAX_FALL:
        estimated["fall"] = trial
        return None
    estimated.update(free=["level", "slope"], fall={**trial, "kept": True}, **_sigmas(fit))
    return fit


def _by_shoreline(pinhole: np.ndarray, n: float, adj: Bundle, estimated: dict,
                  adjusted) -> tuple[Bundle, WaterSurface, dict]:
    """The adjustment's level, or, where it is poorly determined and the model's points [P, 3] (pinhole,
    the frame held level by the positions) find the shoreline more surely (`water.shoreline_level`), the
    adjustment again (`adjusted(free, level)`) with the level held at the shoreline's; `estimated` says
    which."""
    from ragsplat.survey import water as water_fit

    sigma = level_sigma(estimated)[0]
    if sigma <= LEVEL_WARN:
        return adj, adj.water, estimated
    shore = water_fit.shoreline_level(pinhole, n, adj.water.level, min(max(3 * sigma, SHORE_SPAN), 1.0))
    if shore is None or shore.sigma >= sigma:
        estimated["shoreline"] = None if shore is None else shore.report()
        return adj, adj.water, estimated
    from_photos = {"level": adj.water.level, "sigma_m": sigma}
    adj = adjusted((), shore.level)
    estimated.update(by="shoreline", shoreline=shore.report(), adjustment=from_photos,
                     sigma_m={"level": shore.sigma}, sigma_given_cameras_m={"level": shore.sigma},
                     sigma_to_bed_m=shore.sigma)
    return adj, adj.water, estimated


def level_sigma(est: dict) -> tuple[float, bool]:
    """(the estimated level's standard deviation that the depths feel, whether it is relative to the model)
    from water.json's "estimated": in a frame whose height is a consumer drone's (GPS or barometer, held to
    metres), the level's relative to the submerged points, the depths' common offset (a record without it:
    the level's with the cameras held); else its own. A record without "relative_level" is one whose frame
    was consumer GPS exactly when the slope was free."""
    relative = est.get("relative_level", "slope" in est["free"])
    if not relative:
        return float(est["sigma_m"]["level"]), False
    to_bed = est.get("sigma_to_bed_m")
    return float(est["sigma_given_cameras_m"]["level"] if to_bed is None else to_bed), True


def _frame_holder(where: Positions) -> str:
    """What holds the frame's tilt, in words (the positions hold it)."""
    if where.tagged is not None and not where.rtk_fixed:
        return "held by the barometer's heights (decimetres)"
    return "held by the positions"


def _say_lens(lens: dict) -> str:
    said = (f"; the lens's distortion k1 {lens['k1']:+.4f}, k2 {lens['k2']:+.4f}"
            + (f", held from {lens['held']}" if "held" in lens else ""))
    if "nadir_only" in lens:
        off = lens["nadir_only"]["off_nadir_max_deg"]
        said += (f" (estimated from photos within {off:.1f} degrees of nadir and no ground control, where "
                 "a lens's distortion and a dome in the frame trade: fly obliques, give ground control, or "
                 "hold a lens calibrated before with --lens WATER.json of such a flight, or --lens pinhole "
                 "for photos without distortion)")
    return said


def _off_nadir_deg(R) -> float:
    """The largest angle (degrees) between a camera's optical axis and straight down, over cameras
    R [I, 3, 3] (cam_from_world)."""
    down = -R[:, 2, 2]  # the cosine of each: the optical axis is R^T e_z, its z component R[:, 2, 2]
    return math.degrees(math.acos(max(-1.0, min(1.0, float(down.min())))))


def _water_report(survey: Survey, fit: Adjusted) -> dict:
    """RUN/water.json: the surface, how the points lie around it, the adjustment's fit, and the estimated
    water, lens and targets' residuals where there are."""
    import numpy as np

    from ragsplat.dataset import layout
    from ragsplat.survey import water as water_fit

    given, origin, adj, P = survey.given, survey.origin, fit.bundle, fit.points
    z = -fit.water.depth(P.numpy())  # height above the surface
    above = z[z >= 0]
    extent = points_box(P.numpy()) + origin[:2]
    return {"surface": layout.water_json(fit.surface),
            "described": describe_surface(fit.surface, extent.mean(0)),
            **({} if fit.estimated is None else {"estimated": fit.estimated}),
            **({} if fit.lens is None else {"lens": fit.lens}),
            **({} if given.edge is None else {
                "edge_fit": given.edge.report(),
                "along_the_reach": water_fit.profile(P.numpy(), fit.water.height(P.numpy()[:, :2]),
                                                     given.edge_points - origin)}),
            "extent_m": extent.tolist(),
            "points_above": int((z >= 0).sum()),
            "points_below": int((z < 0).sum()),
            "lowest_above_m": float(np.percentile(above, 1)) if len(above) else None,
            "adjusted": adj is not None,
            "rms_px": None if adj is None else float(adj.residuals.pow(2).mean().sqrt()),
            "iterations": None if adj is None else adj.iterations,
            **({} if fit.gcp_residual is None else {"gcp_residual_m": fit.gcp_residual})}


def _level_here(surface: WaterSurface, check: dict) -> float:
    """The surface's height at the centre of the model's points (CRS)."""
    import numpy as np

    return float(surface.height(np.asarray(check["extent_m"]).mean(0)))


def _say_fall(fall: dict | None) -> str:
    """The water's fall in words: kept, refused as steeper than water falls, or nothing where the photos
    show none."""
    if fall is None or (not fall["kept"] and fall["standard_deviations"] < FALL_SIGNIFICANT):
        return ""
    sx, sy = fall["slope"]
    fall_, (ex, ey) = math.hypot(sx, sy), fall["sigma"]
    per_cent, sigma = 100 * fall_, 100 * math.hypot(sx * ex, sy * ey) / fall_  # along the fall
    if not fall["kept"]:
        open_ = 100 * fall["tilt_left_open"]
        why = (f"steeper than water falls ({100 * MAX_FALL:g} %)" if fall_ > MAX_FALL else
               f"but the positions' heights leave the frame's tilt open to {open_:.2f} % (for a river's "
               "fall: RTK geotags, ground control or --water-surface EDGE.csv)")
        return f"; a plane falling {per_cent:.2f} % fits better, {why}: the level alone"
    bearing = math.degrees(math.atan2(-sx, -sy)) % 360  # downhill, clockwise from north (+y)
    return (f"; the water falls {per_cent:.3f} % (+- {sigma:.3f}) towards {bearing:.0f} degrees from north, "
            "the frame held by the positions")


def _say_water(progress: Progress, surface: WaterSurface, check: dict, t0: float) -> None:
    """Stage 3's lines: the estimated level and its uncertainty, the points around the surface, the fit."""
    if "estimated" in check:  # in a frame held only to metres, its uncertainty relative to the bed matters
        est = check["estimated"]
        sigma, relative = level_sigma(est)
        shore = est.get("by") == "shoreline"
        progress.say("water", ("the level from the shoreline, where the model's ground bends into the water "
                               f"({est['shoreline']['straddling']} places)" if shore
                               else "the level estimated from the photos")
                     + f": {_level_here(surface, check):.3f} m"
                     + (" at the survey's centre" if surface.tilted else "")
                     + f" +- {100 * sigma:.1f} cm (1 sigma"
                     + ("" if not relative
                        else ", relative to the bed; the frame's height is the GPS's")
                     + ")"
                     + ("" if "levelled_deg" not in est else
                        f"; the frame levelled by the water's plane, {est['levelled_deg']:.2f} degrees")
                     + ("" if "slope_refused" not in est else
                        "; not levelled by the water's plane, tilted "
                        f"{math.degrees(math.atan(math.hypot(*est['slope_refused']['slope']))):.2f} degrees, "
                        "more than the positions' heights leave open ("
                        f"{math.degrees(math.atan(est['slope_refused']['allowed'])):.2f}): give photos with "
                        "the drone's barometric heights, ground control or --water-surface EDGE.csv")
                     + _say_fall(est.get("fall"))
                     + ("" if not shore else "; through the water alone "
                        f"{100 * est['adjustment']['sigma_m']:.1f} cm")
                     + ("" if sigma <= LEVEL_WARN else "; poorly determined (a flat bed, little depth "
                        "variation or no oblique views hide it"
                        + (", and no shoreline was found" if est.get("shoreline") is None else "")
                        + "): measure it and give --water-level, or --water-surface EDGE.csv"))
    lowest = check["lowest_above_m"]
    progress.say("water", f"{check['described']}: {check['points_below']} points below it, "
                 f"{check['points_above']} above"
                 + ("" if lowest is None else f" (the lowest 1 % within {100 * lowest:.1f} cm of it)")
                 + ("" if check["rms_px"] is None
                    else f"; reprojection error {check['rms_px']:.2f} px after the adjustment")
                 + ("" if "lens" not in check else _say_lens(check["lens"])), t0)
