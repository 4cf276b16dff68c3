"""The survey's inputs, read and checked before any work (`check_inputs`): the photos, what fixes the
frame (positions, ground control, the photos' EXIF GPS), the water as given, and the sizes.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

    from ragsplat.dataset.exif import PhotoPosition
    from ragsplat.survey.stages.base import Progress, SurveyConfig
    from ragsplat.survey.water import EdgeFit
    from ragsplat.water_surface import WaterSurface

from ragsplat.survey.stages.base import AUTO, LENSES, RTK_SIGMA

IMAGE_MEMORY = 0.4  # the training's images (uint8) may take this share of the machine's memory


IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")


@dataclass(frozen=True)
class Positions:
    """What fixes the survey's frame: the cameras' positions (a file, or the photos' EXIF GPS and DJI XMP),
    or ground control points and where the photos see them."""

    source: Path  # the file (or, for EXIF, the photos' folder) that names the photos
    located: list[str]  # the photos it names (with a position, or seeing a target)
    positions: dict[str, np.ndarray] | None = None  # photo -> camera centre (CRS); None with ground control
    control: dict[str, np.ndarray] | None = None  # target -> surveyed position (CRS)
    pixels: list | None = None  # (photo, target, (u, v)): the targets in the photos
    tagged: list[PhotoPosition] | None = None  # the photos' GPS records, where the positions came from them
    sigma: dict[str, np.ndarray] | None = None  # photo -> (horizontal, vertical) sigma, from the photos

    @property
    def frame(self) -> dict[str, np.ndarray]:
        """The known positions: the cameras', else the targets'."""
        return self.positions or self.control

    @property
    def rtk_fixed(self) -> int:
        """How many photos' GPS is RTK fixed (positions from the photos)."""
        return sum(p.rtk_fixed for p in self.tagged)

    @property
    def holds_tilt(self) -> bool:
        """Whether the positions fix the frame's tilt: given, ground control, RTK, or heights from the
        barometer; consumer GPS heights alone (metres from photo to photo) do not."""
        return self.tagged is None or any(p.rtk_fixed or p.barometric for p in self.tagged)


@dataclass(frozen=True)
class GivenWater:
    """The water as the user gives it: one level, a surface fitted to its edge points, or none (estimated)."""

    surface: WaterSurface | None  # in the CRS; None: estimated in the adjustment through the water
    edge: EdgeFit | None = None  # the fit to the edge points (--water-surface)
    edge_points: np.ndarray | None = None  # [K, 3] those points (CRS)


@dataclass(frozen=True)
class Survey:
    """A survey's inputs, read and checked before any work."""

    cfg: SurveyConfig  # resolved: the CRS from the photos, the --max-size that fits
    given_size: int | None  # the --max-size asked for (None: the survey chooses, `training.training_size`)
    photos: list[Path]
    where: Positions
    given: GivenWater
    origin: np.ndarray  # [3] the local frame's origin in the CRS (whole metres)
    water: WaterSurface | None  # the given surface in the local frame
    held_lens: tuple[float, float] | None = None  # (k1, k2) calibrated before (--lens FILE), held

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.photos]

    @property
    def rtk_sigma(self) -> tuple[float, float]:
        return self.cfg.rtk_sigma or RTK_SIGMA

    @property
    def lens(self) -> tuple[float, float]:
        """(k1, k2) the adjustment holds the lens at, or starts its estimate from: none unless calibrated
        before."""
        return self.held_lens or (0.0, 0.0)


