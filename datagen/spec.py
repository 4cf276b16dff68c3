"""Typed scene spec for the synthetic riverbed and its presets.

A `SceneSpec` fully determines a dataset: with the same spec (seed included) the generator writes the same
files. `preset(name)` gives the three sizes; `validate(spec)` raises `SpecError` (one line) for a spec that
cannot make a bathymetric dataset. The resolved spec is written to `scene.json` by the generator.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from ragsplat.errors import SpecError


@dataclass(frozen=True)
class StoneClass:
    radius: float  # m, mean horizontal semi-axis
    density: float  # stones per square metre
    height: float  # cap height as a fraction of the radius


@dataclass(frozen=True)
class BedSpec:
    size: float = 40.0  # side of the square heightfield (m), centred on the world origin
    cell: float = 0.025  # mesh vertex spacing (m); an integer multiple of texel
    texel: float = 0.0125  # albedo texture pixel (m); the heightfield is built at this resolution
    # Gravel bed: mean depth below the water level (m). Reach: the reference depth of the flight plan's
    # overlap and aim and of the trainer's initial plane.
    depth: float = 10.0
    undulation: float = 0.4  # amplitude (m) of the low-frequency relief
    wavelength: float = 8.0  # shortest wavelength (m) in that relief
    taper: float = 2.0  # border width (m) over which relief and stones fade into the flat floor
    stones: tuple[StoneClass, ...] = (
        StoneClass(0.30, 1.5, 0.5),
        StoneClass(0.15, 6.0, 0.55),
        StoneClass(0.07, 20.0, 0.6),
    )


@dataclass(frozen=True)
class ReachSpec:
    """A river reach along x: a meandering channel with pools at the bends and riffles between them, the
    thalweg pushed towards the outer bank, gravel point bars on the inner side and banks that rise above
    the water. Boulders lie in the channel; the bed's gravel classes (`BedSpec.stones`) cover channel and
    bars. Heights are relative to the water level."""

    width: float = 7.0  # channel width at the water line (m)
    max_depth: float = 3.0  # deepest pool below the water (m)
    riffle_depth: float = 0.3  # thalweg depth at the riffles, as a fraction of max_depth
    pool_spacing: float = 9.0  # distance between pools along the flow (m): half the meander wavelength
    meander: float = 0.8  # lateral amplitude of the channel centreline (m)
    bank_height: float = 0.8  # height of the banks above the water (m)
    bank_width: float = 1.2  # horizontal run over which a bank rises (m)
    bar_height: float = 0.25  # height of the gravel bars above the water (m)
    bar_width: float = 2.0  # width of an exposed point bar at a bend (m)
    boulders: StoneClass = StoneClass(0.4, 0.06, 0.55)  # in the channel only

    @property
    def gravel_top(self) -> float:
        """Height above the water (m) up to which gravel lies and the ground is the bed's: the bars'."""
        return self.bar_height

    @property
    def land_top(self) -> float:
        """Height above the water (m) from which the ground is soil and grass: the banks' top."""
        return self.bank_height


@dataclass(frozen=True)
class ShoreSpec:
    """A lake shore along x: dry land towards +y rising from the waterline to `land_height`, and towards -y a
    beach that slopes into the water and levels out on the lake's floor `depth` below it. The waterline
    bends about y = `shoreline` along x. Boulders lie in the water; the bed's gravel classes cover the
    floor, the beach and the sand above the water. Heights are relative to the water level. It takes a
    reach's place in `SceneSpec.reach` (both are ground with dry land beside the water)."""

    depth: float = 1.5  # the lake's floor below the water (m)
    beach_slope: float = 0.1  # the submerged beach's slope at the waterline (dz / dy), levelling to the floor
    land_slope: float = 0.06  # the dry beach's rise at the waterline (dz / dy), levelling to land_height
    land_height: float = 1.2  # the land beyond the beach above the water (m)
    sand_height: float = 0.3  # sand and gravel above the water up to this height (m); soil and grass above
    shoreline: float = 0.0  # y of the waterline's mean (m)
    wander: float = 2.0  # amplitude (m) of the waterline's bends along x
    wander_wavelength: float = 40.0  # length (m) of one bend and back
    boulders: StoneClass = StoneClass(0.5, 0.02, 0.55)  # in the water only

    @property
    def max_depth(self) -> float:
        return self.depth

    @property
    def gravel_top(self) -> float:
        return self.sand_height

    @property
    def land_top(self) -> float:
        return self.land_height


