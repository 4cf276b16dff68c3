"""Field conditions as geometry and numbers for the renderer (numpy only): the rippled water surface and
its per-photo phases, the water body that attenuates, and the ground control targets on the banks.

Ripples: a seeded sum of `ripple_waves` sinusoids, wavelengths log-uniform between the spec's shortest and
longest, directions spread about one wind direction, each wave as steep as the others (amplitude in
proportion to wavelength), scaled so that the surface's rms height is `ripple_amplitude`. Every photo draws
its own phases from (seed, view index): a new surface per photo, the same one on a rerun or in any shard.
The mean surface is the level (a sum of cosines with independent phases has mean zero); the ground truth
stays the bed. Towards the bed's border the ripples fade to the flat plane that continues to the horizon.
Like the bed (`ragsplat.datagen.bed`), everything here is made in the flat scene; under a sloping water
surface the generator shears it (`ragsplat.datagen.bed.shear`), so the ripples ride on the sloping mean
surface and the water body's top stays parallel to it.
"""

from __future__ import annotations

import math

import numpy as np

from ragsplat.datagen.bed import _smoothstep, grid_triangles
from ragsplat.datagen.spec import FieldConditions, SceneSpec
from ragsplat.errors import SpecError

# Random streams of the conditions, apart from the bed's own (`make_bed` draws from default_rng(seed)).
_WAVES, _PHASES, _TARGETS = 1, 2, 3
TARGET_LIFT = 0.005  # m: a target lies this far above the highest ground under it (no z-fighting)
TARGET_TILT = 20.0  # deg: the steepest ground a (level) target is laid on
TARGET_ALBEDO = (0.04, 0.85)  # the targets' black and white (linear diffuse albedo)
# The Secchi-like depth: where the bed's contrast seen from above has fallen to this share of its contrast at
# the surface (5 %: three e-foldings of the two-way path)
CONTRAST_SHARE = 0.05


def ripple_waves(c: FieldConditions, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(wave vectors [K, 2] rad/m, amplitudes [K] m) of the seeded spectrum (see the module docstring)."""
    rng = np.random.default_rng([seed, _WAVES])
    shortest, longest = c.ripple_wavelengths
    wavelength = np.exp(rng.uniform(math.log(shortest), math.log(longest), c.ripple_waves))
    wind = rng.uniform(0, 2 * math.pi)
    direction = wind + rng.normal(0.0, math.radians(35.0), c.ripple_waves)  # spread about the wind
    k = (2 * math.pi / wavelength)[:, None] * np.stack([np.cos(direction), np.sin(direction)], -1)
    amplitude = wavelength * c.ripple_amplitude / math.sqrt(0.5 * np.sum(wavelength**2))  # rms = amplitude
    return k, amplitude


def ripple_phases(c: FieldConditions, seed: int, view: int) -> np.ndarray:
    """Phases [K] (rad) of photo `view`'s surface."""
    return np.random.default_rng([seed, _PHASES, view]).uniform(0, 2 * math.pi, c.ripple_waves)


def ripple_height(xy: np.ndarray, k: np.ndarray, amplitude: np.ndarray, phases: np.ndarray) -> np.ndarray:
    """Height [N] (m, about the level) at points xy [N, 2] of the surface with waves (k [K, 2], amplitude
    [K]) and phases [K]."""
    return np.cos(xy @ k.T + phases) @ amplitude


def ripple_gradient(xy: np.ndarray, k: np.ndarray, amplitude: np.ndarray, phases: np.ndarray) -> np.ndarray:
    """[N, 2] (dz/dx, dz/dy) of `ripple_height`'s surface at points xy [N, 2]."""
    return -(np.sin(xy @ k.T + phases) * amplitude) @ k


def ripple_slope(k: np.ndarray, amplitude: np.ndarray) -> float:
    """rms slope (rad, small angles) of the spectrum: sqrt(sum (a |k|)^2 / 2)."""
    return float(np.sqrt(0.5 * np.sum((amplitude * np.linalg.norm(k, axis=1)) ** 2)))


def water_surface(spec: SceneSpec, size: float, far: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices [V, 3] at the level, triangles [F, 3] counter-clockwise from above, ripple weight [V]) of
    the water: a grid of `ripple_cell` over the centred `size` square whose ripples fade to zero over the
    bed's taper, in a flat frame out to +-far."""
    c = spec.conditions
    count = math.ceil(size / c.ripple_cell) + 1
    xs = np.linspace(-size / 2, size / 2, count)
    gx, gy = np.meshgrid(xs, xs)
    inner = size / 2 - np.maximum(np.abs(gx), np.abs(gy))  # distance to the grid's edge
    weight = _smoothstep(inner / spec.bed.taper).ravel()  # 0 on the edge, 1 inside the taper
    verts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, spec.level)], -1)
    tris = [grid_triangles(count)]
    # The frame: four trapezoids from the grid's corners out to the corners of +-far.
    f, n = far, len(verts)
    outer = np.array([[-f, -f, spec.level], [f, -f, spec.level], [f, f, spec.level], [-f, f, spec.level]])
    corner = [0, count - 1, count * count - 1, count * (count - 1)]  # the grid's, in the outer corners' order
    # The grid's edges carry intermediate vertices the frame's triangles do not share: the surface is flat
    # there (weight 0), so the T-junctions leave no gap.
    tris.append(_triangles([(n + q, n + (q + 1) % 4, corner[(q + 1) % 4], corner[q]) for q in range(4)]))
    verts = np.concatenate([verts, outer])
    weight = np.concatenate([weight, np.zeros(4)])
    return verts, np.concatenate(tris), weight


