"""Projection of 2D Gaussian surfels (2DGS, Huang et al. 2024), in PyTorch for every backend: the torch and
cpu compositing read `rays`, gsplat's reads the ray `transforms`.

A surfel is a centre mu and two scaled world tangents a = s_u t_u, b = s_v t_v: the points
X(u, v) = mu + u a + v b carry the weight G = exp(-(u^2 + v^2) / 2). Any pair (a, b) is allowed, so an
affine map of the surfel (the refraction Jacobian J: a' = J a, b' = J b) is the same kind of surfel.

Ray-splat intersection (2DGS): in the camera frame, with centre p and tangents a, b (rotated), the ray
X = z r through a pixel, r = ((px - cx) / fx, (py - cy) / fy, 1), meets the surfel's plane at
u = (b x p) . r / n . r,  v = (p x a) . r / n . r,  z = n . p / n . r,  with n = a x b (Cramer's rule).
All three are ratios of functions affine in the pixel. Written about the projected centre
(dx, dy) = (px - u_c, py - v_c), where (b x p) . r and (p x a) . r vanish exactly:
  q0 = A0 dx + B0 dy,  q1 = A1 dx + B1 dy,  q2 = A2 dx + B2 dy + C2,  (u, v) = (q0, q1) / q2,
  depth z = z_c C2 / q2  (z_c: the centre's camera z),
which keeps float32 accurate (no large terms cancelling at the centre). `rays` holds (A0, B0, A1, B1, A2,
B2, C2) per surfel.

Per pixel (both backends): rho3 = u^2 + v^2 (infinite where q2 = 0, a ray parallel to the plane), the
2DGS low-pass filter rho2 = 2 (dx^2 + dy^2) (a screen Gaussian of sigma sqrt(2)/2 px around the projected
centre), rho = min(rho3, rho2), alpha = min(0.99, o exp(-rho / 2)); the sample's depth is the plane
intersection's z where rho3 <= rho2 and the centre's z where the filter wins (as 2DGS: an edge-on surfel
reduces to a small screen-aligned blob at its centre's depth).

Screen extent: alpha >= 1/255 exactly where rho <= r2 = 2 ln(255 o), i.e. inside the image of the
surfel's disk of radius sqrt(r2) (an ellipse, boxed exactly from its dual conic) or inside the filter's
disk of radius sqrt(r2 / 2) px. A surfel whose disk reaches the camera's plane z = 0 has no bounded
image (the ellipse becomes a hyperbola) and is culled, as is one whose centre is nearer than 0.01.
The box is a pure acceleration: renders do not depend on tiles or backend.

`means2d` is the projection of the centre (gsplat's own 2DGS projection uses the centre of the disk's image
conic instead, which differs for tilted surfels). The camera-frame centre is rebuilt from it (same point), so
`means2d.grad` is the full screen-space gradient of the loss at fixed depth, as for `rasterize`.

The gsplat backend takes the same surfels as gsplat's "ray transforms" T = K [a b p] (which maps (u, v, 1)
to homogeneous pixels: the 2DGS paper's KWH, stored by rows as gsplat stores it), built here from the
tangents in a few differentiable ops: no quaternion, no SVD. For a pixel (px, py) gsplat intersects the
planes h_u = px T_2 - T_0 and h_v = py T_2 - T_1; (u, v) = (h_u x h_v)_xy / (h_u x h_v)_z is the same
intersection as `rays` gives (tests/test_surfel.py compares them).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from ragsplat.camera import Camera
from ragsplat.raster.reference.project import ALPHA_MIN, BOX_PAD, NEAR


class SurfelsProjected(NamedTuple):
    means2d: torch.Tensor  # [N, 2] pixels, projected centres, differentiable
    rays: torch.Tensor  # [N, 7] (A0, B0, A1, B1, A2, B2, C2): pixel -> surfel plane, differentiable
    depths: torch.Tensor  # [N] camera z of the centres, differentiable
    normals: torch.Tensor  # [N, 3] unit world normals facing the camera, differentiable
    box: torch.Tensor  # [N, 4] int64 inclusive pixel ranges (i0, i1, j0, j1), clipped to the image
    visible: torch.Tensor  # [N] bool
    radii: torch.Tensor  # [N] int32 max distance (pixels) from means2d to the box edge, 0 = not visible
    reach: torch.Tensor  # [N, 2] int32 the same per axis (x, y): the box lies within means2d +- reach
    transforms: torch.Tensor | None  # [N, 3, 3] K [a b p], differentiable; only with transforms=True


def project_surfels(means: torch.Tensor, tangents: torch.Tensor, opacities: torch.Tensor,
                    camera: Camera, transforms: bool = False) -> SurfelsProjected:
    """Project surfels (means [N, 3], scaled world tangents [N, 3, 2], opacities [N]) into `camera`;
    `transforms`: also gsplat's ray transforms (see the module notes)."""
    dtype, device = means.dtype, means.device
    R = camera.tensor("R", dtype, device)
    tc = camera.tensor("t", dtype, device)
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    pc = means @ R.T + tc  # [N, 3]
    front = pc[:, 2] >= NEAR
    z = torch.where(front, pc[:, 2], torch.ones_like(pc[:, 2]))  # culled ones get a harmless z
    u = fx * pc[:, 0] / z + cx
    v = fy * pc[:, 1] / z + cy
    means2d = torch.stack([u, v], -1)  # [N, 2]
    rc = torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], -1)  # [N, 3] ray of the centre
    p = rc * z[:, None]  # [N, 3] the camera-frame centre, as a function of means2d and z
    ab = R @ tangents  # [N, 3, 2] camera-frame tangents
    a, b = ab[..., 0], ab[..., 1]
    n = torch.linalg.cross(a, b)  # [N, 3]
    hu = torch.linalg.cross(b, p)
    hv = torch.linalg.cross(p, a)
    rays = torch.stack([hu[:, 0] / fx, hu[:, 1] / fy, hv[:, 0] / fx, hv[:, 1] / fy, n[:, 0] / fx,
                        n[:, 1] / fy, (n * rc).sum(-1)], -1)  # [N, 7]
    T = None
    if transforms:
        K = camera.tensor("K", dtype, device)
        T = K @ torch.stack([a, b, p], -1)  # [N, 3, 3]
        # placed at means2d: `shift` is zero, and its two terms cancel in every gradient but means2d's own,
        # which becomes the translation of the surfel's whole image on the screen, as the twins' dx = px -
        # means2d make it (densification reads it); T's row 2, (a_z, b_z, z), does not move with it
        shift = means2d - torch.stack([u, v], -1)  # [N, 2]
        T = T + torch.cat([shift[:, :, None] * T[:, 2:3], torch.zeros_like(T[:, :1])], 1)

    normals = torch.nn.functional.normalize(torch.linalg.cross(tangents[..., 0], tangents[..., 1]), dim=-1)
    centre = camera.tensor("camera_center", dtype, device)
    with torch.no_grad():
        facing = torch.where((normals * (centre - means)).sum(-1) < 0, -1.0, 1.0).to(dtype)
    normals = normals * facing[:, None]  # [N, 3]

    with torch.no_grad():
        box, visible, reach = _screen_box(a.detach(), b.detach(), p.detach(), u.detach(), v.detach(),
                                          opacities.detach(), front, camera)
    return SurfelsProjected(means2d, rays, pc[:, 2], normals, box, visible, reach.amax(-1), reach, T)