@dataclass(frozen=True)
class WaterSpec:
    """The water surface z = level + slope[0] x + slope[1] y (`ragsplat.water_surface.WaterSurface`'s
    meaning): a flat plane by default; a river falling by a fraction S downstream (+x) has slope (-S, 0).
    The whole scene falls with it (`ragsplat.datagen.bed.shear`), so the depths are those of the flat
    scene."""

    level: float = 0.0  # z of the water surface at x = y = 0 (m)
    n: float = 1.33  # refractive index relative to air
    radiance_scale: bool = True  # refraction colour 1/n^2 (Cycles does not apply the radiance drop itself)
    slope: tuple[float, float] = (0.0, 0.0)  # (dz/dx, dz/dy); (0, 0): no key in spec.json

    @property
    def sloping(self) -> bool:
        return any(v != 0 for v in self.slope)

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Surface height [...] at horizontal points xy [..., 2] (exactly `level` where the slope is 0)."""
        xy = np.asarray(xy, np.float64)
        return self.level + self.slope[0] * xy[..., 0] + self.slope[1] * xy[..., 1]


@dataclass(frozen=True)
class CameraModel:
    """A drone camera's optics: a mapping preset's photos take its field of view and aspect, rendered at
    fewer pixels (the ground sample distance grows with the ratio of the widths)."""

    name: str
    focal_mm: float
    sensor_mm: tuple[float, float]  # width, height
    pixels: tuple[int, int]  # the photos' width, height

    @property
    def fov_deg(self) -> float:
        """Horizontal field of view (degrees)."""
        return math.degrees(2 * math.atan(self.sensor_mm[0] / 2 / self.focal_mm))

    def record(self, width: int) -> dict:
        """scene.json's account of photos rendered `width` pixels wide with this camera's optics."""
        return {"name": self.name, "focal_mm": self.focal_mm, "sensor_mm": list(self.sensor_mm),
                "pixels": list(self.pixels), "fov_deg": self.fov_deg, "rendered_width": width,
                "gsd_scale": self.pixels[0] / width,
                "meaning": "the camera's field of view and aspect at fewer pixels: the ground sample "
                           "distance is gsd_scale times the real camera's at the same altitude"}


# The consumer drones' cameras a mapping preset stands for (FlightSpec.camera names one).
CAMERAS = {"FC300S": CameraModel("DJI FC300S (Phantom 3 Professional)", 3.61, (6.17, 4.55), (4000, 3000))}


@dataclass(frozen=True)
class FlightSpec:
    width: int = 800  # image width (px)
    fov_deg: float = 70.0  # horizontal field of view (along the image's width)
    altitude: float = 12.0  # flight height above the water level (m)
    # overlap of neighbouring nadirs along each row (x; `mapping`: along each flight line, the forward one),
    # on the bed; and between the rows (y; `mapping`: between the lines, the side one), 0: the same
    overlap: float = 0.85
    side_overlap: float = 0.0
    grid: tuple[int, int] = (4, 4)  # nadir rows (along y) x columns (along x)
    height: int = 0  # image height (px); 0: square images
    camera: str = ""  # a consumer camera of `CAMERAS` whose field of view and aspect these are; "": none
    tilts: tuple[float, ...] = (20.0, 40.0)  # obliques: optical axis angle from the vertical (deg)
    azimuth_step: float = 10.0  # training azimuth step on each ring (at each station) (deg)
    test_azimuth_offset: float = 5.0  # held-out obliques sit between training azimuths
    # held-out ring views every this many degrees (strips: from station to station)
    test_azimuth_step: float = 60.0
    # Obliques: "rings" about the scene centre, or "strips": at `stations` points along the reach's axis
    # (y = 0), from the first nadir column to the last, as a survey of a long reach flies them. "mapping":
    # the nadir lawnmower a planning app flies (DJI Pilot, Pix4Dcapture): each row a flight line along x,
    # flown back and forth, the image's top ahead and its width across the line; its obliques (`tilts`; a
    # mapping preset has none) are taken from the same grid points, tilted towards each azimuth.
    pattern: str = "rings"
    stations: int = 0  # strips only

    @property
    def image_height(self) -> int:
        return self.height or self.width

    @property
    def side(self) -> float:
        """The overlap between the grid's rows (the side overlap)."""
        return self.side_overlap or self.overlap