def water_body(spec: SceneSpec, bottom: float, far: float) -> tuple[np.ndarray, np.ndarray]:
    """(vertices [8, 3], triangles [12, 3], outward) of the closed box that holds the water's volume: from
    `bottom` (below the bed) to 1 mm below four rms ripple heights (the water above it is clear; a trough
    reaches below it with a probability of about 1e-4), +-far across. Its faces are volume boundaries only
    (no surface), so light crosses them unbent; the refracting surface is `water_surface`."""
    c = spec.conditions
    top = spec.level - 4 * c.ripple_amplitude - 0.001
    x = np.array([-far, far])
    verts = np.array([[x[i], x[j], z] for z in (bottom, top) for j in (0, 1) for i in (0, 1)])
    # 0..3 bottom (y-, x- first), 4..7 top; faces counter-clockwise seen from outside.
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    return verts, _triangles(quads)


def _triangles(quads) -> np.ndarray:
    """[2 Q, 3] from Q quads (a, b, c, d) in order around each: (a, b, c) and (a, c, d)."""
    return np.array([t for q in quads for t in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))])


def attenuation(c: FieldConditions) -> tuple[np.ndarray, np.ndarray]:
    """(absorption [3], scattering [3]) coefficients (1/m, linear RGB) of the water body."""
    return np.array(c.absorption) * c.turbidity, np.array(c.scattering) * c.turbidity


def place_targets(c: FieldConditions, height, banks: np.ndarray, level: float, seed: int) -> np.ndarray:
    """Centres [T, 3] of `c.targets` ground control targets on dry ground, far apart: on the emerged
    ground-truth points `banks` [B, 3] whose whole target square stays 3 cm above the water and whose
    ground under it is within TARGET_TILT of level; `height(xy [N, 2]) -> [N]` is the ground. A target is
    a level board just clear of the highest ground under it; its centre, the point a surveyor measures,
    is on the board."""
    from ragsplat.datagen.survey import spread

    half = c.target_size / 2
    offsets = np.array([[sx, sy] for sx in (-half, 0, half) for sy in (-half, 0, half)])
    under = height((banks[:, None, :2] + offsets).reshape(-1, 2)).reshape(len(banks), -1)  # [B, 9]
    tilt = np.hypot(under[:, 7] - under[:, 1], under[:, 5] - under[:, 3]) / (2 * half)  # central differences
    good = (under.min(1) > level + 0.03) & (tilt < math.tan(math.radians(TARGET_TILT)))
    if good.sum() < c.targets:
        raise SpecError(f"only {good.sum()} places on the banks fit a {c.target_size} m target "
                        f"({c.targets} wanted): fewer or smaller targets, or another seed")
    chosen = spread(banks[good], c.targets, np.random.default_rng([seed, _TARGETS]))
    return np.column_stack([chosen[:, :2], height(chosen[:, :2]) + _lift(c, height, chosen)])


