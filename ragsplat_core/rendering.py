"""Rendering a model: the Gaussians as one camera sees them, through the water or without it, and their
image, alpha, z-depth and `meta` (tensors in, tensors out; no I/O).

`view_gaussians` maps the true Gaussians to what the rasterizer takes (the RA-GS transform through the water
per view, or the true ones), `rasterize_view` draws them as volumes or surfels, and `render_splats` adds the
water's own light (its backscatter veil, the surface's reflection of the sky) as training renders it. The
trainer, a finished run's renders (`runs.Model`) and the evaluation all render through these.
"""

from __future__ import annotations

import torch

from ragsplat.camera import Camera
from ragsplat.gaussians import activated
from ragsplat.rasterize import choose_backend, rasterize
from ragsplat.rasterize_surfels import rasterize_surfels
from ragsplat.reflection import reflect, sky_radiance, surface_reflection
from ragsplat.refraction import (
    ApparentGaussians,
    backscatter_veil,
    compiled_refract_gaussians,
    linear_to_srgb,
    opacity_factor,
    pixel_water_paths,
    refract_gaussians,
    srgb_to_linear,
    waterline_weight,
)
from ragsplat.water_surface import WaterSurface


def view_gaussians(splats, center: torch.Tensor, sh_degree: int, water: WaterSurface | None,
                   flags: dict | None, backend: str = "torch", surfels: bool = False,
                   compiled: bool = False, attenuation: torch.Tensor | None = None,
                   wet_degree: int = 3, downwelling: float = 0.0,
                   check_camera: bool = True) -> ApparentGaussians:
    """The Gaussians as the rasterizer takes them for the camera at `center` [3]: the true ones (`flags`
    None) or the apparent ones through `water` (RA-GS, `flags` of `refract_gaussians`). With the `cpu`
    backend (what "auto" means on CPU) the view colours come from its SH kernel. `surfels`: no apparent
    covariances (a surfel renders from its mapped tangents, `jacobians`). `compiled`: the transform through
    `compiled_refract_gaussians` (the same values to round-off). `attenuation`: the water's coefficients [3]
    (1/m) or None, passed to the transform only when given (a variant without it calls it as before), with
    its `downwelling`.
    `wet_degree`: the most SH degree of a Gaussian under `water` (`TrainConfig.wet_sh_degree`), its colour
    blended from the full degree's to that one's across the water line as the refraction is; 3: no cap.
    `check_camera`: `refract_gaussians`' (False: the caller has checked the camera above the water)."""
    scales, quats, opac = activated(splats)
    colors_of = choose_backend(backend, splats["means"].device).colors
    colors = colors_of(splats, center, sh_degree)  # [N, 3]
    if water is not None and wet_degree < sh_degree:
        w = waterline_weight(water.depth(splats["means"]))[:, None]  # [N, 1]: 0 above, 1 under the water
        colors = torch.lerp(colors, colors_of(splats, center, wet_degree), w)
    if flags is None:
        return ApparentGaussians(splats["means"], scales, quats, opac, colors, None, None)
    transform = compiled_refract_gaussians() if compiled else refract_gaussians
    terms = {} if attenuation is None else {"attenuation": attenuation, "downwelling": downwelling}
    return transform(splats["means"], scales, quats, opac, colors, center, water, **flags,
                     covariances=not surfels, check_camera=check_camera, **terms)


def render_splats(splats, camera: Camera, center: torch.Tensor, sh_degree: int, water: WaterSurface | None,
                  flags: dict | None, surfels: bool, background: torch.Tensor, backend: str,
                  compiled: bool = False,
                  attenuation: torch.Tensor | None = None, backscatter: torch.Tensor | None = None,
                  reflection: torch.Tensor | None = None, wet_degree: int = 3, surfel_depth: str = "ray",
                  downwelling: float = 0.0, check_camera: bool = True):
    """(image [H,W,3], alpha [H,W,1], depth [H,W,1], meta) of `camera` (centre `center` [3]) as training
    renders it (`view_gaussians`, then `rasterize_view`). `backscatter`: [2, 3] the water's veil B_inf and its
    coefficients c_b (1/m), or None (nothing computed): the veil along each pixel's path in `water` to the
    point it renders is added to the image (`refraction.backscatter_veil`). `reflection`: [S, S, 3] the sky
    map the surface mirrors (`reflection.sky_radiance`, linear radiance), or None (nothing computed): each wet
    pixel becomes (1 - R) x the rest + R x the mirrored sky (`reflection.reflect`). The trainer and a
    finished run's renders (`runs.Model`) share it. `wet_degree`, `downwelling`, `check_camera`:
    `view_gaussians`'; `surfel_depth`: `rasterize_surfels`' depth."""
    img, alpha, depth, meta = rasterize_view(view_gaussians(splats, center, sh_degree, water, flags, backend,
                                                            surfels, compiled, attenuation, wet_degree,
                                                            downwelling, check_camera),
                                             camera, surfels, background, backend, depth=surfel_depth)
    if backscatter is not None or reflection is not None:
        rays = pixel_rays(camera, depth)  # [H, W, 3]
        lin = srgb_to_linear(img)  # the terms add light in linear light: converted once (a pair costs ~7 ms)
        if backscatter is not None:  # under the surface: the transmitted share below includes it
            paths = pixel_water_paths(rays, depth[..., 0], center, water)  # [H, W]
            lin = lin + backscatter_veil(alpha, paths, backscatter[0], backscatter[1])
        if reflection is not None:
            R, mirrored = surface_reflection(rays, depth[..., 0], center, water)  # [H, W], [H, W, 3]
            lin = reflect(lin, R, sky_radiance(reflection, mirrored))
        img = linear_to_srgb(lin)
    return img, alpha, depth, meta