@dataclass(frozen=True)
class LightSpec:
    sun_elevation: float = 55.0  # deg above the horizon
    sun_azimuth: float = 30.0  # deg, counter-clockwise from +x
    sun_strength: float = 3.0  # W/m^2 (Blender sun units)
    sun_angle: float = 1.0  # angular diameter (deg): slightly soft shadows
    sky_strength: float = 0.3  # sky texture multiplier


@dataclass(frozen=True)
class RenderSpec:
    samples: int = 256  # Cycles samples per pixel for the colour passes
    device: str = "auto"  # "CPU", "GPU" or "auto" (GPU when Cycles finds one)
    threads: int = 0  # 0: all cores
    filter_width: float = 1.5  # colour passes (px, Blackman-Harris)
    depth_filter: float = 0.01  # depth pass: a near-point filter gives the exact surface at the pixel centre
    exposure: float = 0.0  # stops
    lens: bool = True  # the survey's photos again through a lens (survey/images-lens/): a wet image a photo


@dataclass(frozen=True)
class FieldConditions:
    """Field conditions, each off at its default (the ideal survey: still, clear, non-reflecting water).
    Rendered by Cycles itself (`ragsplat.datagen.conditions` makes the geometry and numbers,
    `ragsplat.blender_scenes.render` the materials): a water body that absorbs and scatters per colour
    channel, Fresnel reflection of sky and sun at the surface, ripples with a new phase in every photo, and
    checkerboard ground control targets on the banks."""

    # Water body: absorption and scattering coefficients (1/m) per linear RGB channel, each times
    # `turbidity` (the sweep's scale). Beer-Lambert along every in-water path, the sunlight's included.
    absorption: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scattering: tuple[float, float, float] = (0.0, 0.0, 0.0)
    turbidity: float = 1.0
    reflection: bool = False  # Fresnel reflection of the sky and the sun (glint) at the surface
    ripple_amplitude: float = 0.0  # rms height (m) of the surface about the level; 0: a flat plane
    ripple_wavelengths: tuple[float, float] = (0.2, 2.0)  # shortest and longest ripple (m)
    ripple_waves: int = 32  # sinusoids in the seeded spectrum
    ripple_cell: float = 0.03  # mesh spacing (m) of the rippled surface: several vertices per shortest ripple
    targets: int = 0  # checkerboard ground control targets on the banks (reach scenes)
    target_size: float = 0.3  # side (m) of a target: 2 x 2 black and white squares

    @property
    def turbid(self) -> bool:
        return self.turbidity > 0 and max(*self.absorption, *self.scattering) > 0

    @property
    def rippled(self) -> bool:
        return self.ripple_amplitude > 0


# Fields added after datasets were made, written to spec.json only away from their defaults: the older
# datasets' spec.json, and so their fingerprints, stay as they were.
_LATER = {"flight": ("pattern", "stations", "side_overlap", "height", "camera"), "render": ("lens",)}