def _lift(c: FieldConditions, height, centres: np.ndarray) -> np.ndarray:
    """Height [T] of each (horizontal) target above the ground at its centre: clear of every bump under it."""
    half = c.target_size / 2
    s = np.linspace(-half, half, 7)
    offsets = np.stack(np.meshgrid(s, s), -1).reshape(-1, 2)
    under = height((centres[:, None, :2] + offsets).reshape(-1, 2)).reshape(len(centres), -1)
    return under.max(1) - height(centres[:, :2]) + TARGET_LIFT


def target_meshes(c: FieldConditions, centres: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{"black": (verts, tris), "white": (verts, tris)}: each target a horizontal square of 2 x 2 squares,
    black on the diagonal through (-x, -y), centred on its centre [T, 3]."""
    half = c.target_size / 2
    parts = {"black": [(-1, -1), (0, 0)], "white": [(0, -1), (-1, 0)]}  # lower-left corner of each square
    out = {}
    for colour, squares in parts.items():
        verts = []
        for centre in centres:
            for i, j in squares:
                x0, y0 = centre[0] + i * half, centre[1] + j * half
                verts += [[x0, y0, centre[2]], [x0 + half, y0, centre[2]], [x0 + half, y0 + half, centre[2]],
                          [x0, y0 + half, centre[2]]]
        o = 4 * np.arange(len(verts) // 4)[:, None]
        tris = np.concatenate([o + [0, 1, 2], o + [0, 2, 3]])
        out[colour] = (np.array(verts, float), tris)
    return out


def secchi_depth(extinction, sun_elevation_deg: float) -> np.ndarray:
    """The Secchi-like depth (m) per channel [3]: the depth at which a nadir view's contrast of the bed (the
    radiance difference between two albedos) falls to CONTRAST_SHARE of its value at the surface. The
    sunlight reaches the bed along the straight shadow ray, as the renderer attenuates it (z / sin of the
    sun's elevation; docs/benchmark.md), and the view leaves it along z, both dimmed by exp(-c L), c the
    extinction (absorption plus scattering, 1/m); light scattered into the paths is left out, so this is the
    beam's depth. inf where c = 0."""
    c = np.asarray(extinction, float)  # [3]
    path = 1.0 + 1.0 / math.sin(math.radians(sun_elevation_deg))  # metres of path per metre of depth
    with np.errstate(divide="ignore"):
        return np.where(c > 0, math.log(1.0 / CONTRAST_SHARE) / (c * path), np.inf)


def figures(spec: SceneSpec) -> dict:
    """What scene.json records of the conditions, for a reader of the dataset's figures: the coefficients
    in force and the ripples' slope, beside the spec's own settings."""
    c = spec.conditions
    absorption, scattering = attenuation(c)
    k, amplitude = ripple_waves(c, spec.seed)
    secchi = secchi_depth(absorption + scattering, spec.light.sun_elevation)
    return {"absorption_per_m": absorption.tolist(), "scattering_per_m": scattering.tolist(),
            "extinction_per_m": (absorption + scattering).tolist(),
            "secchi_like_depth_m": [float(v) if math.isfinite(v) else None for v in secchi],
            "reflection": c.reflection,
            "ripple_rms_m": c.ripple_amplitude, "ripple_wavelengths_m": list(c.ripple_wavelengths),
            "ripple_rms_slope_deg": math.degrees(ripple_slope(k, amplitude)), "targets": c.targets,
            "sun_elevation_deg": spec.light.sun_elevation, "sun_azimuth_deg": spec.light.sun_azimuth}
