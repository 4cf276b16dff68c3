"""Training configuration: the variant registry, the typed run config and its presets.

A variant is a set of `refract_gaussians` flags (None: plain 3DGS, the transform is never called). The
ablation harness, the tables and the command line all read `VARIANTS` from here.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace

from ragsplat_core.errors import ConfigError
from ragsplat_core.train.strategy import PAPER_ITERATIONS, DensifyConfig

# variant -> refract_gaussians flags (None: plain 3DGS, no refraction work at all)
VARIANTS: dict[str, dict | None] = {
    "3dgs": None,
    "position": {"position": True, "scale": "none", "opacity": False, "color": False},
    "position+scale": {"position": True, "scale": "isotropic", "opacity": False, "color": False},
    "position+opacity": {"position": True, "scale": "none", "opacity": True, "color": False},
    "full": {"position": True, "scale": "isotropic", "opacity": True, "color": False},
    "full+anisotropic": {"position": True, "scale": "anisotropic", "opacity": True, "color": False},
    "full+color": {"position": True, "scale": "isotropic", "opacity": True, "color": True},
    # Surfels (2DGS): flat Gaussians with a well-defined normal and depth. RA-GS maps a surfel's two tangent
    # vectors by the refraction Jacobian (t' = J t, the exact first-order map), hence scale="anisotropic".
    "2dgs": None,
    "2dgs+full": {"position": True, "scale": "anisotropic", "opacity": True, "color": False},
    # 2dgs+full with the water's own optics on top (issue 50, `WATER_TERMS`)
    "2dgs+full+attenuation": {"position": True, "scale": "anisotropic", "opacity": True, "color": False},
    "2dgs+full+backscatter": {"position": True, "scale": "anisotropic", "opacity": True, "color": False},
    "2dgs+full+reflection": {"position": True, "scale": "anisotropic", "opacity": True, "color": False},
    "2dgs+full+water": {"position": True, "scale": "anisotropic", "opacity": True, "color": False},
}
# rendered as surfels (`rasterize_surfels`)
SURFELS = frozenset({"2dgs", "2dgs+full", "2dgs+full+attenuation", "2dgs+full+backscatter", "2dgs+full+reflection",
                     "2dgs+full+water"})
# variant -> the terms of the water's optics it trains besides the refraction (issue 50); a variant not named
# here computes none of them. "attenuation": each submerged Gaussian's radiance x exp(-c L) per channel of
# linear RGB, L its path in the water along the bent ray (`refraction.water_paths`), c optimised per scene.
# "backscatter": each pixel + the water column's veil B_inf (1 - exp(-c_b L)) in linear RGB, L its path in the
# water to the point it renders (`refraction.pixel_water_paths`, from the rendered depth), B_inf and c_b
# optimised per scene. "reflection": each wet pixel (1 - R) x what the water shows + R x the sky mirrored by the
# surface, R the Fresnel reflectance at its incidence (`reflection.surface_reflection`), the sky a small map of
# linear radiance shared by all views (`reflection.sky_radiance`) optimised per scene. "2dgs+full+water": all three.
WATER_TERMS: dict[str, tuple[str, ...]] = {"2dgs+full+attenuation": ("attenuation",),
                                           "2dgs+full+backscatter": ("backscatter",),
                                           "2dgs+full+reflection": ("reflection",),
                                           "2dgs+full+water": ("attenuation", "backscatter", "reflection")}
# The attenuation coefficients' range (1/m), kept by a clamp: natural waters from clear ocean water's blue
# (about 0.02) to a turbid river's red (a few per metre).
ATTENUATION_RANGE = (0.01, 5.0)
# The backscatter's ranges, kept by clamps: c_b (1/m) as the attenuation's, and B_inf (linear radiance, the
# images' white = 1) from nearly black ocean water to a milky river's bright veil.
BACKSCATTER_RANGE = (0.01, 5.0)
VEIL_RANGE = (1e-3, 1.0)
# The sky map's range (linear radiance, the images' white = 1), kept by a clamp: from a dark overcast sky to a
# glint that still shows through R = 0.02 at nadir (R x 100 = 2: saturated), where the images clip.
SKY_RANGE = (1e-3, 100.0)
# Where the ablation's rows and a survey's training start by default: the training images' tracks, refracted
# (F1@3% about 20 % from the paper's plane on the reach, which has no single bed depth; docs/evaluation.md)
INIT = "refracted"
# Settings of how a run executes, not of what it computes (the same steps, equal to round-off): a checkpoint
# written under one value resumes under another.
RUN_ONLY = frozenset({"compile_refraction", "checkpoint_every"})

# optimize_water -> the WaterSurface fields it calibrates
WATER_PARAMS: dict[str, tuple[str, ...]] = {"none": (), "level": ("level",), "level+n": ("level", "n")}


INITS = ("grid", "points", "triangulated", "refracted")


@dataclass(frozen=True)
class TrainConfig:
    variant: str = "full"
    preset: str = "small"
    seed: int = 0
    iterations: int = 1500
    # initialisation: "grid" (the paper: a horizontal grid at the bed depth), "points" (a point cloud file) or
    # "triangulated" (points triangulated from the training images with their known poses, pycolmap, depths
    # below the water x n) or "refracted" (the same tracks intersected along rays bent at the water)
    init: str = "grid"
    init_depth: float | None = None  # grid depth below the water level (m); None: scene.json spec.bed.depth
    # grid Gaussians (approximately: a square grid over the views' footprint), or at most this many points
    init_count: int = 10_000
    init_points: str | None = None  # .npy [N, 3] or [N, 6] (xyz, rgb in [0, 1]) for init="points"
    # a point start's gaps filled from its TIN (`tracks.fill_gaps`): grid nodes at this spacing (m) with no
    # point within it; 0: the points alone
    init_fill: float = 0.0
    init_opacity: float = 0.1
    sh_degree: int = 3
    sh_degree_every: int = 1000  # raise the active SH degree by one every this many iterations (at 30k)
    # Adam learning rates (3DGS / gsplat defaults); means decays exponentially to lr_means_final
    lr_means: float = 1.6e-4  # x scene scale (camera extent)
    lr_means_final: float = 1.6e-6
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacities: float = 5e-2
    lr_sh0: float = 2.5e-3
    lr_shN: float = 2.5e-3 / 20
    ssim_lambda: float = 0.2
    # Surfel variants only, 2DGS's two geometry terms: depth distortion (sum w_i w_j |z_i - z_j| per pixel, in
    # metres here; 2DGS weighs an NDC-mapped depth) and normal consistency (1 - rendered normal . normal of
    # the rendered depth map), each switched on after a fraction of the run (2DGS: 3k and 7k of 30k).
    lambda_distortion: float = 0.1
    lambda_normal: float = 0.05
    distortion_from: float = 0.1
    normal_from: float = 0.23
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    densify: DensifyConfig = field(default_factory=DensifyConfig)  # at 30k iterations; scaled to `iterations`
    backend: str = "auto"
    device: str = "auto"  # "auto": CUDA when available, else CPU
    # The refraction transform through torch.compile (`compiled_refract_gaussians`): fewer kernel launches on a
    # GPU, where the eager transform is launch-bound; a compile at the start. Not yet timed on a GPU (issue 29).
    compile_refraction: bool = False
    checkpoint_every: int | None = None  # None: every 10 % of the run; 0: only at the end (and on interrupt)
    # The water plane: the dataset's unless overridden (on a dataset without water, water_level adds one with
    # water_n or 1.33). optimize_water calibrates it from the images: "level" or "level+n", each with its
    # own Adam step size (Adam moves a parameter by about its lr per step).
    water_level: float | None = None  # metres, the model's frame (a sloping surface's height at x = y = 0)
    water_n: float | None = None
    # (dz/dx, dz/dy) of a sloping surface; (0, 0) makes a sloping dataset's water one level (a flat-water tool)
    water_slope: tuple[float, float] | None = None
    optimize_water: str = "none"  # "none" | "level" | "level+n"
    # Absolute metres, not x camera extent as the means: how far the level is off is set by how it was
    # measured (a GNSS point on the waterline, a few cm to dm), not by how wide the survey is.
    lr_water_level: float = 1e-3
    lr_water_n: float = 1e-4  # water's n spans 1.33-1.34 with temperature and salinity
    # Fraction of the run before the water moves: while densification runs (to half the run) the Gaussians
    # are cloned, split, pruned and their opacities reset every 10 %, and a level moved against that
    # half-built bed absorbs its depth errors (measured on the small reach with 0: a level 10 cm high rose
    # to 20 cm while the bed was still the initial plane, and ended 16 cm high).
    water_warmup: float = 0.5
    # The attenuation coefficients (variants with "attenuation" in `WATER_TERMS`), trained as log c: the start
    # (1/m, every channel; a clear river's order) and the Adam rate in log c. Adam moves log c by about its lr a
    # step, so 1e-2 crosses the range's factor of 500 (6.2 in log) in a fifth of a 3 000-step run and ends
    # within about 1 % a step of where the images put it.
    attenuation_start: float = 0.1
    lr_attenuation: float = 1e-2
    # The backscatter (variants with "backscatter" in `WATER_TERMS`), trained as log B_inf and log c_b, every
    # channel from the same start: a faint veil (0.05 linear, a dark river's; with 0.1 1/m, 0.006 at 1 m depth,
    # under two 8-bit steps at the bed's mid-greys) that the images raise; the Adam rate as the attenuation's.
    veil_start: float = 0.05
    backscatter_start: float = 0.1
    lr_backscatter: float = 1e-2
    # The sky the surface mirrors (variants with "reflection" in `WATER_TERMS`), a map trained as log radiance,
    # every texel from the same start: a grey sky of 0.3 (linear; the sky's order at the images' exposure), which
    # R = 0.02 at nadir shows as 0.006, under two 8-bit steps at the bed's mid-greys, and the images move: the
    # glint's texels up, by a factor of 100 in 460 steps where seen, at the Adam rate of the other terms.
    sky_start: float = 0.3
    lr_reflection: float = 1e-2

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ConfigError(f"unknown variant {self.variant!r}; choose one of {', '.join(VARIANTS)}")
        if self.iterations < 1:
            raise ConfigError(f"iterations must be >= 1, got {self.iterations}")
        if self.init not in INITS:
            raise ConfigError(f"init must be one of {', '.join(INITS)}, got {self.init!r}")
        if self.init == "points" and not self.init_points:
            raise ConfigError("init='points' needs init_points (--init-points: a .npy point cloud)")
        if not 0 <= self.sh_degree <= 3:
            raise ConfigError(f"sh_degree must be 0..3, got {self.sh_degree}")
        if self.checkpoint_every is not None and self.checkpoint_every < 0:
            raise ConfigError(f"checkpoint_every must be >= 0, got {self.checkpoint_every}")
        if not (math.isfinite(self.init_fill) and self.init_fill >= 0):
            raise ConfigError(f"init_fill is a spacing in metres and must be >= 0, got {self.init_fill}")
        if self.init_fill > 0 and self.init == "grid":
            raise ConfigError("init_fill fills the gaps between a start's points; init='grid' has none "
                              "(--init-fill 0)")
        if self.init_depth is not None and not self.init_depth > 0:
            raise ConfigError(f"init_depth is a depth below the water level and must be > 0, got {self.init_depth}")
        if self.water_level is not None and not math.isfinite(self.water_level):
            raise ConfigError(f"water_level must be finite, got {self.water_level}")
        if self.water_slope is not None and not (len(self.water_slope) == 2 and all(
                math.isfinite(v) and abs(v) < 1 for v in self.water_slope)):
            raise ConfigError(f"water_slope is (dz/dx, dz/dy), each finite and under 1, got {self.water_slope}")
        if self.water_n is not None and not (math.isfinite(self.water_n) and self.water_n >= 1):
            raise ConfigError(f"water_n is a refractive index and must be finite and >= 1, got {self.water_n}")
        if self.optimize_water not in WATER_PARAMS:
            raise ConfigError(f"optimize_water must be one of {', '.join(WATER_PARAMS)}, got {self.optimize_water!r}")
        if self.optimize_water != "none" and VARIANTS[self.variant] is None:
            raise ConfigError(f"optimize_water={self.optimize_water!r} needs a variant that models the water; "
                              f"{self.variant!r} never refracts")
        for name in ("lr_water_level", "lr_water_n"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ConfigError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 0 <= self.water_warmup < 1:
            raise ConfigError(f"water_warmup is a fraction of the run in [0, 1), got {self.water_warmup}")
        lo, hi = ATTENUATION_RANGE
        if not lo <= self.attenuation_start <= hi:
            raise ConfigError(f"attenuation_start is a coefficient in 1/m within [{lo:g}, {hi:g}], got "
                              f"{self.attenuation_start}")
        if not (math.isfinite(self.lr_attenuation) and self.lr_attenuation > 0):
            raise ConfigError(f"lr_attenuation must be > 0, got {self.lr_attenuation}")
        for name, (lo, hi) in (("veil_start", VEIL_RANGE), ("backscatter_start", BACKSCATTER_RANGE)):
            if not lo <= getattr(self, name) <= hi:
                raise ConfigError(f"{name} must lie within [{lo:g}, {hi:g}], got {getattr(self, name)}")
        if not (math.isfinite(self.lr_backscatter) and self.lr_backscatter > 0):
            raise ConfigError(f"lr_backscatter must be > 0, got {self.lr_backscatter}")
        lo, hi = SKY_RANGE
        if not lo <= self.sky_start <= hi:
            raise ConfigError(f"sky_start is a linear radiance within [{lo:g}, {hi:g}], got {self.sky_start}")
        if not (math.isfinite(self.lr_reflection) and self.lr_reflection > 0):
            raise ConfigError(f"lr_reflection must be > 0, got {self.lr_reflection}")

    @property
    def surfels(self) -> bool:
        return self.variant in SURFELS

    @property
    def schedule(self) -> DensifyConfig:
        """The densification schedule stretched to this run's iteration count."""
        return self.densify.scaled(self.iterations)

    @property
    def water_params(self) -> tuple[str, ...]:
        """The WaterSurface fields calibrated in this run."""
        return WATER_PARAMS[self.optimize_water]

    @property
    def water_terms(self) -> tuple[str, ...]:
        """The terms of the water's optics this run's variant trains (`WATER_TERMS`)."""
        return WATER_TERMS.get(self.variant, ())

    @property
    def water_start(self) -> int:
        """The last step with the water frozen (warm-up)."""
        return round(self.water_warmup * self.iterations)

    @property
    def checkpoint_interval(self) -> int:
        """Steps between checkpoints (0: none before the end)."""
        return max(1, self.iterations // 10) if self.checkpoint_every is None else self.checkpoint_every

    @property
    def sh_every(self) -> int:
        return max(1, round(self.sh_degree_every * self.iterations / PAPER_ITERATIONS))

    def active_sh_degree(self, step: int) -> int:
        """The SH degree in use after `step` steps (raised by one every `sh_every`)."""
        return min(self.sh_degree, step // self.sh_every)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["background"] = list(self.background)
        d["refraction"] = VARIANTS[self.variant]
        d["water_terms"] = list(self.water_terms)
        d["densify_scaled"] = asdict(self.schedule)
        d["sh_every_scaled"] = self.sh_every
        d["water_start_scaled"] = self.water_start
        return d

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        names = {f.name for f in fields(cls)}
        kw = {k: v for k, v in d.items() if k in names}
        kw["densify"] = DensifyConfig(**kw.get("densify", {}))
        kw["background"] = tuple(kw.get("background", (0.0, 0.0, 0.0)))
        return cls(**kw)


# Presets: smoke (CI, seconds), small (the 2-core CPU default of `make ablation`), small-field (small for field
# conditions, `FIELD_TUNING`), paper (30k, a GPU).
# The short presets start the position rate higher than 3DGS's 1.6e-4: with the 30k schedule squeezed into
# 1500 steps the default rate lets a Gaussian travel at most about 0.3 m (sum of the per-step rates x
# extent), less than the refraction shift it must be free to follow (0.74 m at 3 m depth).
SHORT_LR_MEANS = 1.6e-3  # smoke (CI): a scale argument, not tuned
# `small` was tuned on the development dataset in `TUNING`, never on the evaluation dataset (README,
# "Protocol"): the `small` reach rendered with dataset seed 1 (evaluation: seed 0), full variant, training
# seed 0, the value with the best F1 at 3 % of depth. results.json repeats this record.
SMALL_LR_MEANS = 5e-3
# 2DGS's normal consistency at 0.05 smooths the bed's stones at this resolution: a fifth of it (TUNING["surfel_terms"]).
SMALL_LAMBDA_NORMAL = 0.01
# The photometric loss weighs (1 - SSIM) at 0.8, not 3DGS's 0.2: the bed's fine relief shows in the images'
# structure more than in their mean colour (TUNING["ssim_lambda"]).
SMALL_SSIM_LAMBDA = 0.8
# Densification stops at 30 % of the run, not 3DGS's half: the cap is reached early on this reach, and the
# steps without cloning, pruning or opacity resets settle the bed (TUNING["refine_stop"]). At the 30k scale.
SMALL_REFINE_STOP = 9_000
# 3 000 steps, not 1 500: the surfel bed keeps sharpening after 1 500 on the development reach, 1.3-2.2 points at
# 1 % of depth on both seeds, for twice the training time, and 4 500 gain nothing more (TUNING["length"]); the
# field preset already trains as long. Chosen for the best variant: `full` loses at 3 000 (4 points at 1 %, seed
# 0), and keeps the same preset so that the rows differ by their model alone.
SMALL_ITERATIONS = 3000
# What the later tuning records below score a bed by (`eval.tune`'s figures), and their two selection rules.
BED_COLUMNS = ["F1@1% (%)", "F1@3% (%)", "wet RMSE (cm)", "wet p95 (cm)", "wet cover (%)"]
RULE_1PCT = "max F1@1% (mean of the two seeds) among settings within 0.5 point of the best F1@3%"
FIELD_RULE = "max F1@3% of 2dgs+full, on both seeds"
TUNING = {"preset": "small", "dataset_preset": "small", "dataset_seed": 1, "training_seed": 0,
          "chosen": {"lr_means": SMALL_LR_MEANS}, "tried": {"lr_means": [5e-4, 1.6e-3, 5e-3]},
          "rule": "max F1@3% of the full variant",
          "command": "python -m eval.tune --data data/small-dev --out runs/tune --values 5e-4 1.6e-3 5e-3",
          # A smaller cap or a shorter run would make `make ablation` faster; both cost bed accuracy on the
          # development reach (refracted start, one thread per run, two runs at a time), so neither was taken.
          "speed": {"kept": {"densify.max_gaussians": 40_000, "iterations": 1500},
                    "columns": ["F1@3% (%)", "F1@1% (%)", "wet RMSE (cm)", "wet cover (%)", "training (s)"],
                    "tried": {"full seed 0": {"40k": [95.0, 71.3, 5.3, 90.5, 276], "20k": [94.5, 73.4, 4.6, 87.5, 190],
                                              "20k, 1000 iterations": [92.5, 69.5, 4.4, 81.7, 110]},
                              "full seed 1": {"40k": [95.6, 74.9, 5.9, 89.6, 221], "20k": [94.3, 74.0, 4.2, 86.3, 195]},
                              "2dgs+full seed 0": {"40k": [97.0, 77.6, 4.1, 94.5, 410],
                                                   "20k": [95.6, 76.4, 4.0, 91.0, 330]}},
                    "rule": "the cheaper setting only if its F1@3% and wet cover are within the seed spread of 40k",
                    "measured_with": "ragsplat ablation --preset small --data data/small-dev --init refracted "
                                     "--jobs 1 --seeds S --variants V, the preset's cap and length set by a "
                                     "driver script (not kept)",
                    "same_configs": "python -m eval.tune --data data/small-dev --out runs/tune-cap "
                                    "--param densify.max_gaussians --values 20000 40000 --variants full 2dgs+full"},
          # Later, for the 1 % band (issue 26), the surfels' two geometry terms and a larger cap, 2dgs+full only
          # (the terms act on surfels alone), the default extraction, training seed 0, then seed 1 as a check;
          # each row is 2DGS's weights (normal 0.05, distortion 0.1) with the named ones changed:
          "surfel_terms": {
              "chosen": {"lambda_normal": SMALL_LAMBDA_NORMAL},
              "rule": "max F1@1% among settings within 0.5 point of the best F1@3%, wet cover >= 85 %",
              "columns": BED_COLUMNS,
              "tried": {"seed 0": {"2DGS's": [78.0, 97.5, 3.7, 7.3, 96.7],
                                   "lambda_normal 0.2": [66.8, 95.3, 5.3, 10.6, 96.6],
                                   "lambda_normal 0.01": [81.3, 97.5, 3.2, 6.4, 95.7],
                                   "lambda_normal 0": [81.1, 97.5, 3.1, 6.1, 94.7],
                                   "lambda_distortion 0.01": [71.3, 96.1, 4.9, 10.0, 96.8],
                                   "lambda_distortion 0.3, lambda_normal 0.01": [77.3, 97.7, 3.5, 7.2, 96.5],
                                   "densify.max_gaussians 80000": [74.1, 97.6, 4.2, 8.4, 98.4]},
                        "seed 1": {"2DGS's": [78.1, 97.7, 3.8, 7.2, 97.3],
                                   "lambda_normal 0.01": [81.7, 97.7, 3.4, 6.3, 96.8]}},
              "command": "python -m eval.tune --data data/small-dev --out DIR --param P --values V "
                         "--variants 2dgs+full --seed S"},
          # Then, with normal 0.01, the loss's SSIM weight, the position rate, densification's threshold and the
          # SH degree (2dgs+full, each row the preset with the named one changed; the base row is seed 0's
          # "lambda_normal 0.01" above and seed 1's below it):
          "ssim_lambda": {
              "chosen": {"ssim_lambda": SMALL_SSIM_LAMBDA},
              "rule": RULE_1PCT,
              "columns": BED_COLUMNS,
              "tried": {"seed 0": {"ssim_lambda 0.2 (3DGS)": [81.3, 97.5, 3.2, 6.4, 95.7],
                                   "ssim_lambda 0.1": [77.3, 97.1, 4.0, 8.1, 96.4],
                                   "ssim_lambda 0.4": [82.4, 98.0, 3.2, 6.6, 97.1],
                                   "ssim_lambda 0.6": [82.5, 98.1, 3.5, 6.2, 96.9],
                                   "ssim_lambda 0.8": [82.9, 98.3, 3.4, 6.3, 97.4],
                                   "ssim_lambda 1": [81.9, 97.9, 4.0, 7.0, 97.2],
                                   "lr_means 2.5e-3": [80.3, 97.4, 3.6, 7.4, 96.7],
                                   "lr_means 1e-2": [80.2, 97.9, 3.5, 6.9, 96.9],
                                   "densify.grow_grad2d 1e-4": [79.9, 97.7, 3.7, 7.3, 97.3],
                                   "densify.grow_grad2d 4e-4": [80.0, 97.4, 3.7, 6.9, 96.1],
                                   "sh_degree 1": [81.9, 97.8, 3.1, 6.2, 96.0]},
                        "seed 1": {"ssim_lambda 0.2 (3DGS)": [81.7, 97.7, 3.4, 6.3, 96.8],
                                   "ssim_lambda 0.4": [82.7, 98.0, 3.2, 6.3, 97.1],
                                   "ssim_lambda 0.6": [82.7, 98.3, 3.5, 6.5, 97.8],
                                   "ssim_lambda 0.8": [82.4, 98.3, 3.6, 6.6, 97.6]}},
              # the same loss for the 3DGS rows of the preset: `full`, seed 0, checked before it was kept
              "full seed 0": {"ssim_lambda 0.2 (3DGS)": [70.4, 94.0, 5.3, 12.2, 95.6],
                              "ssim_lambda 0.8": [75.6, 95.9, 4.8, 10.4, 96.5]},
              "command": "python -m eval.tune --data data/small-dev --out DIR --param P --values V "
                         "--variants 2dgs+full --seed S"},
          # Then, with SSIM 0.8, where densification stops (3DGS: 15k of 30k, here 750 of 1500 steps), the
          # base rows being the "ssim_lambda 0.8" ones above:
          "refine_stop": {
              "chosen": {"densify.refine_stop_iter": SMALL_REFINE_STOP},
              "rule": RULE_1PCT,
              "columns": BED_COLUMNS,
              "tried": {"seed 0": {"15000 (3DGS)": [82.9, 98.3, 3.4, 6.3, 97.4],
                                   "6000": [83.9, 98.2, 3.7, 6.3, 97.9], "9000": [83.9, 98.3, 3.5, 6.1, 97.8],
                                   "22500": [81.7, 97.7, 3.5, 6.3, 95.6],
                                   "densify.reset_every 6000": [82.9, 98.3, 3.0, 6.1, 97.1],
                                   "densify.reset_every 30000 (no reset)": [83.0, 98.4, 3.4, 6.1, 97.7]},
                        "seed 1": {"15000 (3DGS)": [82.4, 98.3, 3.6, 6.6, 97.6],
                                   "6000": [83.1, 98.5, 3.5, 6.6, 98.5], "9000": [83.3, 98.7, 3.5, 6.7, 98.5]}},
              "full seed 0": {"15000 (3DGS)": [75.6, 95.9, 4.8, 10.4, 96.5], "9000": [78.2, 96.6, 4.3, 9.3, 97.1]},
              "command": "python -m eval.tune --data data/small-dev --out DIR --param densify.refine_stop_iter "
                         "--values V --variants 2dgs+full --seed S"},
          # Then, with that stop, a longer run and a larger cap (each row the preset at 1 500 steps with the named
          # one changed):
          "length": {"chosen": {"iterations": SMALL_ITERATIONS},
                     "rule": RULE_1PCT,
                     "columns": BED_COLUMNS,
                     "tried": {"seed 0": {"iterations 1500": [83.9, 98.3, 3.5, 6.1, 97.8],
                                          "iterations 2000": [84.8, 98.6, 3.6, 5.8, 98.4],
                                          "iterations 3000": [85.2, 99.0, 3.4, 5.7, 98.9],
                                          "iterations 4500": [85.0, 98.9, 3.1, 5.6, 98.7],
                                          "densify.max_gaussians 60000": [83.1, 98.4, 3.8, 6.7, 98.6]},
                               "seed 1": {"iterations 1500": [83.3, 98.7, 3.5, 6.7, 98.5],
                                          "iterations 2000": [84.4, 98.9, 3.2, 6.0, 98.5],
                                          "iterations 3000": [85.5, 99.1, 3.0, 5.6, 98.8],
                                          "iterations 4500": [85.4, 98.9, 3.1, 5.8, 98.7]},
                               "full seed 0": {"iterations 1500": [78.2, 96.6, 4.3, 9.3, 97.1],
                                               "iterations 2000": [78.3, 97.1, 4.1, 8.7, 97.3],
                                               "iterations 3000": [74.3, 95.1, 5.3, 12.3, 98.0]}},
                     # 2dgs+full, one thread each, two runs at a time
                     "training_s": {"1500": 470, "3000": 1000, "4500": 1450},
                     "command": "python -m eval.tune --data data/small-dev --out DIR --param P --values V "
                                "--variants V --seed S"}}
# `small-field`: the `small` preset for photos under field conditions (turbid, reflecting, rippled water), tuned
# on the development seed of the `small-field` dataset, never on its evaluation seed: the 2 x 2 of iterations and
# the start's fill below (2dgs+full, refracted start, training seed 0, one thread per run, two runs at a time).
FIELD_TUNING = {"preset": "small-field", "dataset_preset": "small-field", "dataset_seed": 1, "training_seed": 0,
                "variant": "2dgs+full", "chosen": {"iterations": 3000, "init_fill": 0.2},
                "rule": "max F1@3% of 2dgs+full",
                "columns": BED_COLUMNS + ["training (s)"],
                "tried": {"1500, no fill": [62.6, 87.7, 8.8, 13.7, 81.3, 487],
                          "3000, no fill": [62.5, 88.1, 11.5, 9.1, 76.8, 951],
                          "1500, fill 0.2 m": [66.0, 87.9, 6.1, 8.2, 76.3, 476],
                          "3000, fill 0.2 m": [66.9, 89.1, 4.3, 7.3, 75.5, 895]},
                "command": "python -m eval.tune --data data/small-field-s1 --out runs/tune-field-fillF --param "
                           "iterations --values 3000 1500 --set init_fill=F --variants 2dgs+full (F = 0, 0.2)",
                # Later, `small`'s weaker normal term (TUNING["surfel_terms"]) checked here before it was kept:
                # 3 000 iterations, fill 0.2 m, the default extraction (one-cell fill), training seeds 0 and 1.
                "lambda_normal": {"kept": SMALL_LAMBDA_NORMAL, "rule": FIELD_RULE,
                                  "columns": BED_COLUMNS,
                                  "tried": {"0.05 (2DGS)": {"seed 0": [68.5, 90.8, 4.7, 8.4, 83.5],
                                                            "seed 1": [67.9, 89.8, 6.1, 8.8, 82.6]},
                                            "0.01": {"seed 0": [71.3, 91.5, 6.8, 8.2, 85.0],
                                                     "seed 1": [70.6, 90.9, 6.8, 8.4, 84.5]}},
                                  "command": "python -m eval.tune --data data/small-field-s1 --out DIR --preset "
                                             "small-field --param lambda_normal --values 0.01 --variants 2dgs+full "
                                             "--seed S (0.05: the runs above, rescored by `ragsplat eval`)"},
                # and `small`'s SSIM weight (TUNING["ssim_lambda"]), checked the same way with normal 0.01:
                "ssim_lambda": {"kept": SMALL_SSIM_LAMBDA, "rule": FIELD_RULE,
                                "columns": BED_COLUMNS,
                                "tried": {"0.2 (3DGS)": {"seed 0": [71.3, 91.5, 6.8, 8.2, 85.0],
                                                         "seed 1": [70.6, 90.9, 6.8, 8.4, 84.5]},
                                          "0.8": {"seed 0": [73.4, 95.1, 5.2, 8.9, 93.7],
                                                  "seed 1": [73.1, 94.7, 8.2, 9.7, 93.6]}},
                                "command": "python -m eval.tune --data data/small-field-s1 --out DIR --preset "
                                           "small-field --param ssim_lambda --values 0.8 --variants 2dgs+full "
                                           "--seed S (0.2: the lambda_normal 0.01 runs above)"},
                # and `small`'s earlier densification stop (TUNING["refine_stop"]), checked the same way with
                # SSIM 0.8: no gain at 3 % on either seed, so the field keeps 3DGS's stop (half the run)
                "refine_stop": {"kept": {"densify.refine_stop_iter": 15_000},
                                "rule": FIELD_RULE,
                                "columns": BED_COLUMNS,
                                "tried": {"15000 (3DGS)": {"seed 0": [73.4, 95.1, 5.2, 8.9, 93.7],
                                                           "seed 1": [73.1, 94.7, 8.2, 9.7, 93.6]},
                                          "9000": {"seed 0": [72.7, 94.8, 5.1, 9.3, 93.4],
                                                   "seed 1": [73.2, 94.6, 7.3, 9.9, 94.2]}},
                                "command": "python -m eval.tune --data data/small-field-s1 --out DIR --preset "
                                           "small-field --param densify.refine_stop_iter --values 9000 "
                                           "--variants 2dgs+full --seed S (15000: the ssim_lambda 0.8 runs)"}}
PRESETS: dict[str, TrainConfig] = {
    "smoke": TrainConfig(preset="smoke", iterations=150, init_count=1_500, sh_degree=1,
                         lr_means=SHORT_LR_MEANS, densify=DensifyConfig(max_gaussians=4_000)),
    "small": TrainConfig(preset="small", iterations=SMALL_ITERATIONS, init_count=16_000, lr_means=SMALL_LR_MEANS,
                         lambda_normal=SMALL_LAMBDA_NORMAL, ssim_lambda=SMALL_SSIM_LAMBDA,
                         densify=DensifyConfig(max_gaussians=40_000, refine_stop_iter=SMALL_REFINE_STOP)),
    "paper": TrainConfig(preset="paper", iterations=30_000, init_count=40_000),
}
# small-field keeps 3DGS's densification stop: `SMALL_REFINE_STOP` gained nothing on its development seed
# (FIELD_TUNING["refine_stop"])
PRESETS["small-field"] = replace(PRESETS["small"], preset="small-field", init="refracted",
                                 densify=DensifyConfig(max_gaussians=40_000), **FIELD_TUNING["chosen"])
# The `3dgs` row as its own field would train it (issue 46): `small`'s size and length, but 3DGS's loss (SSIM
# weight 0.2) and densification stop (half the run) instead of the values tuned for `2dgs+full`.
PRESETS["small-3dgs"] = replace(PRESETS["small"], preset="small-3dgs", ssim_lambda=TrainConfig.ssim_lambda,
                                densify=DensifyConfig(max_gaussians=40_000))


def preset_config(name: str, **overrides) -> TrainConfig:
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return replace(PRESETS[name], **overrides)