@dataclass(frozen=True)
class SceneSpec:
    preset: str
    seed: int = 0
    bed: BedSpec = field(default_factory=BedSpec)
    # None: the paper's gravel bed, flat on average at bed.depth; a river reach or a lake shore
    reach: ReachSpec | ShoreSpec | None = None
    water: WaterSpec | None = field(default_factory=WaterSpec)
    flight: FlightSpec = field(default_factory=FlightSpec)
    light: LightSpec = field(default_factory=LightSpec)
    render: RenderSpec = field(default_factory=RenderSpec)
    conditions: FieldConditions | None = None  # None: the ideal survey (no key in spec.json)

    @property
    def level(self) -> float:
        """Reference height: the water plane, or z = 0 for a dry scene."""
        return self.water.level if self.water is not None else 0.0

    @property
    def n(self) -> float:
        return self.water.n if self.water is not None else 1.0

    def to_dict(self) -> dict:
        d = asdict(self)
        if self.conditions is None:  # the ideal presets' spec.json, and so their datasets, stay as they were
            del d["conditions"]
        if self.water is not None and not self.water.sloping:  # so do the flat presets'
            del d["water"]["slope"]
        for part, keys in _LATER.items():  # and those that keep these fields' defaults
            default = type(getattr(self, part))()
            for k in keys:
                if d[part][k] == getattr(default, k):
                    del d[part][k]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> SceneSpec:
        bed = dict(d["bed"])
        bed["stones"] = tuple(StoneClass(**s) for s in bed["stones"])
        flight = dict(d["flight"])
        flight["grid"] = tuple(flight["grid"])
        flight["tilts"] = tuple(flight["tilts"])
        reach = d.get("reach")
        if reach is not None:
            kind = ShoreSpec if "beach_slope" in reach else ReachSpec
            reach = kind(**{**reach, "boulders": StoneClass(**reach["boulders"])})
        return cls(preset=d["preset"], seed=int(d["seed"]), bed=BedSpec(**bed), reach=reach,
                   water=None if d["water"] is None else WaterSpec(**{
                       k: tuple(v) if isinstance(v, list) else v for k, v in d["water"].items()}),
                   flight=FlightSpec(**flight), light=LightSpec(**d["light"]),
                   render=RenderSpec(**d["render"]),
                   conditions=None if d.get("conditions") is None else FieldConditions(**{
                       k: tuple(v) if isinstance(v, list) else v for k, v in d["conditions"].items()}))


# Presets. River reaches (`ReachSpec`): smoke (CI scale, seconds), small (the default of `make dataset`,
# pools 3 m deep, 256 px, on 2 CPU cores) and paper-reach (pools 10 m deep, 800 px: a GPU). The paper's
# gravel bed: paper (800 x 800, 70 deg, about 90 training views, bed 10 m deep), and smoke-bed / small-bed
# at the smoke and small scales (the benchmark before the reach).
PRESETS: dict[str, SceneSpec] = {
    "smoke": SceneSpec(
        preset="smoke",
        bed=BedSpec(size=12.0, cell=0.05, texel=0.025, depth=0.8, taper=0.5,
                    stones=(StoneClass(0.25, 2.0, 0.5), StoneClass(0.12, 8.0, 0.55))),
        reach=ReachSpec(width=3.0, max_depth=2.0, pool_spacing=4.0, meander=0.4, bank_height=0.5,
                        bank_width=0.6, bar_height=0.15, bar_width=0.9, boulders=StoneClass(0.3, 0.1, 0.55)),
        flight=FlightSpec(width=64, altitude=3.0, grid=(2, 2), azimuth_step=90.0, test_azimuth_step=180.0),
        render=RenderSpec(samples=16, device="CPU"),
    ),
    "small": SceneSpec(
        preset="small",
        bed=BedSpec(size=20.0, cell=0.02, texel=0.01, depth=1.5, taper=1.0,
                    stones=(StoneClass(0.20, 2.0, 0.5), StoneClass(0.10, 8.0, 0.55),
                            StoneClass(0.05, 25.0, 0.6))),
        reach=ReachSpec(),
        flight=FlightSpec(width=256, altitude=4.0, grid=(3, 5), azimuth_step=10.0, test_azimuth_step=60.0),
        render=RenderSpec(samples=24, device="CPU"),
    ),
    "paper-reach": SceneSpec(
        preset="paper-reach",
        bed=BedSpec(size=66.0, cell=0.04, texel=0.02, depth=5.0, taper=3.0,
                    stones=(StoneClass(0.30, 1.5, 0.5), StoneClass(0.15, 6.0, 0.55),
                            StoneClass(0.07, 20.0, 0.6))),
        reach=ReachSpec(width=23.0, max_depth=10.0, pool_spacing=23.0, meander=2.7, bank_height=2.0,
                        bank_width=4.0, bar_height=0.6, bar_width=6.5, boulders=StoneClass(1.0, 0.02, 0.55)),
        flight=FlightSpec(altitude=12.0, grid=(3, 5)),
    ),
    "smoke-bed": SceneSpec(
        preset="smoke-bed",
        bed=BedSpec(size=10.0, cell=0.05, texel=0.025, depth=2.0, undulation=0.1, wavelength=4.0, taper=0.5,
                    stones=(StoneClass(0.25, 2.0, 0.5), StoneClass(0.12, 8.0, 0.55))),
        flight=FlightSpec(width=64, altitude=3.0, grid=(2, 2), azimuth_step=90.0, test_azimuth_step=180.0),
        render=RenderSpec(samples=16, device="CPU"),
    ),
    "small-bed": SceneSpec(
        preset="small-bed",
        bed=BedSpec(size=16.0, cell=0.02, texel=0.01, depth=3.0, undulation=0.15, wavelength=5.0, taper=1.0,
                    stones=(StoneClass(0.20, 2.0, 0.5), StoneClass(0.10, 8.0, 0.55),
                            StoneClass(0.05, 25.0, 0.6))),
        flight=FlightSpec(width=256, altitude=4.0, grid=(3, 3), azimuth_step=10.0, test_azimuth_step=60.0),
        render=RenderSpec(samples=32, device="CPU"),
    ),
    "paper": SceneSpec(preset="paper"),
}