def _screen_box(a, b, p, u, v, opacities, front, camera: Camera):
    """Pixel box of each surfel (see the module notes), in float64 so every backend bins alike: (box [N, 4],
    visible [N], reach [N, 2] int32 pixels from (u, v) to the box's farther edge per axis, 0 if not
    visible)."""
    a, b, p, u, v = (x.double() for x in (a, b, p, u, v))
    W, H = camera.width, camera.height
    r2 = 2 * torch.log(torch.clamp(opacities.double(), min=ALPHA_MIN) * 255.0)  # [N]

    def screen(w):  # K w: screen homogeneous coordinates (x, y, w) of camera-frame vectors [N, 3]
        return camera.fx * w[:, 0] + camera.cx * w[:, 2], camera.fy * w[:, 1] + camera.cy * w[:, 2], w[:, 2]

    (ax, ay, az), (bx, by, bz), (px, py, pz) = screen(a), screen(b), screen(p)
    # Dual conic of the disk of radius sqrt(r2): T diag(1, 1, -1) T^T with T = K [sqrt(r2) a, sqrt(r2) b, p].
    d00 = r2 * (ax * ax + bx * bx) - px * px
    d11 = r2 * (ay * ay + by * by) - py * py
    d02 = r2 * (ax * az + bx * bz) - px * pz
    d12 = r2 * (ay * az + by * bz) - py * pz
    d22 = r2 * (az * az + bz * bz) - pz * pz
    bounded = d22 < 0  # the disk lies in front of the camera plane: its image is an ellipse
    d22 = torch.where(bounded, d22, -torch.ones_like(d22))
    xc, yc = d02 / d22, d12 / d22  # ellipse centre
    ex = torch.sqrt(torch.clamp(d02 * d02 - d00 * d22, min=0)) / -d22  # half-widths
    ey = torch.sqrt(torch.clamp(d12 * d12 - d11 * d22, min=0)) / -d22
    rf = torch.sqrt(r2 / 2)  # the low-pass filter's disk
    lo_u = torch.minimum(xc - ex, u - rf) - BOX_PAD
    hi_u = torch.maximum(xc + ex, u + rf) + BOX_PAD
    lo_v = torch.minimum(yc - ey, v - rf) - BOX_PAD
    hi_v = torch.maximum(yc + ey, v + rf) + BOX_PAD
    # Pixel i is in the box when its centre i + 0.5 lies in [lo, hi].
    i0 = torch.ceil(lo_u - 0.5).clamp(-1, W)
    i1 = torch.floor(hi_u - 0.5).clamp(-1, W)
    j0 = torch.ceil(lo_v - 0.5).clamp(-1, H)
    j1 = torch.floor(hi_v - 0.5).clamp(-1, H)
    ok = front & bounded & (opacities >= ALPHA_MIN) & torch.isfinite(lo_u + hi_u + lo_v + hi_v)
    visible = ok & (i1 >= 0) & (i0 <= W - 1) & (j1 >= 0) & (j0 <= H - 1) & (i0 <= i1) & (j0 <= j1)
    box = torch.stack([i0.clamp(0, W - 1), i1.clamp(0, W - 1), j0.clamp(0, H - 1), j1.clamp(0, H - 1)], -1)
    box = torch.where(visible[:, None], box, torch.zeros_like(box)).to(torch.int64)
    reach = torch.stack([torch.maximum(u - lo_u, hi_u - u), torch.maximum(v - lo_v, hi_v - v)], -1)  # [N, 2]
    reach = torch.where(visible[:, None], torch.ceil(reach), torch.zeros_like(reach)).to(torch.int32)
    return box, visible, reach
