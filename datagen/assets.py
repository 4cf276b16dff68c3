"""The scene's geometry on disk: the bed, the floor around it, the water surface and the conditions' objects
as meshes for the renderer (scene/geometry.npz, `scene_geometry`), and the exact ground truth beside them
(gt/: the mesh, the height grid, the bed and bank grids, the elevation raster, the waterline;
`write_bed_assets`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ragsplat.datagen import conditions, flight
from ragsplat.datagen.bed import (
    Bed,
    ground_truth,
    height_at,
    make_bed,
    mesh,
    shear,
    world_surface,
    world_waterline,
)
from ragsplat.datagen.spec import SceneSpec
from ragsplat.dataset import layout, rasters
from ragsplat.outputs import atomic_path

FAR = 2000.0  # half-size (m) of the floor and water planes: beyond every view's horizon-free field


def scene_geometry(spec: SceneSpec, bed: Bed, targets: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Everything Blender meshes: bed, the floor frame around it, the water surface and, with field
    conditions, the water body and the ground control `targets` [T, 3] (arrays for the npz). `bed` and
    `targets` are the flat scene's; the vertices returned the world's (`bed.shear`: under a sloping surface
    the whole scene, water included, falls with it)."""
    geo = _flat_geometry(spec, bed, targets)
    return {k: shear(spec, v) if k.endswith("_verts") else v for k, v in geo.items()}


def _flat_geometry(spec: SceneSpec, bed: Bed, targets: np.ndarray | None) -> dict[str, np.ndarray]:
    size = bed.heights.shape[0] * bed.texel  # the albedo image's period (m)

    def uv(xy):  # texel i's centre is at x0 + i * texel
        return (np.asarray(xy)[:, :2] - bed.x0 + bed.texel / 2) / size

    verts, tris = mesh(bed)
    geo = {"bed_verts": verts, "bed_tris": tris, "bed_uv": uv(verts)}
    # Floor from one cell inside the border out to FAR (the overlap is coplanar and carries the same texture,
    # so no crack can open at the seam). Gravel bed: a flat frame at the border height. Reach: the border
    # cross-section extruded along x, textured with the border column's colours, and flat land beyond.
    a, f, z = bed.x0 + bed.cell, FAR, bed.z0
    b = bed.x0 + bed.extent - bed.cell
    if bed.profile is None:
        fv = np.array([[a, a, z], [b, a, z], [b, b, z], [a, b, z], [-f, -f, z], [f, -f, z], [f, f, z],
                       [-f, f, z]])
        ft = np.array([[4, 5, 1], [4, 1, 0], [5, 6, 2], [5, 2, 1], [6, 7, 3], [6, 3, 2], [7, 4, 0],
                       [7, 0, 3]])
        fuv = uv(fv)
    else:
        fv, ft, fuv = _reach_floor(bed, a, b, f, uv)
    geo.update(floor_verts=fv, floor_tris=ft, floor_uv=fuv)
    c = spec.conditions
    if spec.water is not None and (c is None or not c.rippled):
        lv = spec.water.level
        geo.update(water_verts=np.array([[-f, -f, lv], [f, -f, lv], [f, f, lv], [-f, f, lv]]),
                   water_tris=np.array([[0, 1, 2], [0, 2, 3]]))  # counter-clockwise: normal +Z
    if c is None:
        return geo
    if c.rippled:
        geo["water_verts"], geo["water_tris"], geo["water_weight"] = conditions.water_surface(
            spec, bed.extent, f)
    if c.turbid:
        geo["volume_verts"], geo["volume_tris"] = conditions.water_body(spec, float(bed.heights.min()) - 1.0,
                                                                        1.01 * f)
    if targets is not None:
        for colour, (verts, tris) in conditions.target_meshes(c, targets).items():
            geo[f"target_{colour}_verts"], geo[f"target_{colour}_tris"] = verts, tris
    return geo


