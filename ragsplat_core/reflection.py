"""The water surface's reflection of sky and sun: a Fresnel-weighted layer over the wet pixels.

A camera ray meeting the water (unit direction v, the surface's upward unit normal N) splits: the share R of
the light arriving along the mirrored direction m = v - 2 (v . N) N is reflected into the camera, the share
1 - R of the light coming up from under the water is transmitted. R is the unpolarised Fresnel reflectance at
the incidence angle theta_i (cos theta_i = -v . N) from air into water of index n (`fresnel`): the mean of

    Rs = ((cos_i - n cos_t) / (cos_i + n cos_t))^2,   Rp = ((n cos_i - cos_t) / (n cos_i + cos_t))^2,

cos_t = sqrt(1 - sin^2 theta_i / n^2) by Snell. R(0) = ((n - 1) / (n + 1))^2 (0.020 at n = 1.33), R -> 1 at
grazing, Rp = 0 at Brewster's angle tan theta_i = n, R = 0 everywhere at n = 1. By reciprocity the same R is
what the surface reflects back down of the light coming up, so 1 - R is the transmitted share either way.

Which pixels are wet is decided as `refraction.pixel_water_paths` decides where the water column is: by the
rendered depth, P' = C + depth ray the apparent point the pixel sees, wet where P' lies below the surface
(banks and bars above it, and pixels that render nothing, P' = C, reflect nothing: R = 0). A tilted plane:
its own normal; a curved surface: the normal of its tangent plane above P' (as `pixel_water_paths`; the ray
meets the surface d' tan(theta_a) aside, where a reach's gentle profile has nearly the same slope).

The reflected light is an environment shared by all views: a small sky map (`SKY_SIZE`^2 texels of linear RGB
radiance) over the orthographic projection of the upper hemisphere, texel (i, j) at the direction whose world
(x, y) is (-1 + 2 j / (S - 1), -1 + 2 i / (S - 1)), sampled bilinearly (`sky_radiance`).
"""

from __future__ import annotations

import torch

from ragsplat.refraction import GRAZING_COS, linear_to_srgb, srgb_to_linear, upward_normals
from ragsplat.water_surface import WaterSurface

# Texels per side of the sky map. A map, not spherical harmonics: what the water mirrors is a smooth sky
# gradient plus the sun's glint, which ripples of a few mm widen into a lobe of some 10-20 degrees (the
# surface tilts a few degrees and the mirror doubles it). Degree-3 SH resolves about 60 degrees: it would
# smear that lobe over the sky and ring below zero around it, and the degree that resolves 20 degrees (about
# 9, 100 basis functions a pixel) costs more than a 4-tap lookup. 16 texels over the hemisphere's disk are
# 7.7 degrees apart at the zenith (9.3 at the sun's usual 35 degrees from it): a lobe spans 2-3 texels.
SKY_SIZE = 16


def fresnel(cos_i, n):
    """(Rs, Rp) [...] the Fresnel reflectances of s- and p-polarised light at incidence cos_i [...] in (0, 1]
    from air into a medium of index n >= 1 (broadcast). Their mean is the unpolarised R (`reflectance`)."""
    n = torch.as_tensor(n, dtype=cos_i.dtype, device=cos_i.device)
    cos_t = torch.sqrt(1 - (1 - cos_i * cos_i) / (n * n))  # Snell; > 0 for n >= 1 and cos_i > 0
    rs = (cos_i - n * cos_t) / (cos_i + n * cos_t)
    rp = (n * cos_i - cos_t) / (n * cos_i + cos_t)
    return rs * rs, rp * rp


def reflectance(cos_i, n):
    """[...] the unpolarised Fresnel reflectance (Rs + Rp) / 2 at incidence cos_i [...] (`fresnel`)."""
    rs, rp = fresnel(cos_i, n)
    return (rs + rp) / 2


