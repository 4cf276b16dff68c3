"""Seeded riverbed: heightfield, gravel albedo aligned to the stones, exact mesh and ground-truth grid.

The heightfield is built on the texel grid (x_i = x0 + i * texel, same in y; array index [j, i] = [y, x]);
the mesh takes every `stride`-th sample and splits each cell along the same diagonal, so the rendered surface
is exactly `height_at` and `gt/bed.ply`. Two kinds of relief, then rounded (half-ellipsoid) stones in a few
size classes merged by maximum:
- the paper's gravel bed: a sum of low-frequency waves around the mean plane z = level - depth; towards
  the border relief and stones fade into that plane and the albedo into periodic noise, so a flat floor
  textured with the same repeating image continues the bed seamlessly beyond its edge;
- a river reach (`ReachSpec`): a channel along x with pools, riffles, point bars and banks above the
  water; towards the border it fades into one cross-section `profile(y)`, which the floor extrudes along x
  to the horizon, with flat land beyond the banks.
Albedo: a per-stone colour with speckle, sand-coloured noise between stones, soil and grass on dry land.

Everything here is built in the flat scene, under the water plane z = level. A sloping water surface
(`WaterSpec.slope`) tilts the valley with it: the world is the flat scene sheared vertically, every height
z -> z + sx x + sy y (`shear`, `world_surface`), so vertical depths below the surface, what is wet and
the waterline are exactly the flat scene's. The generator shears what it writes; this module's functions
(`ground_truth`'s `z < level`, `waterline`) work in the flat scene.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ragsplat.datagen.spec import SceneSpec, ShoreSpec
from ragsplat.dataset.layout import Surface


@dataclass(frozen=True)
class Bed:
    x0: float  # world x (= y) of texel 0
    texel: float  # m
    stride: int  # mesh vertex every `stride` texels
    z0: float  # the flat floor height: level - depth (gravel bed) or the land beyond the banks (reach)
    heights: np.ndarray  # [M, M] float64 world z on the texel grid, index [j (y), i (x)]
    albedo: np.ndarray  # [M, M, 3] uint8 sRGB on the same grid
    profile: np.ndarray | None = None  # [M] world z of the border cross-section by texel row (reach only)

    @property
    def cell(self) -> float:
        return self.texel * self.stride

    @property
    def mesh_heights(self) -> np.ndarray:  # [K, K]
        return self.heights[:: self.stride, :: self.stride]

    @property
    def extent(self) -> float:
        """Side (m) of the mesh square."""
        return (self.mesh_heights.shape[0] - 1) * self.cell


def _periodic_noise(rng: np.random.Generator, m: int, wavelength_px: float) -> np.ndarray:
    """Zero-mean, unit-std Gaussian random field [m, m], periodic with period m, features ~wavelength_px."""
    k = np.fft.fftfreq(m)
    kk = np.hypot(*np.meshgrid(k, k))
    spectrum = np.exp(-0.5 * (kk * wavelength_px) ** 2)  # low-pass at ~1 / wavelength
    field = np.fft.ifft2(np.fft.fft2(rng.standard_normal((m, m))) * spectrum).real
    return (field - field.mean()) / field.std()


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def make_bed(spec: SceneSpec) -> Bed:
    b = spec.bed
    rng = np.random.default_rng(spec.seed)
    stride = round(b.cell / b.texel)
    cells = round(b.size / b.cell)
    m = cells * stride + 1
    x0 = -cells * b.cell / 2
    coords = x0 + np.arange(m) * b.texel  # [M]
    gx, gy = np.meshgrid(coords, coords)  # [M, M], index [j, i]
    reach = spec.reach

    if reach is None:
        # Low-frequency relief: peaks about the spec's amplitude, wavelengths >= b.wavelength.
        relief = _wave_field(rng, gx, gy, b.wavelength) * (b.undulation / 3.0)
        classes = list(b.stones)
    else:
        relief, profile = (_shore_relief(reach, b, gx, gy, coords, rng) if isinstance(reach, ShoreSpec)
                           else _reach_relief(reach, gx, gy, coords, rng))  # heights above the water level
        classes = [reach.boulders, *b.stones]

    # Stones: half-ellipsoids sunk 30 % into the relief, merged by maximum; `owner` remembers the top stone.
    z = relief.copy()
    owner = np.full((m, m), -1, dtype=np.int64)
    stones = []
    area = (m * b.texel) ** 2
    for cls in sorted(classes, key=lambda s: -s.radius):
        for _ in range(rng.poisson(cls.density * area)):
            cx, cy = rng.uniform(coords[0], coords[-1], 2)
            a = cls.radius * math.exp(0.25 * rng.standard_normal())
            bb = a * rng.uniform(0.55, 1.0)
            rot = rng.uniform(0, math.pi)
            h = cls.height * bb * rng.uniform(0.8, 1.2)
            if reach is not None:  # boulders in the water, gravel in it and on the bars (the beach)
                ground = relief[np.searchsorted(coords, cy).clip(0, m - 1),
                                np.searchsorted(coords, cx).clip(0, m - 1)]
                if ground >= (-0.3 if cls is reach.boulders else reach.gravel_top + 0.05):
                    continue
            stones.append((cx, cy, a, bb, rot, h))
    for sid, (cx, cy, a, bb, rot, h) in enumerate(stones):
        i0, i1 = np.searchsorted(coords, [cx - a, cx + a])
        j0, j1 = np.searchsorted(coords, [cy - a, cy + a])
        if i1 <= i0 or j1 <= j0:
            continue
        dx, dy = gx[j0:j1, i0:i1] - cx, gy[j0:j1, i0:i1] - cy
        u = dx * math.cos(rot) + dy * math.sin(rot)
        v = -dx * math.sin(rot) + dy * math.cos(rot)
        q = 1.0 - (u / a) ** 2 - (v / bb) ** 2
        base = relief[min(max((j0 + j1) // 2, 0), m - 1), min(max((i0 + i1) // 2, 0), m - 1)]
        cap = np.where(q > 0, base - 0.3 * h + h * np.sqrt(np.clip(q, 0, None)), -np.inf)
        patch = z[j0:j1, i0:i1]
        top = cap > patch
        patch[top] = cap[top]
        owner[j0:j1, i0:i1][top] = sid

    # Fade over `taper` metres from the edge (exactly the border shape on the outermost cell): to the flat
    # mean plane for the gravel bed, to the border cross-section for a reach.
    edge = np.minimum.reduce([gx - coords[0], coords[-1] - gx, gy - coords[0], coords[-1] - gy])
    fade = _smoothstep((edge - b.cell) / (b.taper - b.cell))  # [M, M]
    if reach is None:
        z -= z.mean()
        z0 = spec.level - b.depth
        heights = z0 + fade * z
        border = None
    else:
        heights = spec.level + profile[:, None] + fade * (z - profile[:, None])
        border = spec.level + profile
        z0 = float(border[0])  # the land beyond the banks

    # Albedo (linear reflectance, then sRGB-encoded for the PNG): stones get a colour and speckle,
    # the gaps sand; the background noise is periodic so the floor can repeat it.
    # river rock hues
    tints = np.array([[1.0, 1.0, 1.0], [1.0, 0.85, 0.65], [0.85, 0.9, 1.0], [1.0, 0.75, 0.6]])
    count = max(len(stones), 1)
    palette = rng.dirichlet(np.full(len(tints), 0.5), count) @ tints * rng.uniform(0.12, 0.55, (count, 1))
    speckle = _periodic_noise(rng, m, 1.0)[..., None]  # [M, M, 1] texel-scale grain
    mottle = _periodic_noise(rng, m, 0.05 / b.texel)[..., None]  # 5 cm blotches in the sand
    sand = np.array([0.38, 0.34, 0.27]) * (1 + 0.25 * mottle + 0.15 * speckle)
    if reach is not None:  # soil and grass above the bars (the beach), full cover at the bank top
        patches = _periodic_noise(rng, m, 0.5 / b.texel)[..., None]  # 50 cm patches of grass and soil
        green = _smoothstep(0.5 + patches)  # [M, M, 1] share of grass
        land = (green * np.array([0.10, 0.16, 0.05]) + (1 - green) * np.array([0.22, 0.17, 0.11])) \
            * (1 + 0.2 * mottle + 0.15 * speckle)
        dry = _smoothstep((heights - spec.level - reach.gravel_top) / (reach.land_top - reach.gravel_top))
        sand = (1 - dry[..., None]) * sand + dry[..., None] * land
    stone_col = palette[np.maximum(owner, 0)] * (1 + 0.2 * speckle)
    w = (owner >= 0)[..., None] * fade[..., None]
    rho = np.clip((1 - w) * sand + w * stone_col, 0.02, 0.9)
    albedo = np.round(255 * _linear_to_srgb(rho)).astype(np.uint8)
    return Bed(x0=float(x0), texel=b.texel, stride=stride, z0=float(z0), heights=heights, albedo=albedo,
               profile=border)


def _reach_relief(r, gx: np.ndarray, gy: np.ndarray, coords: np.ndarray, rng: np.random.Generator):
    """(heights above the water [M, M], border cross-section [M] by row) of a river reach along x.

    The centreline meanders as meander * sin(k x + phase), k = pi / pool_spacing, so the bends (pools) are
    pool_spacing apart and the crossings between them are riffles. At a bend the thalweg moves towards the
    outer bank, the outer bank is steep, and on the inner side a gravel bar emerges. Across the channel the
    depth is D(x) (1 - |s|^q) with s in [-1, 1] from one water line to the other through the thalweg; above
    the water line the ground rises to the bar and then to the bank top. The border cross-section is the
    same construction at a riffle with the centreline at y = 0.
    """
    phase = rng.uniform(0, 2 * math.pi)
    land = 0.05 * r.bank_height * _wave_field(rng, gx, gy, 3.0)  # gentle relief of the land and bars

    def heights(bend: np.ndarray, centre: np.ndarray, y: np.ndarray) -> np.ndarray:
        """bend in [-1, 1]: signed bend strength (+: the +y bank is the outer one); centre: centreline y."""
        strength = np.abs(bend)
        half = 0.5 * r.width * (1 + 0.15 * (1 - strength))  # riffles are wider
        depth = r.max_depth * (r.riffle_depth + (1 - r.riffle_depth) * strength ** 1.5)
        thalweg = 0.45 * half * bend
        u = y - centre
        above = u >= thalweg
        side = np.where(above, half - thalweg, half + thalweg)  # thalweg to water line on this side (m)
        s = (u - thalweg) / side  # [-1, 1] in the water
        outer = np.where(above, bend > 0, bend < 0)  # the side of the outer bank
        q = np.where(outer, 1.5 + 1.5 * strength, 1.5 - 0.4 * strength)  # steep outside, gentle bar inside
        wet = -depth * (1 - np.abs(s).clip(0, 1) ** q)
        # Dry side: metres beyond the water line, rising over the bar (wide inside a bend) to the bank top.
        beyond = (np.abs(s) - 1).clip(0, None) * side
        # exposed bar width: wide inside a bend, narrow under the cut bank, the same on both sides at a riffle
        bar = np.where(outer, 0.25 * (1 - 0.6 * strength), 0.25 + strength) * r.bar_width
        dry = r.bar_height * _smoothstep(beyond / (0.3 * bar)) \
            + (r.bank_height - r.bar_height) * _smoothstep((beyond - bar) / r.bank_width)
        return np.where(np.abs(s) < 1, wet, dry)

    bend = np.sin(math.pi * gx / r.pool_spacing + phase)
    centre = r.meander * bend  # the centreline swings out towards the outer bank of each bend
    relief = heights(bend, centre, gy)
    relief += np.where(relief > 0, land, 0.0)
    profile = heights(np.zeros_like(coords), np.zeros_like(coords), coords)
    return relief, profile


def _shore_relief(s: ShoreSpec, b, gx: np.ndarray, gy: np.ndarray, coords: np.ndarray,
                  rng: np.random.Generator):
    """(heights above the water [M, M], border cross-section [M] by row) of a lake shore along x.

    The waterline bends as wander * sin(2 pi x / wander_wavelength + phase) about y = shoreline. At u metres
    beyond it (towards +y) the land rises as land_height (1 - exp(-land_slope u / land_height)); at u < 0 the
    beach falls as depth (exp(beach_slope u / depth) - 1): the given slopes at the waterline, levelling out
    far from it. Gentle relief (the bed's `undulation` at its `wavelength`) fades in over the first 0.3 m of
    height either side, so that the waterline stays where the bends put it. The border cross-section is the
    same without bends or relief.
    """
    phase = rng.uniform(0, 2 * math.pi)
    relief = _wave_field(rng, gx, gy, b.wavelength) * (b.undulation / 3.0)

    def heights(u: np.ndarray) -> np.ndarray:
        land = s.land_height * (1 - np.exp(-s.land_slope * np.maximum(u, 0.0) / s.land_height))
        return np.where(u >= 0, land, s.depth * (np.exp(s.beach_slope * np.minimum(u, 0.0) / s.depth) - 1))

    line = s.shoreline + s.wander * np.sin(2 * math.pi * gx / s.wander_wavelength + phase)
    ground = heights(gy - line)
    return ground + relief * _smoothstep(np.abs(ground) / 0.3), heights(coords - s.shoreline)


def _wave_field(rng: np.random.Generator, gx: np.ndarray, gy: np.ndarray, wavelength: float) -> np.ndarray:
    """A sum of six plane waves of random direction and phase, wavelengths 1-3x `wavelength`: std ~1.7."""
    out = np.zeros_like(gx)
    for _ in range(6):
        theta, phase = rng.uniform(0, 2 * math.pi, 2)
        wl = wavelength * rng.uniform(1.0, 3.0)
        out += np.cos(2 * math.pi * (gx * math.cos(theta) + gy * math.sin(theta)) / wl + phase)
    return out


def _linear_to_srgb(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)


def grid_triangles(k: int) -> np.ndarray:
    """Triangles [2 (k-1)^2, 3] int64 of a k x k vertex grid numbered row by row (index j * k + i, j along
    y): cell (j, i) -> (00, 10, 11) and (00, 11, 01), counter-clockwise seen from +z."""
    idx = np.arange(k * k).reshape(k, k)
    v00, v10, v01, v11 = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]  # 10: +x, 01: +y
    return np.concatenate([np.stack([v00, v10, v11], -1).reshape(-1, 3),
                           np.stack([v00, v11, v01], -1).reshape(-1, 3)])


def mesh(bed: Bed) -> tuple[np.ndarray, np.ndarray]:
    """Vertices [V, 3] float64 and triangles [F, 3] int64 (`grid_triangles`)."""
    h = bed.mesh_heights
    k = h.shape[0]
    c = bed.x0 + np.arange(k) * bed.cell
    gx, gy = np.meshgrid(c, c)
    verts = np.stack([gx.ravel(), gy.ravel(), h.ravel()], -1)
    return verts, grid_triangles(k)


def surface(bed: Bed) -> Surface:
    """The exact mesh surface as a height function (the data contract's `Surface`)."""
    return Surface(bed.x0, bed.cell, bed.mesh_heights)


def shear(spec: SceneSpec, points: np.ndarray) -> np.ndarray:
    """World points [..., 3] of the flat scene's `points` [..., 3]: z + sx x + sy y under a sloping water
    surface (a new array); the very `points` under a flat surface or none."""
    w = spec.water
    if w is None or not w.sloping:
        return points
    out = np.array(points, np.float64)
    out[..., 2] += w.slope[0] * out[..., 0] + w.slope[1] * out[..., 1]
    return out


def world_surface(spec: SceneSpec, bed: Bed) -> Surface:
    """`surface(bed)` sheared with the water (`shear`): exact, as the shear maps each triangle onto one."""
    flat = surface(bed)
    if spec.water is None or not spec.water.sloping:
        return flat
    k = flat.heights.shape[0]
    c = bed.x0 + np.arange(k) * bed.cell
    gx, gy = np.meshgrid(c, c)
    return Surface(bed.x0, bed.cell, shear(spec, np.stack([gx, gy, flat.heights], -1))[..., 2])


def world_waterline(spec: SceneSpec, bed: Bed) -> list[np.ndarray]:
    """`waterline` in the world: polylines [K, 2] under a flat surface, [K, 3] with their heights on a
    sloping one."""
    lines = waterline(bed, spec.level)
    if spec.water is None or not spec.water.sloping:
        return lines
    return [np.column_stack([line, spec.water.height(line)]) for line in lines]


def height_at(bed: Bed, xy: np.ndarray) -> np.ndarray:
    """Exact height [N] of the triangulated mesh at horizontal points [N, 2] (inside the mesh)."""
    return surface(bed).height_at(xy)


def ground_truth_grid(bed: Bed, region: dict[str, float], step: float) -> np.ndarray:
    """Points [N, 3] float64 on a `step` horizontal grid over `region`, at the exact mesh height."""
    xs = np.arange(region["xmin"], region["xmax"] + 1e-9, step)
    ys = np.arange(region["ymin"], region["ymax"] + 1e-9, step)
    gx, gy = np.meshgrid(xs, ys)
    xy = np.stack([gx.ravel(), gy.ravel()], -1)
    return np.concatenate([xy, height_at(bed, xy)[:, None]], -1)


def ground_truth(spec: SceneSpec, bed: Bed, region: dict[str, float], step: float):
    """(bed grid [N, 3], bank grid [M, 3] or None) over `region`, in the flat scene (`shear` for the world):
    for a reach the submerged bed (below the level there: the depth below a sloping surface once sheared),
    which is what bathymetry measures, and the emerged ground apart; for the gravel bed the whole grid."""
    grid = ground_truth_grid(bed, region, step)
    if spec.reach is None:
        return grid, None
    wet = grid[:, 2] < spec.level
    return grid[wet], grid[~wet]


def waterline(bed: Bed, level: float) -> list[np.ndarray]:
    """Polylines [K, 2] (metres) where the mesh surface crosses the water plane z = level."""
    import contourpy

    k = bed.mesh_heights.shape[0]
    c = bed.x0 + np.arange(k) * bed.cell
    return [line for line in contourpy.contour_generator(c, c, bed.mesh_heights).lines(level)
            if len(line) > 1]
