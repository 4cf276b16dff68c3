"""Refraction at a calm planar air-water interface: true -> apparent Gaussians (RA-GS).

Geometry, per camera: centre C at height H above the plane z = level, a submerged point P at depth
d = level - z > 0 and horizontal offset v = P_xy - C_xy, r = |v|. The light path from P bends at the
interface point at radius s = H tan(theta_a) with sin(theta_a) = n sin(theta_w). The apparent point P'
is where the straight air ray through the interface point reaches depth d' below the plane.

The unknown is alpha = tan(theta_a) / r (= s / (H r)), which stays finite at nadir (r = 0). With
D = sqrt(n^2 + (n^2 - 1) r^2 alpha^2) one has tan(theta_w) = r alpha / D, and Snell's law plus the
geometry H tan(theta_a) + d tan(theta_w) = r become

    g(alpha) = alpha (H + d / D) - 1 = 0,      g'(alpha) = H + d n^2 / D^3 > 0.

g is increasing and concave, so iterations started below the root climb towards it. Two lower bounds are
known in closed form: the paraxial 1 / (H + d / n) and, since tan(theta_w) < 1 / sqrt(n^2 - 1),
(r sqrt(n^2 - 1) - d) / (H r sqrt(n^2 - 1)) at grazing views; the solve starts from the larger one and
takes Halley steps (Newton alone crawls through the knee where the water leg saturates, H << d ~ r),
kept inside [lower bound, 1 / H].
The apparent point (the paper's Eq. 5 rewritten in alpha) is

    d' = d n^2 / D^3  (so z' = level - d'),   P'_xy = C_xy + rho v  with  rho = r'/r = alpha (H + d').

At n = 1: D = 1, alpha = 1 / (H + d), d' = d, rho = 1. Gradients never pass through the solver loop: one
final Newton step with a detached slope turns the solve into implicit differentiation, so gradients
reach the points, the camera, the water level and n.

A river's surface slopes: `WaterSurface.slope` makes it the tilted plane z = level + sx x + sy y. Refraction
depends on the interface's normal alone, so the tilted transform is the flat one in the plane's own frame,
exactly: rotate the world so that the normal is +z, transform, rotate back (`water_surface.plane_frame`).
Gradients reach the slope through the rotation as they reach the level.

Water absorbs along the light's path: from P to the interface the bent ray runs L = d /
cos(theta_w) in the water. With t = r alpha = tan(theta_a), sin(theta_w) = t / (n sqrt(1 + t^2)), so
cos(theta_w) = D / (n sqrt(1 + t^2)) and L = d n sqrt(1 + t^2) / D (`water_paths`), the solve's alpha reused;
at n = 1 it is the straight ray's share below the level, d sqrt(1 + t^2). `refract_gaussians(attenuation=c)`
multiplies a submerged Gaussian's radiance by exp(-c L) per channel. The daylight that lights the point has
crossed the water too, k d of it on the way down (`downwelling` k: 1 / sin of the sun's elevation for the
direct sun): with k, by exp(-c (L + k d)). That factor does not change with the view, so a Gaussian's colour
can absorb it; it matters where the colour is kept from trending with depth (the trainer's `detrend_albedo`),
and then fixes c at the water's own coefficient, not c (1 + k d / L).

The water column in front of what a pixel renders adds a veil B_inf (1 - exp(-c_b L)) (backscatter, SeaThru's
model), L the pixel's path in the water. The rendered depth gives the APPARENT point on the pixel's ray, and
the apparent depth d' = d n^2 / D^3 inverts in closed form along that ray: L = d' (n^2 - 1 + cos^2 theta_a) /
(n cos^3 theta_a) (`pixel_water_paths`, no second render); `add_backscatter` adds the veil in linear light
(`backscatter_veil`).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
import torch

from ragsplat.gaussians import covariance
from ragsplat.water_surface import WaterSurface, frames, into_frame, out_of_frame

SCALE_MODES = ("none", "isotropic", "determinant", "anisotropic")
# Gaussians whose centre lies less than this below the level blend from their true state (at the level) to
# the refracted one (at this depth and deeper), so that scale, opacity and colour, and their gradients, are
# continuous across the water line (the refraction factors jump there: x0.88 scale, x0.57 opacity at
# n = 1.33). Thin next to the benchmark's 5 cm cells; the blend's slope, at most 1.9 x the jump / band, keeps
# float32 gradients moderate. Positions need no blend: the apparent point tends to the true one at the level.
WATERLINE_BAND = 0.01  # metres


def waterline_weight(d):
    """[M] weight in [0, 1] of the refracted state for depths d [M]: smootherstep(d / WATERLINE_BAND), 0 at
    the level, 1 from the band's depth on, flat to second order at both ends (C2: values and gradients are
    continuous, and finite differences of the gradient agree with it right at the band's edge)."""
    t = (d / WATERLINE_BAND).clamp(0, 1)
    return t * t * t * (t * (6 * t - 15) + 10)