def check_inputs(cfg: SurveyConfig, progress: Progress) -> Survey:
    """Everything that can be refused, refused before any work: the photos, what fixes their frame
    (`locate`), the water as given, a camera above it, the sizes (`_check_sizes`); then the run folder
    claimed and RUN/survey.json written with the config resolved."""
    import numpy as np

    from ragsplat.errors import DatasetError
    from ragsplat.outputs import claim

    if not cfg.images.is_dir():
        raise DatasetError(f"{cfg.images}: no such folder of photos")
    photos = sorted(p for p in cfg.images.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if len(photos) < 3:
        raise DatasetError(f"{cfg.images}: {len(photos)} photos (JPEG, PNG or TIFF); at least 3 are needed")
    if cfg.variant is None:
        from ragsplat.train.defaults import survey_variant

        cfg = replace(cfg, variant=survey_variant(cfg.preset))
    if cfg.uncertainty is not None:
        from ragsplat.export import read_uncertainty

        read_uncertainty(cfg.uncertainty)  # ConfigError before any work
    held_lens = None if cfg.lens in LENSES else read_lens(Path(cfg.lens))
    cfg, where = locate(cfg, photos, progress)
    given = water_as_given(cfg, where, progress)
    if where.positions is not None and given.surface is not None:
        check_above(given.surface, np.array([where.positions[n] for n in where.located]))
    sized = where.located if where.positions else where.control
    given_size = cfg.max_size
    cfg = _check_sizes(cfg, progress, photos, np.array([where.frame[n] for n in sized]), given.surface)
    claim(cfg.out, "survey run")
    write_config(cfg)
    # a local origin (whole metres): UTM-sized coordinates keep millimetres in every float64 step
    origin = np.round(np.mean(list(where.frame.values()), axis=0))
    water = None if given.surface is None else given.surface.shifted(origin)
    return Survey(cfg, given_size, photos, where, given, origin, water, held_lens)


def read_lens(path: Path) -> tuple[float, float]:
    """(k1, k2) of a lens calibrated before: a survey's water.json (its "lens") or JSON with "k1" and "k2"
    (COLMAP's RADIAL; OpenCV's k1, k2 are the same, in normalised coordinates). ConfigError otherwise."""
    from ragsplat.errors import ConfigError

    try:
        record = json.loads(path.read_text())
        lens = record.get("lens", record)
        k = float(lens["k1"]), float(lens["k2"])
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        raise ConfigError(f"{path}: not a lens (JSON with k1 and k2, or a survey's water.json with its lens; "
                          f"{type(e).__name__}: {e})") from None
    if not all(math.isfinite(v) for v in k):
        raise ConfigError(f"{path}: k1, k2 must be finite, got {k}")
    return k


def write_config(cfg: SurveyConfig) -> None:
    """RUN/survey.json: the config as resolved."""
    from ragsplat.outputs import write_json

    write_json(cfg.out / "survey.json",
               {k: str(v) if isinstance(v, Path) else v for k, v in asdict(cfg).items()})


def locate(cfg: SurveyConfig, photos: list[Path], progress: Progress) -> tuple[SurveyConfig, Positions]:
    """What will fix the photos' frame: the positions file, or the photos' EXIF GPS and DJI XMP (the CRS
    they choose set in the returned config), or the ground control points with their pixels. ConfigError
    for a half-given ground control, DatasetError unless enough of the names are photos."""
    from ragsplat.dataset import layout
    from ragsplat.errors import ConfigError, DatasetError

    names = [p.name for p in photos]
    tagged = sigma = pixels = None
    if cfg.positions is not None:
        positions, control = layout.read_positions(cfg.positions), None
        known, source = positions, cfg.positions
    elif cfg.gcp is None:  # the positions from the photos' EXIF GPS and DJI XMP
        from ragsplat.dataset import exif

        if cfg.gcp_pixels is not None:
            raise ConfigError("--gcp-pixels needs --gcp (the targets' surveyed positions)")

        tagged = exif.read_photos(photos)
        positions, crs = exif.positions(tagged, cfg.crs)
        cfg = replace(cfg, crs=cfg.crs or exif.crs_label(crs))
        sigma = dict(zip(names, exif.sigmas(tagged, cfg.rtk_sigma, tuple(cfg.gps_sigma),
                                            cfg.barometer_sigma)))
        control, known, source = None, positions, cfg.images
        fixed = sum(p.rtk_fixed for p in tagged)
        baro = sum(p.barometric for p in tagged)
        heights = sorted({p.altitude_source for p in tagged if not p.barometric})
        said = ([f"{baro} from the barometer (DJI RelativeAltitude, to {cfg.barometer_sigma:g} m)"] if baro
                else []) + ([f"as the photos give them ({', '.join(heights)})"] if heights else [])
        progress.say("check", f"positions from the photos: {len(tagged)} of {len(photos)} have GPS "
                     f"({fixed} RTK fixed, {len(tagged) - fixed} consumer GPS), in {exif.describe_crs(crs)}; "
                     f"heights {', '.join(said)}")
    else:
        if cfg.gcp_pixels is None:
            raise ConfigError("--gcp needs --gcp-pixels (where each target is in the photos)")
        positions, control = None, layout.read_positions(cfg.gcp)
        pixels = layout.read_gcp_pixels(cfg.gcp_pixels)
        known, source = {image: None for image, _, _ in pixels}, cfg.gcp_pixels
        strange = sorted({name for _, name, _ in pixels} - set(control))
        if strange:
            raise DatasetError(f"{cfg.gcp_pixels}: targets not in {cfg.gcp}: {', '.join(strange[:5])}")
    unknown = sorted(set(known) - set(names))
    located = [n for n in names if n in known]
    if len(located) < (3 if control is None else 2):
        raise DatasetError(f"{source}: {len(located)} of its names are photos in {cfg.images} "
                           f"(e.g. {', '.join(sorted(known)[:3])} vs {', '.join(names[:3])}); at least "
                           f"{3 if control is None else 2} are needed")
    if unknown:
        progress.say("check", f"{len(unknown)} names in {source} are not photos in {cfg.images} (ignored), "
                     f"e.g. {unknown[0]}")
    return cfg, Positions(source, located, positions, control, pixels, tagged, sigma)


def water_as_given(cfg: SurveyConfig, where: Positions, progress: Progress) -> GivenWater:
    """The water given: a surface fitted to the edge points (--water-surface, which must lie near the
    positions), one level, or none: estimated in the adjustment through it (which --no-water-adjustment
    refuses, a ConfigError)."""
    import numpy as np

    from ragsplat.dataset import layout
    from ragsplat.errors import ConfigError
    from ragsplat.survey import water as water_fit
    from ragsplat.water_surface import WaterSurface

    if cfg.water_surface is not None:
        edge_points = layout.read_points(cfg.water_surface)
        frame = np.array(list(where.frame.values()), float)
        _check_near(edge_points, frame, cfg.water_surface, "the photos' positions" if where.control is None
                    else f"the ground control ({cfg.gcp})", cfg.crs)
        edge = water_fit.fit_edge(edge_points)
        surface = WaterSurface(edge.level, cfg.n, edge.slope, edge.profile)
        described = describe_surface(surface, edge_points[:, :2].mean(0))
        progress.say("check", f"water surface from {len(edge.residuals)} edge points: "
                     f"{described}, rms {100 * edge.report()['rms_m']:.1f} cm, "
                     f"{int((~edge.inliers).sum())} left out")
        return GivenWater(surface, edge, edge_points)
    if cfg.water_level == AUTO:  # estimated in the adjustment through the water (stage 3)
        if cfg.no_water_adjustment:
            raise ConfigError("--no-water-adjustment needs a water level or surface: without one it is "
                              "estimated in that adjustment (give --water-level Z or --water-surface "
                              "EDGE.csv)")
        return GivenWater(None)
    return GivenWater(WaterSurface(cfg.water_level, cfg.n))


def describe_surface(water, at=None) -> str:
    """The surface in words; a sloping one's height at the horizontal point `at` [2] (CRS; default x = y = 0,
    which in a projected CRS is far away)."""
    if not (water.tilted or water.curved):
        return f"level {water.level:g} m"
    import numpy as np

    xy = np.zeros(2) if at is None else np.asarray(at, float)
    where = ("x = y = 0" if at is None else f"x, y = {xy[0]:.1f}, {xy[1]:.1f}")
    height = f"{float(water.height(xy)):.3f} m at {where}"
    fall = f"a plane falling {100 * (water.slope[0] ** 2 + water.slope[1] ** 2) ** 0.5:.2f} %"
    if water.curved:
        return f"{fall} with a profile of {len(water.profile.stations)} stations along the reach ({height})"
    return f"{fall} (slope {water.slope[0]:+.5f}, {water.slope[1]:+.5f}; {height})"


def _check_near(points, frame, source: Path, what: str, crs: str | None) -> None:
    """ConfigError when `points` [N, 3] lie far from the survey `frame` [M, 3] (the positions or targets):
    more than a kilometre, and ten times the frame's extent, from its centre, they are in another frame (e.g.
    a local one beside EXIF positions in UTM)."""
    import numpy as np

    from ragsplat.errors import ConfigError

    centre = frame[:, :2].mean(0)
    extent = float(np.ptp(frame[:, :2], axis=0).max()) if len(frame) > 1 else 0.0
    far = float(np.linalg.norm(points[:, :2].mean(0) - centre))
    if far > max(1000.0, 10 * extent):
        raise ConfigError(f"{source}: its points lie {far:.0f} m from {what}: give them in the same frame"
                          + (f" ({crs})" if crs else ""))


def check_above(water, centres) -> None:
    """ConfigError unless some camera of centres [V, 3] is above the water surface."""
    import numpy as np

    from ragsplat.errors import ConfigError

    top = int(np.argmin(water.depth(centres)))
    if not water.depth(centres[top]) < 0:
        raise ConfigError(f"the water surface ({describe_surface(water)}) is not below any camera (the "
                          f"highest above it is at {centres[top, 2]:g} m, the surface "
                          f"{float(water.height(centres[top, :2])):g} m there)")


def _check_sizes(cfg: SurveyConfig, progress: Progress, photos: list[Path], centres, surface) -> SurveyConfig:
    """Every size refusal before any work, each in one line with advice that works: the training's images
    must fit `IMAGE_MEMORY` of this machine's memory (without --max-size, the largest that fits is chosen,
    said and returned in the config), and the DEM's grid over the cameras' footprints must pass
    `export.sample_count` at --resolution (the area is known only after structure from motion; here its lower
    bound: the cameras' extent, grown by each one's nadir footprint where the water level is given)."""

    import numpy as np
    from PIL import Image

    from ragsplat.errors import ConfigError
    from ragsplat.export import sample_count

    sizes = []
    for p in photos:
        with Image.open(p) as im:
            sizes.append(im.size)
    sizes = np.array(sizes, dtype=np.float64)  # [N, 2] width, height
    longest = sizes.max(1)
    asked = cfg.max_size

    def image_bytes(max_size):
        scale = np.minimum(1.0, max_size / longest) if max_size else 1.0
        return float((3 * np.prod(sizes, 1) * scale * scale).sum())

    from ragsplat.dataset.exif import focal_pixels

    focal = focal_pixels(photos[0])
    above = float(np.median(-surface.depth(centres))) if surface is not None else None  # over the water
    budget = IMAGE_MEMORY * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    if image_bytes(cfg.max_size) > budget:
        fits = int(longest.max() * (budget / image_bytes(None)) ** 0.5) // 16 * 16  # bytes go as size^2
        while fits > 16 and image_bytes(fits) > budget:
            fits -= 16
        if asked is not None:
            raise ConfigError(f"{len(photos)} photos at --max-size {cfg.max_size} take "
                              f"{image_bytes(cfg.max_size) / 1e9:.1f} GB in training, over "
                              f"{budget / 1e9:.1f} GB ({IMAGE_MEMORY:.0%} of this machine's memory); give "
                              f"--max-size {fits} or less")
        cfg = replace(cfg, max_size=fits)
        progress.say("check", f"{len(photos)} photos of {int(longest.max())} px take "
                     f"{image_bytes(None) / 1e9:.1f} GB: training on them downscaled to at most {fits} px "
                     f"({image_bytes(fits) / 1e9:.1f} GB; --max-size to choose)")
    lo, hi = centres[:, :2].min(0), centres[:, :2].max(0)
    # the nadir footprint's half width: height over the water x half the sensor / focal
    if above is not None and focal:
        reach = above * 0.5 * sizes[0].max() / focal
        lo, hi = lo - max(reach, 0.0), hi + max(reach, 0.0)
    sample_count(lo, hi, cfg.resolution)  # ConfigError with the resolution that passes
    return cfg