# Clear river water (diffuse attenuation of a few tenths per metre, strongest in red), sky reflection with
# the default sun's glint (35 degrees from nadir, towards the sun), light wind ripples, six bank targets.
CLEAR_RIVER = FieldConditions(absorption=(0.40, 0.12, 0.15), scattering=(0.04, 0.05, 0.06), reflection=True,
                              ripple_amplitude=0.005, targets=6)
PRESETS["small-field"] = replace(PRESETS["small"], preset="small-field", conditions=CLEAR_RIVER)
PRESETS["smoke-field"] = replace(PRESETS["smoke"], preset="smoke-field", conditions=replace(
    CLEAR_RIVER, ripple_wavelengths=(0.3, 2.0), ripple_cell=0.04, target_size=0.6))


def with_slope(spec: SceneSpec, fall: float, name: str | None = None) -> SceneSpec:
    """`spec` with its water surface falling by the fraction `fall` downstream (+x): slope (-fall, 0)."""
    water = None if spec.water is None else replace(spec.water, slope=(-float(fall) if fall else 0.0, 0.0))
    return replace(spec, water=water, preset=name or spec.preset)


# A steep gravel-bed river: the reach falling 1 % (10 cm over `small`'s 10 m evaluated stretch), and its
# CI-scale twin.
PRESETS["small-slope"] = with_slope(PRESETS["small"], 0.01, "small-slope")
PRESETS["smoke-slope"] = with_slope(PRESETS["smoke"], 0.01, "smoke-slope")

# `small` flown as its nadir grid alone (the 15 photos without the 72 obliques, the same reach and nadirs):
# what the obliques buy a surveyor.
PRESETS["small-nadir"] = replace(PRESETS["small"], preset="small-nadir",
                                 flight=replace(PRESETS["small"].flight, tilts=()))

# River scale: `long`, a reach of 110 m (evaluated; the bed 120 m) falling 0.3 %, 10 m wide with a
# pool every 20 m, flown as a survey flies it: 12 m above the water, 384 px (4.4 cm a pixel at the water,
# 4.8 cm on the bed 1.5 m down), three nadir strips along it and obliques at 27 stations along its axis
# looking up, down and across the river: 321 training photos, to test what a survey of a real reach asks of
# the method (tiling, memory, drift). `smoke-long`: the same at CI scale (smoke's reach, 15 m evaluated,
# 72 photos of 64 px), long enough that a survey splits into tiles. Neither renders the lens photos.
PRESETS["long"] = with_slope(SceneSpec(
    preset="long",
    bed=BedSpec(size=120.0, cell=0.05, texel=0.025, depth=1.5, taper=3.0,
                stones=(StoneClass(0.25, 1.5, 0.5), StoneClass(0.12, 6.0, 0.55))),
    reach=ReachSpec(width=10.0, pool_spacing=20.0, meander=2.0, bank_height=1.2, bank_width=2.0,
                    bar_height=0.3, bar_width=3.5, boulders=StoneClass(0.5, 0.05, 0.55)),
    flight=FlightSpec(width=384, altitude=12.0, grid=(3, 35), azimuth_step=90.0, test_azimuth_offset=45.0,
                      test_azimuth_step=90.0, pattern="strips", stations=27),
    render=RenderSpec(samples=24, device="CPU", lens=False),
), 0.003)
PRESETS["smoke-long"] = with_slope(replace(
    PRESETS["smoke"], preset="smoke-long", bed=replace(PRESETS["smoke"].bed, size=24.0),
    flight=replace(PRESETS["long"].flight, width=64, altitude=3.0, grid=(2, 16), stations=5),
    render=replace(PRESETS["smoke"].render, lens=False),
), 0.003)