def pixel_rays(camera: Camera, like: torch.Tensor) -> torch.Tensor:
    """[H, W, 3] world directions of the rays through the pixel centres, scaled to unit camera z (a rendered
    z-depth times them reaches the point from the centre); `like` gives dtype and device. R^T (x, y, 1) as a
    sum of R's rows: a [H W, 3] x [3, 3] product costs more here than the whole veil."""
    kw = {"dtype": like.dtype, "device": like.device}
    x = (torch.arange(camera.width, **kw) + 0.5 - camera.cx) / camera.fx  # [W]
    y = (torch.arange(camera.height, **kw) + 0.5 - camera.cy) / camera.fy  # [H]
    R = camera.tensor("R", like.dtype, like.device)
    return x[None, :, None] * R[0] + y[:, None, None] * R[1] + R[2]


def visible_weights(g: ApparentGaussians, camera: Camera, surfels: bool, backend: str,
                    mask: torch.Tensor | None = None, depth: str = "ray") -> torch.Tensor:
    """[N] each Gaussian's compositing weights (its alpha times the transmittance in front of it) summed over
    the pixels of `camera` (those of `mask` [H, W] only, when given): how much of the image it makes. The
    gradient of the image's sum with respect to a grey colour, so exact for either rasterizer; `g`'s colours
    are not used."""
    probe = torch.ones(len(g.means), 1, device=g.means.device, requires_grad=True)  # [N, 1]
    with torch.enable_grad():
        img = rasterize_view(g._replace(colors=probe.expand(-1, 3)), camera, surfels,
                             torch.zeros(3, device=g.means.device), backend, depth=depth)[0][..., 0]  # [H, W]
        (img.sum() if mask is None else img[mask].sum()).backward()
    return probe.grad[:, 0]


def rasterize_view(g: ApparentGaussians, camera: Camera, surfels: bool, background: torch.Tensor,
                   backend: str, median: bool = False, depth: str = "ray"):
    """`rasterize` the Gaussians `g`, or `rasterize_surfels` them as surfels (the first two scales span the
    disk; with `g.jacobians` the tangents are mapped through the water, t' = J t). `median`: also
    meta["median_depth"] (surfels always have it). `depth`: the surfels' (`rasterize_surfels`)."""
    if not surfels:
        return rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, camera, background,
                         covars=g.covars, backend=backend, median=median)
    # [N, 3, 2] t' = J t through the water; without it quats and scales
    tangents = None if g.jacobians is None else (
        g.jacobians @ choose_backend(backend, g.means.device).tangents(g.quats, g.scales[:, :2]))
    return rasterize_surfels(g.means, g.quats, g.scales[:, :2], g.opacities, g.colors, camera, background,
                             tangents=tangents, backend=backend, depth=depth)


def backscatter_json(backscatter: torch.Tensor) -> dict:
    """[2, 3] (B_inf, c_b) as config.json and train_stats.json write it (`backscatter_tensor` reads it)."""
    return {"veil": [float(b) for b in backscatter[0]], "coefficients": [float(c) for c in backscatter[1]]}


def backscatter_tensor(d: dict, device) -> torch.Tensor:  # [2, 3] float32 from `backscatter_json`'s dict
    return torch.tensor([d["veil"], d["coefficients"]], dtype=torch.float32, device=device)


def reflection_json(sky: torch.Tensor) -> dict:
    """The sky map [S, S, 3] as config.json and train_stats.json write it (`reflection_tensor` reads it): rows
    of texels of linear RGB, exactly (a float32 is a double)."""
    return {"sky": sky.tolist()}


def reflection_tensor(d: dict, device) -> torch.Tensor:  # [S, S, 3] float32 from `reflection_json`'s dict
    return torch.tensor(d["sky"], dtype=torch.float32, device=device)


def fades_opacity(flags: dict | None) -> bool:
    """Whether a variant's renders fade submerged opacity (alpha / n^2): then pruning, resets and the median
    depth of the true Gaussians use the opacity as rendered."""
    return flags is not None and flags["opacity"]


def median_depth(splats, camera: Camera, surfels: bool, fade: WaterSurface | None,
                 backend: str) -> torch.Tensor:
    """[H, W] median z-depth of the TRUE Gaussians (or surfels) seen by `camera` along straight rays, 0 where
    the transmittance stays above 0.5: the bed that depth fusion wants (rendered through the interface the
    depth would be the apparent bed's, and the z of a refracted ray is no distance to the true one). With
    `fade` (a variant that fades submerged opacity, e.g. `full`) each one is drawn with the opacity its
    training renders had, alpha / n^2: drawn at the full parameter the median surface sits too high
    (measured on the development reach: F1 at 3 % of depth 33 vs 68). For `3dgs` this is its apparent bed."""
    center = torch.tensor(camera.camera_center, dtype=torch.float32, device=splats["means"].device)
    with torch.no_grad():
        g = view_gaussians(splats, center, 0, None, None)  # colours do not move the depth: degree 0
        if fade is not None:
            g = g._replace(opacities=g.opacities * opacity_factor(g.means, fade))
        meta = rasterize_view(g, camera, surfels, torch.zeros(3, device=g.means.device), backend,
                              median=True)[3]
    return meta["median_depth"][..., 0]