def _scalar(x, like, dtype=None):
    """A number or 0-d tensor `x` as a tensor of `like`'s device and `dtype` (`like`'s when None): a tensor
    is converted, a number filled there (`torch.as_tensor` of a number copies it from the host, which waits
    for the device's queue)."""
    dtype = like.dtype if dtype is None else dtype
    if torch.is_tensor(x):
        return x.to(dtype=dtype, device=like.device)
    return torch.full((), float(x), dtype=dtype, device=like.device)


def _fade(w, n):  # [M] the factor on opacity and radiance: 1 at the level, 1 / n^2 below the band
    return torch.lerp(torch.ones_like(w), 1 / _scalar(n, w) ** 2, w)


def opacity_factor(means, water: WaterSurface):
    """[N] rendered / true opacity of Gaussians centred at means [N, 3] under `water` (RA-GS's 1 / n^2,
    blended at the water line as in `refract_gaussians`; 1 above the level). Pruning and opacity resets
    apply their thresholds to what is rendered through it."""
    # the depth along the surface's normal (its frames'), as the transform blends
    if water.tilted or water.curved:
        return _fade(waterline_weight(-into_frame(*frames(water, means), means)[:, 2]), water.n)
    level = _scalar(water.level, means)
    return _fade(waterline_weight(level - means[:, 2]), water.n)