# The flight people fly: a planning app's nadir lawnmower at 80 % forward and 70 % side
# overlap with a DJI Phantom 3's camera (FC300S: 81 degrees across its 4:3 photos), rendered 1200 x 900 px
# (the real 4000 x 3000's field of view, the ground sample distance 3.3 times as coarse), no obliques.
# `lake-mapping`: a lake shore 40 m below the drone, 21 photos in three lines: a beach sloping into water that
# levels out 1.5 m deep, boulders in it. `river-mapping`: the `long` reach's river, 20 photos in two lines
# 30 m up. Their `smoke-` twins: the same kind of flight at CI scale, photos large enough for structure from
# motion (240 x 180 px). None renders the lens photos.
MAPPING = FlightSpec(width=1200, height=900, fov_deg=CAMERAS["FC300S"].fov_deg, altitude=40.0, overlap=0.8,
                     side_overlap=0.7, grid=(3, 7), tilts=(), pattern="mapping", camera="FC300S")
LAKE_GRAVEL = (StoneClass(0.25, 1.0, 0.5), StoneClass(0.12, 4.0, 0.55))
PRESETS["lake-mapping"] = SceneSpec(
    preset="lake-mapping",
    bed=BedSpec(size=124.0, cell=0.08, texel=0.04, depth=1.0, undulation=0.15, wavelength=12.0, taper=3.0,
                stones=LAKE_GRAVEL),
    reach=ShoreSpec(shoreline=10.0),
    flight=MAPPING,
    render=RenderSpec(samples=24, device="CPU", lens=False),
)
PRESETS["river-mapping"] = replace(
    PRESETS["long"], preset="river-mapping", flight=replace(MAPPING, altitude=30.0, grid=(2, 10)))
PRESETS["smoke-lake-mapping"] = SceneSpec(
    preset="smoke-lake-mapping",
    bed=BedSpec(size=26.0, cell=0.05, texel=0.025, depth=0.5, undulation=0.1, wavelength=4.0, taper=1.0,
                stones=PRESETS["smoke"].bed.stones),
    reach=ShoreSpec(depth=0.8, beach_slope=0.15, land_slope=0.15, land_height=0.6, sand_height=0.2,
                    shoreline=3.0, wander=0.8, wander_wavelength=15.0, boulders=StoneClass(0.3, 0.1, 0.55)),
    flight=replace(MAPPING, width=240, height=180, altitude=10.0, grid=(2, 5)),
    render=RenderSpec(samples=16, device="CPU", lens=False),
)
PRESETS["smoke-river-mapping"] = replace(
    PRESETS["smoke-long"], preset="smoke-river-mapping",
    flight=replace(MAPPING, width=240, height=180, altitude=6.0, grid=(2, 6)))


def with_conditions(spec: SceneSpec, turbidity: float | None = None, reflection: bool | None = None,
                    ripple_amplitude: float | None = None) -> SceneSpec:
    """`spec` with these field conditions changed (None: as the spec has them). An ideal spec starts from
    CLEAR_RIVER with every effect off, so that `--turbidity 1` alone gives clear river water and nothing
    else; a spec left with no effect on is the ideal one (no conditions)."""
    c = (spec.conditions
         or replace(CLEAR_RIVER, turbidity=0.0, reflection=False, ripple_amplitude=0.0, targets=0))
    changes = {"turbidity": turbidity, "reflection": reflection, "ripple_amplitude": ripple_amplitude}
    c = replace(c, **{k: v for k, v in changes.items() if v is not None})
    ideal = not (c.turbid or c.reflection or c.rippled or c.targets)
    return replace(spec, conditions=None if ideal and spec.conditions is None else c)


def preset(name: str, seed: int | None = None) -> SceneSpec:
    if name not in PRESETS:
        raise SpecError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    spec = PRESETS[name]
    return spec if seed is None else replace(spec, seed=int(seed))


MAX_SLOPE = 0.1  # steepest water surface (dz per metre) a spec may ask for: 10 %, ten times a steep river


