"""Small synthetic scenes rendered with our own rasterizer: for the benchmark and the end-to-end tests.

`bed_scene` makes a textured bed of Gaussians under water; `render_views` renders it (through the water with
`refract_gaussians`, and without) from a ring of cameras; `write_dataset` stores views in the dataset
layout of the README so the real loader and trainer read them. Nothing here touches Blender.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from ragsplat.camera import Camera
from ragsplat.dataset import layout
from ragsplat.outputs import write_json
from ragsplat.water_surface import WaterSurface


def write_dataset(root: str | Path, views: list[dict], water: WaterSurface | None,
                  eval_region: dict | None = None, bed: dict | None = None) -> Path:
    """Write `views` (dicts with camera, image [H,W,3] in [0,1], optional dry, split, kind) as a dataset.

    All cameras must share intrinsics (the contract stores them once). `bed` ({"depth", "size"} of a square
    bed centred on the origin) goes to scene.json as `spec.bed`, where the generator puts it.
    """
    root = Path(root)
    cam0: Camera = views[0]["camera"]
    frames = []
    for i, v in enumerate(views):
        cam: Camera = v["camera"]
        if (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) != (cam0.width, cam0.height, cam0.fx,
                                                                       cam0.fy, cam0.cx, cam0.cy):
            raise ValueError("write_dataset: all views must share intrinsics")
        name = f"{i:04d}"
        image = layout.relative_path("wet" if water is not None else "dry", name)
        layout.write_png(root / image, v["image"])
        dry = layout.relative_path("dry", name) if v.get("dry") is not None else None
        if dry is not None and water is not None:
            layout.write_png(root / dry, v["dry"])
        frames.append(layout.frame(name, cam, v.get("split", "train"), v.get("kind", "nadir"), image, dry))
    write_json(root / layout.TRANSFORMS, layout.transforms_json(cam0, frames, water), indent=1)
    spec = {"bed": bed} if bed is not None else {}
    write_json(root / layout.SCENE,
               layout.scene_json(spec, eval_region, generator="ragsplat.bench.synthetic"), indent=1)
    return root


def ring_cameras(count: int, size: int, height: float, radius: float, fov_deg: float = 70.0,
                 target=(0.0, 0.0, -1.0), nadir: bool = True) -> list[Camera]:
    """`count` cameras on a circle of `radius` at `height` looking at `target`, plus one nadir if asked."""
    cams = [Camera.look_at([0.0, 0.0, height], [0.0, 0.0, target[2]], size, size, fov_deg)] if nadir else []
    for k in range(count):
        a = 2 * math.pi * k / count
        eye = [radius * math.cos(a), radius * math.sin(a), height]
        cams.append(Camera.look_at(eye, target, size, size, fov_deg, up=(0.0, 0.0, 1.0)))
    return cams


def bed_scene(count: int, half: float, depth: float, seed: int = 0, dtype=torch.float32,
              device=None) -> dict[str, torch.Tensor]:
    """`count` Gaussians on a wavy bed z = -depth + 0.1 depth sin(.) over [-half, half]^2, textured colours.

    Returns activated tensors: means [N,3], quats [N,4], scales [N,3] (linear), opacities [N], colors [N,3].
    """
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(count, 2, generator=g, dtype=torch.float64) * 2 - 1) * half
    z = -depth + 0.1 * depth * torch.sin(2.0 * xy[:, 0] / half) * torch.cos(1.5 * xy[:, 1] / half)
    means = torch.cat([xy, z[:, None]], 1)
    spacing = 2 * half / math.sqrt(count)
    scales = spacing * (0.6 + 0.4 * torch.rand(count, 3, generator=g, dtype=torch.float64))
    scales[:, 2] *= 0.3  # flat, like stones lying on the bed
    quats = torch.nn.functional.normalize(torch.randn(count, 4, generator=g, dtype=torch.float64), dim=-1)
    quats[:, 1:3] *= 0.2  # mostly rotated about the vertical
    quats = torch.nn.functional.normalize(quats, dim=-1)
    # Checker-like albedo so that photometric matching has texture to lock on to.
    cell = torch.floor(xy / (half / 4)).sum(1) % 2
    base = torch.stack([0.35 + 0.4 * cell, 0.3 + 0.25 * (1 - cell), 0.25 + 0.1 * cell], 1)
    colors = (base + 0.15 * torch.rand(count, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    out = {"means": means, "quats": quats, "scales": scales,
           "opacities": torch.full((count,), 0.95, dtype=torch.float64), "colors": colors}
    return {k: v.to(dtype=dtype, device=device) for k, v in out.items()}


def render_views(scene: dict[str, torch.Tensor], cameras: list[Camera], water: WaterSurface | None,
                 backend: str = "auto", background=(0.0, 0.0, 0.0), attenuation=None,
                 backscatter=None, reflection=None, downwelling: float = 0.0) -> list[dict]:
    """Render `scene` (from `bed_scene`) from each camera: `image` through the water with the full RA-GS
    transform (position, isotropic scale, opacity; `attenuation`: the water's coefficients [3] in 1/m, or
    None, with the daylight's `downwelling` path per metre of depth; `backscatter`: [2, 3] its veil B_inf
    and coefficients c_b, added as the trainer does, or None;
    `reflection`: [S, S, 3] the sky map the surface mirrors, composited as the trainer does, or None), `dry`
    without it, and the dry expected `depth`."""
    from ragsplat.rasterize import rasterize
    from ragsplat.reflection import add_reflection, sky_radiance, surface_reflection
    from ragsplat.refraction import add_backscatter, pixel_water_paths, refract_gaussians
    from ragsplat.rendering import pixel_rays

    out = []
    for cam in cameras:
        s = scene
        with torch.no_grad():
            dry, _, depth, _ = rasterize(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"],
                                         cam, background, backend=backend)
            wet = dry
            if water is not None:
                c = torch.as_tensor(cam.camera_center, dtype=s["means"].dtype, device=s["means"].device)
                a = refract_gaussians(s["means"], s["scales"], s["quats"], s["opacities"], s["colors"], c,
                                      water, attenuation=attenuation, downwelling=downwelling)
                wet, alpha, z, _ = rasterize(a.means, a.quats, a.scales, a.opacities, a.colors, cam,
                                             background, backend=backend)
                if backscatter is not None:
                    paths = pixel_water_paths(pixel_rays(cam, z), z[..., 0], c, water)
                    wet = add_backscatter(wet, alpha, paths, backscatter[0], backscatter[1])
                if reflection is not None:
                    R, mirrored = surface_reflection(pixel_rays(cam, z), z[..., 0], c, water)
                    wet = add_reflection(wet, R, sky_radiance(reflection, mirrored))
        out.append({"camera": cam, "image": wet.clamp(0, 1), "dry": dry.clamp(0, 1), "depth": depth})
    return out