def srgb_to_linear(c):
    """The sRGB transfer function, inverted (IEC 61966-2-1); safe for values outside [0, 1] (SH colours)."""
    return torch.where(c <= 0.04045, c / 12.92, ((c.clamp(min=0.04045) + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c):
    return torch.where(c <= 0.0031308, 12.92 * c, 1.055 * c.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


# Halley steps after the lower-bound start: measured over the stability domain (`ragsplat bench
# refraction`), 3 steps reach float32 round-off and 4 reach float64 round-off.
SOLVER_STEPS = {torch.float64: 4, torch.float32: 3, torch.float16: 2, torch.bfloat16: 2}


def solve_alpha(r2, d, H, n, steps: int | None = None):
    """Snell solve in alpha = tan(theta_a) / r. Broadcasts; r2 = r^2 [N], d > 0 [N], H > 0, n >= 1.

    Returns alpha [N] carrying implicit-function gradients w.r.t. r2, d, H and n.
    """
    dtype = torch.result_type(r2, d)
    steps = SOLVER_STEPS.get(dtype, 4) if steps is None else steps
    n = _scalar(n, r2, dtype)
    H = _scalar(H, r2, dtype)
    with torch.no_grad():
        r2_, d_, H_, n_ = r2.detach(), d.detach(), H.detach(), n.detach()
        n2, m2 = n_ * n_, (n_ - 1) * (n_ + 1)  # not n^2 - 1: cancellation near n = 1
        rm = torch.sqrt(r2_ * m2)  # r sqrt(n^2 - 1)
        paraxial = 1 / (H_ + d_ / n_)
        # Grazing bound; where r m <= d it is non-positive and the paraxial bound is the larger one.
        grazing = (rm - d_) / (H_ * torch.clamp(rm, min=torch.finfo(dtype).tiny))
        lower = torch.maximum(paraxial, grazing)
        upper = 1 / H_  # the water leg only adds to the radius
        alpha = lower
        c, dn2 = m2 * r2_, d_ * n2  # loop invariants
        for _ in range(steps):
            D2 = n2 + c * alpha * alpha
            inv_D = torch.rsqrt(D2)
            g = alpha * (H_ + d_ * inv_D) - 1
            water_slope = dn2 * inv_D / D2  # d n^2 / D^3
            g1 = H_ + water_slope
            g2 = -3 * c * alpha * water_slope / D2
            # Halley; g' > 0 and g'' <= 0 keep the denominator >= 2 g'^2 above the root, and the clamp
            # guards the step from below.
            den = torch.clamp(2 * g1 * g1 - g * g2, min=0.5 * g1 * g1)
            alpha = torch.minimum(torch.maximum(alpha - 2 * g * g1 / den, lower), upper)
        slope = H_ + dn2 / torch.sqrt(n2 + c * alpha * alpha) ** 3
    # One tracked Newton step at the root: value unchanged to round-off, gradient = -dg/dx / g'.
    D = torch.sqrt(n * n + (n - 1) * (n + 1) * r2 * alpha * alpha)
    return alpha - (alpha * (H + d / D) - 1) / slope


def apparent_offsets(r2, d, H, n, steps: int | None = None):
    """(rho = r'/r, apparent depth d') for broadcast r2 [N], d [N], H, n. See the module docstring."""
    return _offsets(solve_alpha(r2, d, H, n, steps), r2, d, H, n)


def _offsets(alpha, r2, d, H, n):  # (rho, d') [N] from the solved alpha [N]
    D = torch.sqrt(n * n + (n - 1) * (n + 1) * r2 * alpha * alpha)
    d_app = d * n * n / D**3
    return alpha * (H + d_app), d_app


class _Local(NamedTuple):
    v: torch.Tensor  # [M, 2] horizontal offset from the camera nadir
    r2: torch.Tensor  # [M]
    d: torch.Tensor  # [M] true depth
    H: torch.Tensor  # [] camera height
    n: torch.Tensor  # []
    origin: torch.Tensor  # [2] camera nadir
    level: torch.Tensor  # []


def _local(points, camera_center, water) -> _Local:
    level = _scalar(water.level, points)
    n = _scalar(water.n, points)
    C = torch.as_tensor(camera_center, dtype=points.dtype, device=points.device)
    v = points[:, :2] - C[..., :2]  # C [3], or [M, 3]: a camera per point (the curved surface's own frames)
    return _Local(v, (v * v).sum(-1), level - points[:, 2], C[..., 2] - level, n, C[..., :2], level)


# [M] in-water length of the bent ray, d / cos(theta_w) (module docstring)
def _path_lengths(loc: _Local, alpha):
    t2 = loc.r2 * alpha * alpha  # tan^2(theta_a)
    D = torch.sqrt(loc.n * loc.n + (loc.n - 1) * (loc.n + 1) * t2)
    return loc.d * loc.n * torch.sqrt(1 + t2) / D


def water_paths(points, camera_center, water: WaterSurface, steps: int | None = None):
    """[N] length (m) of the light path inside the water from points [N, 3] to the surface, along the ray
    that reaches camera_center [3] (refracted at the surface: d / cos(theta_w) under a flat one); 0 at or
    above the surface. A tilted or curved surface: the flat length in its frame(s), as `apparent_points`.
    Gradients reach the points, the camera and the water. Raises ValueError for a camera not above the
    water."""
    _check_camera(camera_center, water)
    C = torch.as_tensor(camera_center, dtype=points.dtype, device=points.device)
    if water.tilted or water.curved:  # a length is the same in any frame
        R, p0 = frames(water, points)
        points, C, water = into_frame(R, p0, points), into_frame(R, p0, C), _flat_in_plane(water)
    wet = _submerged(points, water)
    loc = _local(points[wet], C[wet] if C.dim() == 2 else C, water)  # C [N, 3]: a curved surface's frames
    L = _path_lengths(loc, solve_alpha(loc.r2, loc.d, loc.H, loc.n, steps))
    return torch.zeros_like(points[:, 0]).index_put((wet,), L)


def upward_normals(g):
    """[..., 3] the upward unit normals of a surface with gradients g [..., 2] (dz/dx, dz/dy)."""
    return torch.cat([-g, torch.ones_like(g[..., :1])], -1) / torch.sqrt(1 + (g * g).sum(-1, keepdim=True))


def facet_offsets(points, camera_center, water: WaterSurface, gradient):
    """[N, 2] how far, horizontally, a rippled surface moves where the ray from camera_center [3] to each
    true point [N, 3] lands at the point's depth: the ray crosses the flat surface at p [2] and is bent there
    by the facet of gradient(p) [M, 2] (dz/dx, dz/dy of the ripples at p [M, 2]) instead of by the flat one,
    on which it lands on the point. Exact in the facet's slope, first order in its height (the facet passes
    through the flat crossing); points at or above the level get 0. The bed point a photo sees through its
    ripples where it sees this point is the point plus the offset; so the photo shows the point where the
    flat surface shows the point minus it. A horizontal surface only (ValueError otherwise, or for a camera
    not above the water)."""
    _check_camera(camera_center, water)
    if water.tilted or water.curved:
        raise ValueError("facet_offsets: a horizontal water surface only")
    wet = _submerged(points, water)
    loc = _local(points[wet], camera_center, water)
    reach = loc.H * solve_alpha(loc.r2, loc.d, loc.H, loc.n)[:, None] * loc.v  # [M, 2] H tan(theta_a) along v
    down = torch.cat([reach, -loc.H.expand(len(loc.d))[:, None]], -1)  # [M, 3] camera -> crossing
    down = down / torch.linalg.vector_norm(down, dim=-1, keepdim=True)
    facet = upward_normals(gradient(loc.origin + reach))  # [M, 3]
    flat = torch.zeros_like(facet)
    flat[:, 2] = 1

    def landing(normal):  # [M, 2] from the crossing to depth d, along the refracted ray (Snell, vector form)
        cos_i = -(down * normal).sum(-1, keepdim=True)
        cos_t = torch.sqrt(1 - (1 - cos_i * cos_i) / (loc.n * loc.n))
        t = down / loc.n + (cos_i / loc.n - cos_t) * normal
        return t[:, :2] * (loc.d / -t[:, 2])[:, None]

    return torch.zeros_like(points[:, :2]).index_put((wet,), landing(facet) - landing(flat))


GRAZING_COS = 1e-3  # `pixel_water_paths`' floor on cos(theta_a)


def pixel_water_paths(rays, depth, camera_center, water: WaterSurface):
    """[...] in-water length (m) of each pixel's light path to the point it renders, from the rendered depth.

    rays [..., 3]: the pixels' world ray directions scaled to unit camera z, depth [...]: the rendered (alpha-
    normalised) camera z-depth, so that P' = C + depth ray is the APPARENT point the pixel sees; camera_center
    [3]. Inverting the RA-GS map along the ray (module docstring: d' = d n^2 / D^3 with the ray's own
    t = tan(theta_a)) gives the true depth d = n d' (cos theta_w / cos theta_a)^3 and the bent path
    L = d / cos theta_w = d' (n^2 - 1 + cos^2 theta_a) / (n cos^3 theta_a): n d' at nadir, the straight ray's
    share below the level at n = 1, 0 where P' is at or above the surface (d' <= 0: banks, nothing rendered).
    A tilted plane: d' and theta_a to its normal (exact, as the transform works in its frame); a curved one:
    the tangent plane above P' (the transform's is above the true point, a few cm aside). Differentiable in
    depth, the camera and the water; gradients are finite everywhere (0 where L = 0)."""
    C = torch.as_tensor(camera_center, dtype=rays.dtype, device=rays.device)
    p = C + depth[..., None] * rays  # [..., 3] the apparent point
    if water.tilted or water.curved:
        normal = upward_normals(water.gradient(p[..., :2]))  # [..., 3]
        d_app = water.depth(p) * normal[..., 2]  # [...] to the (tangent) plane along its normal
        down = -(rays * normal).sum(-1)
    else:
        d_app, down = water.depth(p), -rays[..., 2]
    # [...] cos(theta_a) to the normal; the floor keeps a ray that never meets the water (d' < 0, also where
    # nothing is rendered: P' = C) finite in value and gradient, and no bed is seen within 0.06 deg of grazing
    cos = (down / torch.linalg.vector_norm(rays, dim=-1)).clamp(min=GRAZING_COS)
    n = _scalar(water.n, rays)
    # clamps, not wheres: fewer ops
    return d_app.clamp(min=0) * ((n - 1) * (n + 1) + cos * cos) / (n * cos**3)


def backscatter_veil(alpha, paths, veil, coefficients):
    """[..., 3] the water column's veil B_inf (1 - exp(-c_b L)) in linear light, weighted by alpha.

    alpha [..., 1] the rendered coverage, paths [...] each pixel's in-water length L (`pixel_water_paths`),
    veil B_inf [3] (linear radiance of infinitely deep water), coefficients c_b [3] (1/m). The veil is
    weighted by alpha: a pixel's uncovered share shows the background (the model's stand-in for what it has
    not built, e.g. random colours that punish holes), which the veil leaves as it is, so that a hole cannot
    pass for deep water."""
    return -alpha * veil * torch.expm1(-coefficients * paths[..., None])


def add_backscatter(image, alpha, paths, veil, coefficients):
    """image [..., 3] (sRGB) + the water column's veil (`backscatter_veil`) in linear light, re-encoded."""
    return linear_to_srgb(srgb_to_linear(image) + backscatter_veil(alpha, paths, veil, coefficients))


def _place(loc: _Local, rho, d_app):  # [M, 3] apparent points from r'/r and d'
    return torch.cat([loc.origin + rho[:, None] * loc.v, (loc.level - d_app)[:, None]], -1)


# under torch.compile: a graph break (it reads a value), not a traced float() and a warning (_GRAPH_BREAKS)
def _check_camera(camera_center, water) -> None:
    C = torch.as_tensor(camera_center).detach().double().reshape(-1, 3)  # one camera, or one per row
    if not len(C):
        return
    with torch.no_grad():
        surface = torch.as_tensor(water.height(C[:, :2]), dtype=C.dtype)
    low = int(torch.argmin(C[:, 2] - surface))
    if not float(C[low, 2]) > float(surface[low]):
        raise ValueError(f"camera centre z = {float(C[low, 2])} is not above the water surface "
                         f"({float(surface[low])} there): refraction needs the camera in air")


def _flat_in_plane(water: WaterSurface) -> WaterSurface:  # a tilted surface in its own frame: q_z = 0
    return WaterSurface(0.0, water.n)


def _submerged(points, water):  # [N] bool
    return points[:, 2] < _scalar(water.level, points)


def apparent_points(points, camera_center, water: WaterSurface, steps: int | None = None):
    """True points [N, 3] -> apparent points [N, 3] seen from camera_center [3] through the water.

    Points at or above the level are returned unchanged. Raises ValueError for a camera not above the level.
    """
    _check_camera(camera_center, water)
    if water.is_identity:
        return points.clone()
    if water.tilted or water.curved:
        return _apparent_in_frames(points,
                                   torch.as_tensor(camera_center, dtype=points.dtype, device=points.device),
                                   water, steps)
    wet = _submerged(points, water)
    loc = _local(points[wet], camera_center, water)
    return points.index_put((wet,), _place(loc, *apparent_offsets(loc.r2, loc.d, loc.H, loc.n, steps)))


def _apparent_in_frames(points, centers, water: WaterSurface, steps):
    """Apparent points [N, 3] under a tilted or curved surface: the flat transform in its frame(s)
    (`frames`), each point seen from centers [3] or its own [N, 3]; points above the surface stay exactly as
    they are."""
    R, p0 = frames(water, points)
    local = into_frame(R, p0, points)
    moved = apparent_points_each(local, into_frame(R, p0, centers).expand_as(local), _flat_in_plane(water),
                                 steps)
    return torch.where((local[:, 2] < 0)[:, None], out_of_frame(R, p0, moved), points)


def apparent_points_each(points, centers, water: WaterSurface, steps: int | None = None):
    """[M, 3] apparent points of true points [M, 3], each seen from its own camera centre centers [M, 3] (the
    bundle adjustment's observations); points above the surface are returned unchanged."""
    if water.is_identity:
        return points.clone()
    if water.tilted or water.curved:
        return _apparent_in_frames(points, centers, water, steps)
    level = _scalar(water.level, points)
    wet = points[:, 2] < level
    C = centers[wet]
    v = points[wet, :2] - C[:, :2]
    rho, d_app = apparent_offsets((v * v).sum(-1), level - points[wet, 2], C[:, 2] - level,
                                  _scalar(water.n, points), steps)
    return points.index_put((wet,), torch.cat([C[:, :2] + rho[:, None] * v, (level - d_app)[:, None]], -1))


class _Derivatives(NamedTuple):
    """alpha, rho, d' and the total derivatives of rho and d' w.r.t. r2 and d, for the submerged points
    [M]."""

    alpha: torch.Tensor
    rho: torch.Tensor
    d_app: torch.Tensor
    rho_r2: torch.Tensor
    rho_d: torch.Tensor
    dapp_r2: torch.Tensor
    dapp_d: torch.Tensor


def _derivatives(loc: _Local, steps: int | None) -> _Derivatives:
    n2, m2 = loc.n * loc.n, (loc.n - 1) * (loc.n + 1)
    alpha = solve_alpha(loc.r2, loc.d, loc.H, loc.n, steps)
    D = torch.sqrt(n2 + m2 * loc.r2 * alpha * alpha)
    D3 = D**3
    d_app = loc.d * n2 / D3
    slope = loc.H + d_app  # g'(alpha)
    # Implicit derivatives of alpha from g(alpha; r2, d) = 0.
    alpha_r2 = m2 * loc.d * alpha**3 / (2 * D3 * slope)
    alpha_d = -alpha / (D * slope)
    # dD/dx = dD/dalpha * dalpha/dx + explicit part (only r2 appears explicitly).
    D_alpha = m2 * loc.r2 * alpha / D
    D_r2 = m2 * alpha * alpha / (2 * D) + D_alpha * alpha_r2
    D_d = D_alpha * alpha_d
    dapp_r2 = -3 * d_app / D * D_r2
    dapp_d = n2 / D3 - 3 * d_app / D * D_d
    rho = alpha * slope
    return _Derivatives(alpha, rho, d_app, alpha_r2 * slope + alpha * dapp_r2,
                        alpha_d * slope + alpha * dapp_d, dapp_r2, dapp_d)


def _jacobian(loc: _Local, der: _Derivatives):  # [M, 3, 3]
    v = loc.v
    top_left = der.rho[:, None, None] * torch.eye(2, dtype=v.dtype, device=v.device) \
        + 2 * der.rho_r2[:, None, None] * v[:, :, None] * v[:, None, :]
    top_right = -(v * der.rho_d[:, None])[:, :, None]  # d/dz = -d/dd
    bottom_left = (-2 * der.dapp_r2[:, None] * v)[:, None, :]  # z' = level - d'
    bottom_right = der.dapp_d[:, None, None]  # dz'/dz = dd'/dd
    return torch.cat([torch.cat([top_left, top_right], 2), torch.cat([bottom_left, bottom_right], 2)], 1)


def apparent_jacobian(points, camera_center, water: WaterSurface, steps: int | None = None):
    """d apparent / d true [N, 3, 3] in world axes; identity for points at or above the level."""
    _check_camera(camera_center, water)
    N = points.shape[0]
    J = torch.eye(3, dtype=points.dtype, device=points.device).expand(N, 3, 3).clone()
    if water.is_identity:
        return J
    if water.tilted or water.curved:  # J_world = R^T J_frame R (a curved surface: its tangent planes')
        R, p0 = frames(water, points)
        C = into_frame(R, p0, torch.as_tensor(camera_center, dtype=points.dtype, device=points.device))
        return (R.transpose(-1, -2)
                @ apparent_jacobian(into_frame(R, p0, points), C, _flat_in_plane(water), steps) @ R)
    wet = _submerged(points, water)
    per_row = torch.is_tensor(camera_center) and camera_center.dim() == 2  # a curved surface's frames
    loc = _local(points[wet], camera_center[wet] if per_row else camera_center, water)
    return J.index_put((wet,), _jacobian(loc, _derivatives(loc, steps)))


def _column_norms(loc: _Local, der: _Derivatives):  # [M, 3]: |J e_x|, |J e_y|, |J e_z| without forming J
    v2 = loc.v * loc.v
    xy = (der.rho[:, None] ** 2
          + (4 * der.rho * der.rho_r2 + 4 * der.rho_r2**2 * loc.r2 + 4 * der.dapp_r2**2)[:, None] * v2)
    z = loc.r2 * der.rho_d**2 + der.dapp_d**2
    return torch.sqrt(torch.cat([xy, z[:, None]], -1))


def _abs_det(loc: _Local, der: _Derivatives):  # [M]: tangential rho times the radial-vertical 2x2 block
    j11 = der.rho + 2 * loc.r2 * der.rho_r2
    return torch.abs(der.rho * (j11 * der.dapp_d - 2 * loc.r2 * der.rho_d * der.dapp_r2))


# data-dependent: under torch.compile a graph break, not a traced bool() and a warning (_GRAPH_BREAKS)
def _wet_rows(wet):  # [M] indices of the True entries of wet [N], None when all are
    return None if bool(wet.all()) else wet.nonzero().squeeze(1)


class ApparentGaussians(NamedTuple):
    means: torch.Tensor  # [N, 3]
    scales: torch.Tensor  # [N, 3]
    quats: torch.Tensor  # [N, 4]
    opacities: torch.Tensor  # [N]
    colors: torch.Tensor  # [N, ...]
    covars: torch.Tensor | None  # [N, 3, 3] for scale="anisotropic", else None
    # [N, 3, 3] d apparent / d true (identity above the level, blended in the waterline band) for
    # scale="anisotropic", else None: it maps a surfel's tangent vectors exactly to first order (t' = J t)
    jacobians: torch.Tensor | None


def refract_gaussians(means, scales, quats, opacities, colors, camera_center, water: WaterSurface,
                      position: bool = True, scale: str = "isotropic", opacity: bool = True,
                      color: bool = False, steps: int | None = None, covariances: bool = True,
                      attenuation: torch.Tensor | None = None, downwelling: float = 0.0,
                      check_camera: bool = True) -> ApparentGaussians:
    """Map true Gaussians to the apparent ones one camera sees through the water (RA-GS, per view).

    means [N, 3], scales [N, 3] (linear), quats [N, 4] (wxyz), opacities [N] in [0, 1], colors [N, ...]
    (sRGB-encoded, the training target's space), camera_center [3]. Only Gaussians whose centre is below
    the level change. `scale`: "none"; "isotropic" (the paper: s' = S s, S = (|J e_x| |J e_y| |J e_z|)^(1/3));
    "determinant" (S = |det J|^(1/3)); "anisotropic" (covars = J Sigma J^T and `jacobians` J, scales left
    as given; `covariances=False`: the Jacobians alone, which is all a surfel's tangents need).
    Opacity: alpha' = alpha / n^2. Colour: radiance / n^2 in linear light, re-encoded to sRGB. Within
    `WATERLINE_BAND` of the level each factor (S, J, 1 / n^2) blends from 1 (`waterline_weight`).
    `attenuation`: the water's attenuation coefficients c [3] (1/m, per channel of linear RGB) or None
    (nothing computed): each submerged Gaussian's radiance times exp(-c L) in linear light, L its in-water
    path (`water_paths`), which tends to 0 at the level and needs no blend; at n = 1 it alone applies.
    `downwelling` k (with `attenuation`): the daylight's path down to the Gaussian per metre of its depth d;
    the radiance is then times exp(-c (L + k d)) (module docstring).
    `check_camera`: a ValueError where the camera is not above the surface; False for a caller that has
    checked it (the check reads the centre back from the device, which waits for the device's queue).
    """
    if scale not in SCALE_MODES:
        raise ValueError(f"scale must be one of {SCALE_MODES}, got {scale!r}")
    if check_camera:
        _check_camera(camera_center, water)
    covars = jacobians = None
    if scale == "anisotropic":
        covars = covariance(quats, scales) if covariances else None
        jacobians = torch.eye(3, dtype=means.dtype, device=means.device).expand(len(means), 3, 3)
    if water.is_identity or not (position or opacity or color or scale != "none"):
        if attenuation is None:
            return ApparentGaussians(means, scales, quats, opacities, colors, covars, jacobians)
        # the geometry is the identity: absorb only
        position, scale, opacity, color = False, "none", False, False
    if water.tilted or water.curved:
        return _refract_in_frames(*frames(water, means), means, scales, quats, opacities, colors,
                                  camera_center, water, position, scale, opacity, color, steps, covars,
                                  attenuation, downwelling)
    wet = _submerged(means, water)
    rows = _wet_rows(wet)  # found once: a boolean index searches every time
    all_wet = rows is None

    def put(full, part):  # writes the submerged rows; skips the scatter when every Gaussian is submerged
        return part if all_wet else full.index_copy(0, rows, part)

    def take(full):
        return full if all_wet else full.index_select(0, rows)

    level = _scalar(water.level, means)
    w = waterline_weight(level - take(means)[:, 2])  # [M]
    if position or scale != "none" or attenuation is not None:
        per_row = torch.is_tensor(camera_center) and camera_center.dim() == 2  # a curved surface's frames
        loc = _local(take(means), take(camera_center) if per_row else camera_center, water)
        der = _derivatives(loc, steps) if scale != "none" else None
        alpha = der.alpha if der else solve_alpha(loc.r2, loc.d, loc.H, loc.n, steps)  # one solve for all
        if position:
            rho, d_app = (der.rho, der.d_app) if der else _offsets(alpha, loc.r2, loc.d, loc.H, loc.n)
            means = put(means, _place(loc, rho, d_app))
        if scale in ("isotropic", "determinant"):
            factor = (_column_norms(loc, der).prod(-1) if scale == "isotropic"
                      else _abs_det(loc, der)) ** (1 / 3)
            scales = put(scales, take(scales) * torch.lerp(torch.ones_like(factor), factor, w)[:, None])
        elif scale == "anisotropic":
            eye = torch.eye(3, dtype=means.dtype, device=means.device).expand(len(w), 3, 3)
            J = torch.lerp(eye, _jacobian(loc, der), w[:, None, None])
            if covars is not None:
                covars = put(covars, J @ take(covars) @ J.transpose(1, 2))
            jacobians = put(jacobians, J)
    fade = _fade(w, water.n)  # [M]
    if opacity:
        opacities = put(opacities, take(opacities) * fade)
    # the interface and the water scale radiance: factors in linear light
    if color or attenuation is not None:
        lin = srgb_to_linear(take(colors))
        if color:
            lin = lin * fade.reshape(-1, *[1] * (lin.dim() - 1))
        if attenuation is not None:  # Beer-Lambert along the bent ray, and the daylight's way down
            path = _path_lengths(loc, alpha)
            path = path + downwelling * loc.d if downwelling else path
            lin = lin * torch.exp(-attenuation * path[:, None])
        colors = put(colors, linear_to_srgb(lin))
    return ApparentGaussians(means, scales, quats, opacities, colors, covars, jacobians)


def _refract_in_frames(R, p0, means, scales, quats, opacities, colors, camera_center, water, position, scale,
                       opacity, color, steps, covars, attenuation, downwelling) -> ApparentGaussians:
    """`refract_gaussians` under a tilted or curved surface, in its frame(s) (`frames`): the flat transform
    there, positions and Jacobians rotated back (J_world = R^T J_frame R; covariances J Sigma J^T in the
    world). The isotropic and determinant scale factors are the frame's (the determinant is the same in any
    frame).

    A tilted plane is exact. A curved surface (a profile along the reach) refracts each Gaussian through the
    tangent plane above it: the light path meets the surface off the point's vertical (by up to d tan(theta_w)
    + the air leg's share), where the surface departs from that tangent plane by about curvature x offset^2 /
    2 (tests/test_water_surface.py measures it against a ray trace by Fermat's principle). Its Jacobians are
    the planes' (the plane's own motion with the point is left out of them, not of the gradients)."""
    local = into_frame(R, p0, means)
    C = into_frame(R, p0, torch.as_tensor(camera_center, dtype=means.dtype, device=means.device))
    out = refract_gaussians(local, scales, quats, opacities, colors, C, _flat_in_plane(water), position,
                            scale, opacity, color, steps, covariances=False, attenuation=attenuation,
                            downwelling=downwelling)
    if position:  # rows above the surface keep their coordinates exactly, not rotated there and back
        means = torch.where((local[:, 2] < 0)[:, None], out_of_frame(R, p0, out.means), means)
    jacobians = None
    if scale == "anisotropic":
        jacobians = R.transpose(-1, -2) @ out.jacobians @ R
        if covars is not None:
            covars = jacobians @ covars @ jacobians.transpose(1, 2)
    return ApparentGaussians(means, out.scales, quats, out.opacities, out.colors, covars, jacobians)


# marked for torch.compile when a compile is first asked for, not at import: torch.compiler.disable imports
# torch._dynamo, 3 s of CPU on the 2-core machine at the start of every command that imports this module,
# where only a training needs it (torch.optim's Adam imports it then): `ragsplat score`, `export`, a survey's
# first stages
_GRAPH_BREAKS = ("_check_camera", "_wet_rows")


@functools.cache
def compiled_refract_gaussians():
    """`refract_gaussians` through `torch.compile` (dynamic shapes): its few dozen small elementwise ops
    become a handful of fused kernels. That matters where every op is a kernel launch: on a GPU the eager
    transform is launch-bound (docs/lab/performance.md). Values and gradients equal the eager ones to
    round-off (tests/test_refraction.py); each new family of shapes compiles first (tens of seconds on a
    CPU)."""
    for name in _GRAPH_BREAKS:  # the compiled trace reads them here, as module globals
        globals()[name] = torch.compiler.disable(globals()[name])
    return torch.compile(refract_gaussians, dynamic=True)


VIEW_BINS = ((0, 2), (3, 4), (5, 6), (7, 9), (10, None))  # photos that see a point, inclusive classes


def views_through_water(points: np.ndarray, R: np.ndarray, centres: np.ndarray, K: np.ndarray,
                        sizes: np.ndarray, water, chunk: int = 500_000) -> np.ndarray:
    """[N] how many of the pinhole cameras R [V, 3, 3] (world -> camera), centres [V, 3], intrinsics K [V, 4]
    (fx, fy, cx, cy) and image sizes [V, 2] (width, height) hold each true point [N, 3] in their image, a
    submerged point at its apparent position through `water` (`WaterSurface`; exact refraction), a dry one
    where it is. A camera not above the surface sees nothing."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    seen = np.zeros(len(points), dtype=np.int64)
    for Rv, C, (fx, fy, cx, cy), (w, h) in zip(R, centres, K, sizes):
        if C[2] <= float(water.height(np.asarray(C[None, :2]))[0]):
            continue
        centre = torch.as_tensor(C, dtype=torch.float64)
        for s in range(0, len(points), chunk):
            with torch.no_grad():
                app = apparent_points(torch.as_tensor(points[s:s + chunk]), centre, water).numpy()
            pc = (app - C) @ np.asarray(Rv).T  # [n, 3] camera frame
            with np.errstate(divide="ignore", invalid="ignore"):  # a point in the camera's plane: not inside
                u, v = fx * pc[:, 0] / pc[:, 2] + cx, fy * pc[:, 1] / pc[:, 2] + cy
                seen[s:s + chunk] += (pc[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    return seen