def validate(spec: SceneSpec) -> None:
    """Raise SpecError naming the first problem; a spec that passes can be planned and rendered."""
    b, f, r = spec.bed, spec.flight, spec.render
    if spec.water is not None and not (math.isfinite(spec.water.n) and spec.water.n >= 1.0):
        raise SpecError(f"water refractive index must be finite and >= 1, got {spec.water.n}")
    if not (f.altitude > 0 and math.isfinite(f.altitude)):
        raise SpecError(f"camera under water: flight altitude {f.altitude} m must be above the water level")
    if spec.water is not None:
        _validate_slope(spec)
    if not (b.depth > 0 and math.isfinite(b.depth)):
        raise SpecError(f"bed depth {b.depth} m must be positive (the bed lies below the water level)")
    if spec.reach is None:
        if b.undulation + max((s.radius * s.height for s in b.stones), default=0.0) >= b.depth:
            raise SpecError("bed relief reaches the water surface: reduce undulation/stones or increase "
                            "depth")
    elif isinstance(spec.reach, ShoreSpec):
        _validate_shore(spec)
    else:
        _validate_reach(spec)
    if not (0.0 < f.overlap < 1.0 and 0.0 <= f.side_overlap < 1.0):
        raise SpecError(f"overlap must be in (0, 1), got {f.overlap} forward and {f.side_overlap} side (0: "
                        "the forward one); zero overlap leaves nothing to match")
    if not (0.0 < f.fov_deg < 180.0):
        raise SpecError(f"field of view must be in (0, 180) degrees, got {f.fov_deg}")
    if min(f.width, f.image_height) < 8 or f.height < 0:
        raise SpecError(f"image width and height must be at least 8 px, got {f.width} x {f.height} "
                        "(0: square)")
    if f.camera:
        _validate_camera(f)
    if min(f.grid) < 1:
        raise SpecError(f"nadir grid must have at least 1 x 1 views, got {f.grid}")
    if any(not (0.0 < t < 90.0 - f.fov_deg / 2) for t in f.tilts):
        raise SpecError(f"oblique tilts {f.tilts} must be in (0, {90 - f.fov_deg / 2:g}) deg to stay below "
                        "the horizon")
    if not (0.0 < f.azimuth_step <= 360.0 and 0.0 < f.test_azimuth_step <= 360.0):
        raise SpecError("azimuth steps must be in (0, 360] degrees")
    if f.pattern not in ("rings", "strips", "mapping"):
        raise SpecError(f"flight pattern must be 'rings', 'strips' or 'mapping', got {f.pattern!r}")
    if f.pattern != "strips" and f.stations != 0 or f.pattern == "strips" and min(f.stations, f.grid[1]) < 2:
        raise SpecError("oblique stations belong to the strips pattern, which needs at least 2 of them and "
                        f"2 nadir columns: got {f.stations} stations and {f.grid[1]} columns for {f.pattern}")
    if b.texel <= 0 or b.cell <= 0 or abs(b.cell / b.texel - round(b.cell / b.texel)) > 1e-9:
        raise SpecError(f"bed cell {b.cell} must be a positive integer multiple of texel {b.texel}")
    if b.taper < 2 * b.cell or 2 * b.taper >= b.size:
        raise SpecError(f"bed taper {b.taper} m must be at least two cells and less than half the bed size")
    if r.samples < 1 or r.device not in ("CPU", "GPU", "auto") or r.threads < 0:
        raise SpecError(f"bad render settings: samples {r.samples}, device {r.device!r}, threads {r.threads}")
    if not (r.filter_width > 0 and r.depth_filter > 0):
        raise SpecError("pixel filter widths must be positive")
    if not (0 < spec.light.sun_elevation <= 90 and math.isfinite(spec.light.sun_azimuth)):
        raise SpecError(f"sun elevation must be in (0, 90] deg and the azimuth finite, got "
                        f"{spec.light.sun_elevation} and {spec.light.sun_azimuth}")
    if spec.conditions is not None:
        _validate_conditions(spec)


def _validate_slope(spec: SceneSpec) -> None:
    slope = spec.water.slope
    if not (len(slope) == 2 and all(math.isfinite(v) for v in slope) and math.hypot(*slope) <= MAX_SLOPE):
        raise SpecError(f"water slope {tuple(slope)} must be finite and at most {MAX_SLOPE:g} in gradient "
                        "(rivers fall 0.001-0.01)")
    rise = math.hypot(*slope) * spec.bed.size / math.sqrt(2)  # from the centre to a corner of the bed
    if rise and not rise < spec.flight.altitude / 2:
        raise SpecError(f"water slope {tuple(slope)} lifts the surface {rise:.2f} m within the bed, more "
                        f"than half the {spec.flight.altitude} m flight altitude: a gentler slope or a "
                        "higher flight")


