"""Seeded riverbed: heightfield, gravel albedo aligned to the stones, exact mesh and ground-truth grid.

The heightfield is built on the texel grid (x_i = x0 + i * texel, same in y; array index [j, i] = [y, x]);
the mesh takes every `stride`-th sample and splits each cell along the same diagonal, so the rendered surface
is exactly `height_at` and `gt/bed.ply`. Relief: a sum of low-frequency waves plus rounded (half-ellipsoid)
stones in a few size classes, merged by maximum. Albedo: a per-stone colour with speckle, sand-coloured
noise between stones. Towards the border relief and stones fade into the flat mean plane (z = level - depth)
and the albedo into the periodic noise, so a flat floor textured with the same repeating image continues
the bed seamlessly beyond its edge.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from datagen.spec import SceneSpec


@dataclass(frozen=True)
class Bed:
    x0: float  # world x (= y) of texel 0
    texel: float  # m
    stride: int  # mesh vertex every `stride` texels
    z0: float  # the flat floor height: level - depth
    heights: np.ndarray  # [M, M] float64 world z on the texel grid, index [j (y), i (x)]
    albedo: np.ndarray  # [M, M, 3] uint8 sRGB on the same grid

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

    # Low-frequency relief: a few plane waves with random direction and phase, wavelengths >= b.wavelength.
    relief = np.zeros((m, m))
    for _ in range(6):
        theta, phase = rng.uniform(0, 2 * math.pi, 2)
        wl = b.wavelength * rng.uniform(1.0, 3.0)
        relief += np.cos(2 * math.pi * (gx * math.cos(theta) + gy * math.sin(theta)) / wl + phase)
    relief *= b.undulation / 3.0  # six unit waves: std ~1.7, peaks ~ the spec's amplitude

    # Stones: half-ellipsoids sunk 30 % into the relief, merged by maximum; `owner` remembers the top stone.
    z = relief.copy()
    owner = np.full((m, m), -1, dtype=np.int64)
    stones = []
    area = (m * b.texel) ** 2
    for cls in sorted(b.stones, key=lambda s: -s.radius):
        for _ in range(rng.poisson(cls.density * area)):
            cx, cy = rng.uniform(coords[0], coords[-1], 2)
            a = cls.radius * math.exp(0.25 * rng.standard_normal())
            bb = a * rng.uniform(0.55, 1.0)
            rot = rng.uniform(0, math.pi)
            h = cls.height * bb * rng.uniform(0.8, 1.2)
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
    z -= z.mean()

    # Fade to the flat plane over `taper` metres from the edge (exactly flat on the outermost cell).
    edge = np.minimum.reduce([gx - coords[0], coords[-1] - gx, gy - coords[0], coords[-1] - gy])
    fade = _smoothstep((edge - b.cell) / (b.taper - b.cell))  # [M, M]
    z0 = spec.level - b.depth
    heights = z0 + fade * z

    # Albedo (linear reflectance, then sRGB-encoded for the PNG): stones get a colour and speckle,
    # the gaps sand; the background noise is periodic so the floor can repeat it.
    tints = np.array([[1.0, 1.0, 1.0], [1.0, 0.85, 0.65], [0.85, 0.9, 1.0], [1.0, 0.75, 0.6]])  # river rock hues
    count = max(len(stones), 1)
    palette = rng.dirichlet(np.full(len(tints), 0.5), count) @ tints * rng.uniform(0.12, 0.55, (count, 1))
    speckle = _periodic_noise(rng, m, 1.0)[..., None]  # [M, M, 1] texel-scale grain
    mottle = _periodic_noise(rng, m, 0.05 / b.texel)[..., None]  # 5 cm blotches in the sand
    sand = np.array([0.38, 0.34, 0.27]) * (1 + 0.25 * mottle + 0.15 * speckle)
    stone_col = palette[np.maximum(owner, 0)] * (1 + 0.2 * speckle)
    w = (owner >= 0)[..., None] * fade[..., None]
    rho = np.clip((1 - w) * sand + w * stone_col, 0.02, 0.9)
    albedo = np.round(255 * _linear_to_srgb(rho)).astype(np.uint8)
    return Bed(x0=float(x0), texel=b.texel, stride=stride, z0=float(z0), heights=heights, albedo=albedo)


def _linear_to_srgb(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)


def mesh(bed: Bed) -> tuple[np.ndarray, np.ndarray]:
    """Vertices [V, 3] float64 and triangles [F, 3] int64; cell (j, i) -> (00, 10, 11) and (00, 11, 01)."""
    h = bed.mesh_heights
    k = h.shape[0]
    c = bed.x0 + np.arange(k) * bed.cell
    gx, gy = np.meshgrid(c, c)
    verts = np.stack([gx.ravel(), gy.ravel(), h.ravel()], -1)
    idx = np.arange(k * k).reshape(k, k)
    v00, v10, v01, v11 = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]  # 10: +x, 01: +y
    tris = np.concatenate([np.stack([v00, v10, v11], -1).reshape(-1, 3),
                           np.stack([v00, v11, v01], -1).reshape(-1, 3)])
    return verts, tris


def height_at(bed: Bed, xy: np.ndarray) -> np.ndarray:
    """Exact height [N] of the triangulated mesh at horizontal points [N, 2] (inside the mesh)."""
    h = bed.mesh_heights
    fx, fy = (np.asarray(xy, float) - bed.x0).T / bed.cell
    i = np.clip(np.floor(fx).astype(int), 0, h.shape[1] - 2)
    j = np.clip(np.floor(fy).astype(int), 0, h.shape[0] - 2)
    s, t = fx - i, fy - j
    h00, h10, h01, h11 = h[j, i], h[j, i + 1], h[j + 1, i], h[j + 1, i + 1]
    lower = s >= t  # triangle (00, 10, 11)
    return np.where(lower, h00 + s * (h10 - h00) + t * (h11 - h10), h00 + t * (h01 - h00) + s * (h11 - h01))


def ground_truth_grid(bed: Bed, region: dict[str, float], step: float) -> np.ndarray:
    """Points [N, 3] float64 on a `step` horizontal grid over `region`, at the exact mesh height."""
    xs = np.arange(region["xmin"], region["xmax"] + 1e-9, step)
    ys = np.arange(region["ymin"], region["ymax"] + 1e-9, step)
    gx, gy = np.meshgrid(xs, ys)
    xy = np.stack([gx.ravel(), gy.ravel()], -1)
    return np.concatenate([xy, height_at(bed, xy)[:, None]], -1)


def write_ply(path, verts: np.ndarray, tris: np.ndarray) -> None:
    """Binary little-endian PLY with double vertices (exact) and int32 triangles."""
    header = (f"ply\nformat binary_little_endian 1.0\ncomment ragsplat riverbed (world metres, z up)\n"
              f"element vertex {len(verts)}\nproperty double x\nproperty double y\nproperty double z\n"
              f"element face {len(tris)}\nproperty list uchar int vertex_indices\nend_header\n")
    face = np.empty(len(tris), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face["n"], face["v"] = 3, tris
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(np.ascontiguousarray(verts, dtype="<f8").tobytes())
        f.write(face.tobytes())