def surface_reflection(rays, depth, camera_center, water: WaterSurface):
    """(R [...], mirrored [..., 3]) of each pixel: the Fresnel reflectance of the water where its ray meets it
    (0 on dry pixels: the module docstring) and the unit mirrored direction (the upper hemisphere's for a ray
    that meets the water; defined everywhere).

    rays [..., 3] the pixels' world ray directions (any length, e.g. `rendering.pixel_rays`' unit camera z),
    depth [...] the rendered camera z-depth along them, camera_center [3]. Differentiable in the rays, the
    camera and the water (n, level, slope); not in the depth, which only decides which pixels are wet."""
    C = torch.as_tensor(camera_center, dtype=rays.dtype, device=rays.device)
    if water.tilted or water.curved:
        v = rays / torch.linalg.vector_norm(rays, dim=-1, keepdim=True)  # [..., 3] unit
        p = C + depth[..., None].detach() * rays.detach()  # [..., 3] the apparent point the pixel renders
        normal = upward_normals(water.gradient(p[..., :2]))  # [..., 3]
        vn = (v * normal).sum(-1)  # [...] = -cos theta_i for a ray meeting the water
        mirrored = v - 2 * vn[..., None] * normal
        wet = water.depth(p) > 0  # [...] bool
    else:  # the horizontal plane, N = e_z: [H, W] ops where they do (a third of an [H, W, 3] one's cost)
        inv = torch.rsqrt((rays * rays).sum(-1))  # [...] 1 / |ray|
        vn = rays[..., 2] * inv
        mirrored = torch.cat([rays[..., :2], -rays[..., 2:]], -1) * inv[..., None]
        level = torch.as_tensor(water.level, dtype=rays.dtype, device=rays.device).detach()
        wet = (C[2] + depth * rays[..., 2]).detach() < level  # the apparent point's height
    # the floor keeps a ray that never meets the water finite in value and gradient (its R is zeroed)
    R = reflectance((-vn).clamp(min=GRAZING_COS), water.n)
    return R * wet, mirrored


def sky_radiance(sky, directions):
    """[..., 3] linear radiance of the sky map sky [S, S, 3] (`SKY_SIZE`, the module docstring) in the unit
    directions [..., 3], bilinear in their world (x, y) (`grid_sample`, align_corners: the outer texels'
    centres on the square's edges). Differentiable in both."""
    shape = directions.shape[:-1]
    grid = directions[..., :2].reshape(1, 1, -1, 2).to(sky.dtype)  # [1, 1, P, 2] (x: column, y: row)
    out = torch.nn.functional.grid_sample(sky.permute(2, 0, 1)[None], grid, mode="bilinear",
                                          padding_mode="border", align_corners=True)  # [1, 3, 1, P]
    return out[0, :, 0].T.reshape(*shape, 3)


def sky_directions(size: int = SKY_SIZE, dtype=torch.float32, device=None):
    """[size, size, 3] the unit directions of the sky map's texels (z >= 0; the corners beyond the unit disk
    at the horizon): to build a map from a function of the direction."""
    t = torch.linspace(-1, 1, size, dtype=dtype, device=device)
    y, x = torch.meshgrid(t, t, indexing="ij")
    r = torch.sqrt(x * x + y * y).clamp(min=1)  # the corners: pulled onto the horizon
    x, y = x / r, y / r
    return torch.stack([x, y, torch.sqrt((1 - x * x - y * y).clamp(min=0))], -1)


def reflect(lin, R, radiance):
    """[..., 3] (1 - R) lin + R radiance, all in linear light: lin [..., 3] what the water shows, R [...] each
    pixel's Fresnel reflectance (`surface_reflection`, 0 on dry pixels, which stay as they are), radiance
    [..., 3] the mirrored sky's (`sky_radiance`). The 1 - R is the transmitted share of the light from under
    the water; the radiance step 1 / n^2 of the refraction is a separate factor (`refract_gaussians`)."""
    return lin + R[..., None] * (radiance - lin)


def add_reflection(image, R, radiance):
    """image [..., 3] (sRGB) -> `reflect` in linear light, re-encoded."""
    return linear_to_srgb(reflect(srgb_to_linear(image), R, radiance))