def _reach_floor(bed: Bed, a: float, b: float, far: float, uv):
    """(vertices, triangles, uv) of a reach's floor: the border cross-section extruded from x = a to -far
    and from x = b to +far, and land at the border height beyond y = a and y = b."""
    ys = bed.x0 + np.arange(1, bed.mesh_heights.shape[0] - 1) * bed.cell  # mesh rows a .. b
    zs = bed.profile[:: bed.stride][1:-1]
    k = len(ys)
    verts, tris, uvs = [], [], []

    def strip(x_in: float, x_out: float) -> None:  # rows x_in and x_out, quads between neighbouring y
        base = sum(len(v) for v in verts)
        inner = np.column_stack([np.full(k, x_in), ys, zs])
        verts.append(np.concatenate([inner, inner * [0, 1, 1] + [x_out, 0, 0]]))
        uvs.append(np.concatenate([uv(inner)] * 2))  # colours of the border column, stretched along x
        i = base + np.arange(k - 1)
        order = (i, i + k, i + k + 1, i, i + k + 1, i + 1) if x_out > x_in else \
            (i, i + 1, i + k + 1, i, i + k + 1, i + k)  # counter-clockwise from above
        tris.append(np.stack(order, -1).reshape(-1, 3))

    strip(a, -far)
    strip(b, far)
    land = bed.z0
    base = sum(len(v) for v in verts)
    quads = [[[-far, -far], [far, -far], [far, a], [-far, a]], [[-far, b], [far, b], [far, far], [-far, far]]]
    for q, corners in enumerate(quads):
        c = np.column_stack([np.array(corners, float), np.full(4, land)])
        verts.append(c)
        uvs.append(np.repeat(uv(np.array([[0.0, a if q == 0 else b]])), 4, axis=0))  # one land colour
        o = base + 4 * q
        tris.append(np.array([[o, o + 1, o + 2], [o, o + 2, o + 3]]))
    return np.concatenate(verts), np.concatenate(tris), np.concatenate(uvs)


def write_bed_assets(spec: SceneSpec, out: Path) -> None:
    """Heightfield-derived files, each written once (atomically) and reused by later runs and shards."""
    files = [out / "scene" / "geometry.npz", out / "scene" / "albedo.png", out / layout.GT_MESH,
             out / layout.GT_SURFACE, out / layout.GT_GRID]
    if spec.reach is not None:
        files += [out / layout.GT_BANKS, out / layout.GT_WATERLINE, out / layout.GT_ELEVATION]
    c = spec.conditions
    with_targets = c is not None and c.targets > 0
    if with_targets:
        files.append(out / layout.GT_TARGETS)
    if all(p.exists() for p in files):
        return
    bed = make_bed(spec)  # the flat scene: what is written is sheared into the world (`bed.shear`)
    grid, banks = ground_truth(spec, bed, flight.eval_region(spec), layout.GT_GRID_STEP)
    targets = None
    if with_targets:
        targets = conditions.place_targets(c, lambda xy: height_at(bed, xy), banks, spec.level, spec.seed)
        layout.write_npy(out / layout.GT_TARGETS, shear(spec, targets))
    geo = scene_geometry(spec, bed, targets)
    with atomic_path(files[0]) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **geo)
    # Blender reads images bottom row first: flip so that texel row j (y index) is at v = (j + 0.5) / M.
    layout.write_png(files[1], np.ascontiguousarray(bed.albedo[::-1]))
    layout.write_ply(files[2], geo["bed_verts"], geo["bed_tris"], "ragsplat riverbed (world metres, z up)")
    world_surface(spec, bed).save(files[3])
    grid = shear(spec, grid)
    layout.write_npy(out / layout.GT_GRID, grid)
    if banks is not None:
        layout.write_npy(out / layout.GT_BANKS, shear(spec, banks))
        rasters.write_elevation(out / layout.GT_ELEVATION, grid, layout.GT_GRID_STEP)
        # polylines [K, 2] at the level, or [K, 3] with their heights on a sloping surface
        layout.write_waterline(out / layout.GT_WATERLINE, world_waterline(spec, bed), spec.level)