def _validate_conditions(spec: SceneSpec) -> None:
    c = spec.conditions
    if spec.water is None:
        raise SpecError("field conditions need water: drop --no-water or use an ideal preset")
    numbers = (*c.absorption, *c.scattering, c.turbidity, c.ripple_amplitude, *c.ripple_wavelengths,
               c.ripple_cell, c.target_size)
    if not all(math.isfinite(v) for v in numbers) or min(numbers) < 0:
        raise SpecError("absorption, scattering, turbidity, ripple amplitude, wavelengths, cell and target "
                        "size must be finite and >= 0")
    shortest, longest = c.ripple_wavelengths
    if not (0 < shortest <= longest) or c.ripple_waves < 1:
        raise SpecError(f"ripple wavelengths {c.ripple_wavelengths} need 0 < shortest <= longest, and a wave")
    if c.rippled and not 0 < c.ripple_cell <= shortest / 6:
        raise SpecError(f"ripple cell {c.ripple_cell} m must be at most a sixth of the shortest ripple "
                        f"({shortest} m): with fewer vertices per wave the mesh facets it")
    if c.targets and (spec.reach is None or c.target_size <= 0):
        raise SpecError("ground control targets need a reach with banks, and a positive target size")


def _validate_camera(f: FlightSpec) -> None:
    model = CAMERAS.get(f.camera)
    if model is None:
        raise SpecError(f"unknown camera {f.camera!r}; choose one of {', '.join(CAMERAS)}")
    w, h = model.pixels
    if abs(f.fov_deg - model.fov_deg) > 1e-6 or abs(f.image_height * w / h - f.width) > 1:
        raise SpecError(f"the {f.camera}'s photos are {w} x {h} px with a {model.fov_deg:.2f} deg field of "
                        f"view: {f.width} x {f.image_height} px at {f.fov_deg:g} deg is not that camera's at "
                        "fewer pixels")


def _validate_shore(spec: SceneSpec) -> None:
    s, b = spec.reach, spec.bed
    if not all(v > 0 for v in (s.depth, s.beach_slope, s.land_slope, s.land_height, s.wander_wavelength)):
        raise SpecError("shore depth, beach_slope, land_slope, land_height and wander_wavelength must be > 0")
    if not (0 <= s.sand_height < s.land_height and s.wander >= 0):
        raise SpecError("a shore needs 0 <= sand_height < land_height and wander >= 0")
    if abs(s.shoreline) + s.wander >= b.size / 2 - b.taper:
        raise SpecError(f"the shoreline (y {s.shoreline:g} m, bending {s.wander:g} m) does not lie in the "
                        f"{b.size} m bed minus its {b.taper} m border")
    if not 0 < b.depth <= s.depth:
        raise SpecError(f"bed.depth {b.depth} m (the flight plan's reference) must be in (0, depth]")


def _validate_reach(spec: SceneSpec) -> None:
    r, b = spec.reach, spec.bed
    if not all(v > 0 for v in (r.width, r.max_depth, r.pool_spacing, r.bank_height, r.bank_width,
                               r.bar_width)):
        raise SpecError("reach width, max_depth, pool_spacing, bank_height, bank_width and bar_width must be "
                        "> 0")
    if not (0 < r.riffle_depth <= 1 and 0 <= r.bar_height < r.bank_height and r.meander >= 0):
        raise SpecError("reach needs 0 < riffle_depth <= 1, 0 <= bar_height < bank_height and meander >= 0")
    reach = 0.5 * r.width * 1.15 + r.meander + 1.25 * r.bar_width + r.bank_width  # centre to bank top, worst
    if reach >= b.size / 2 - b.taper:
        raise SpecError(f"the reach ({reach:.2f} m from the centre to the bank top) does not fit in the "
                        f"{b.size} m bed minus its {b.taper} m border: enlarge bed.size")
    if not 0 < b.depth <= r.max_depth:
        raise SpecError(f"bed.depth {b.depth} m (the flight plan's reference) must be in (0, max_depth]")
