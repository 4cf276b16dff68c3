"""Fast CPU surfel compositing: numba kernels, parallel over tiles, float32 maths, hand-written backward.

Same semantics as the torch twin (`reference/surfel_composite.py`), organised as the 3DGS kernels of
`composite.py` (whose tile helpers it uses): the projection stays in PyTorch; per tile, surfels are visited
front to back and each one only touches the pixels of the tile that can reach alpha >= 1/255, row by row:
the span of the row inside the image of the surfel's disk (a quadratic in the pixel column, solved in
float64) joined with the span inside the low-pass filter's disk. Forward and backward evaluate alpha with the
same float32 code, so they skip the same (pixel, surfel) pairs.

Backward (as 3DGS): per pixel, back to front from its last composited surfel, restoring the transmittance
by division by (1 - alpha) and keeping running sums of what lies behind (features, and the distortion's
dD/dw_j w_j). With A = 1 - T_final and Z = sum_j w_j z_j the pixel's totals, the distortion
D = 2 sum_{j<i} w_i w_j (z_i - z_j) has
  dD/dw_i = 2 (2 (z_i (1 - T_i) - S_i) + Z - z_i A),  S_i = sum_{j<i} w_j z_j (Z minus what lies at and
  behind i),
  dD/dz_i = 2 w_i (2 (1 - T_i) + w_i - A)  (gsplat's formulas).
Each (tile, surfel) pair writes its own gradient slot, so tiles run in parallel without atomics.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from ragsplat.raster.cpu.composite import _chunks, _np32, _tile_box
from ragsplat.raster.reference.project import ALPHA_MAX, ALPHA_MIN, BOX_PAD, T_MIN, Bins
from ragsplat.raster.reference.surfel_project import SurfelsProjected

_F = np.float32
_HALF = _F(0.5)
_ONE = _F(1.0)
_TWO = _F(2.0)
_ZERO = _F(0.0)
_AMIN = _F(ALPHA_MIN)
_AMAX = _F(ALPHA_MAX)
_TMIN = _F(T_MIN)
_LOG255 = np.log(255.0)
_NC = 6  # per-surfel features: colour (3), normal (3)
_NO = _NC + 1  # composited per pixel: the features and the sample's z
# Gradient slot: mean2d (2), rays (7), centre z, opacity, features (6).
_NG = 2 + 7 + 1 + 1 + _NC


@njit(cache=True, inline="always")
def _span_coeffs(a0, b0, a1, b1, a2, b2, c2, r2):
    """Coefficients (float64) of the disk's image Q = q0^2 + q1^2 - r2 q2^2 = al dx^2 + 2 be dx + ga with
    be = be1 dy + be0 and ga = ga2 dy^2 + ga1 dy + ga0; `full`: not an ellipse in float64 (near-degenerate
    surfel), take whole box rows."""
    a0, b0, a1, b1 = np.float64(a0), np.float64(b0), np.float64(a1), np.float64(b1)
    a2, b2, c2 = np.float64(a2), np.float64(b2), np.float64(c2)
    al = a0 * a0 + a1 * a1 - r2 * a2 * a2
    return (al, a0 * b0 + a1 * b1 - r2 * a2 * b2, -r2 * a2 * c2, b0 * b0 + b1 * b1 - r2 * b2 * b2,
            -2.0 * r2 * b2 * c2, -r2 * c2 * c2, al <= 0 and c2 != 0)


@njit(cache=True, inline="always")
def _row_span(mx, dy, al, be1, be0, ga2, ga1, ga0, full, r2, i0, i1):
    """Pixels i in [i0, i1] of a row (dy = row centre - my, float64) whose centres can reach rho <= r2: the
    row's span inside the disk's image (Q <= 0, a quadratic in dx) joined with its span inside the
    filter's disk 2 (dx^2 + dy^2) <= r2. Padded; the per-pixel test decides."""
    if full:
        return i0, i1
    lo, hi = np.inf, -np.inf
    f = r2 / 2 - dy * dy
    if f >= 0:
        lo, hi = -np.sqrt(f), np.sqrt(f)
    if al > 0:
        be = be1 * dy + be0
        disc = be * be - al * (ga2 * dy * dy + ga1 * dy + ga0)
        if disc >= 0:
            root = np.sqrt(disc)
            lo, hi = min(lo, (-be - root) / al), max(hi, (-be + root) / al)
    if lo > hi:
        return 1, 0
    centre = np.float64(mx) - 0.5  # i + 0.5 = mx + dx  <=>  i = mx + dx - 0.5
    return (max(i0, np.int64(np.ceil(centre + lo - BOX_PAD))),
            min(i1, np.int64(np.floor(centre + hi + BOX_PAD))))


@njit(cache=True, inline="always")
def _sample(q0, q1, q2, rho2, zc, c2):
    """(rho, on_plane, z, 1 / q2, s, t) of one pixel and surfel (see `reference/surfel_project.py`)."""
    if q2 == 0:
        return rho2, False, zc, _ZERO, _ZERO, _ZERO
    inv = _ONE / q2
    s = q0 * inv
    t = q1 * inv
    rho3 = s * s + t * t
    if rho3 <= rho2:
        return rho3, True, zc * c2 * inv, inv, s, t
    return rho2, False, zc, inv, s, t


@njit(cache=True, parallel=True)
def _forward(mean2d, rays, zcs, opac, feat, box, gauss, offsets, width, height, tiles_x, centre,
             out_feat, out_t, out_dist, out_med, out_last, out_medk):
    for t in prange(offsets.shape[0] - 1):
        x0, y0, x1, y1 = _tile_box(t, tiles_x, width, height)
        tw = x1 - x0
        npx = tw * (y1 - y0)
        trans = np.ones(npx, np.float32)
        acc = np.zeros((npx, _NO), np.float32)
        dist = np.zeros(npx, np.float32)
        med = np.zeros(npx, np.float32)
        last = np.full(npx, -1, np.int64)
        medk = np.full(npx, -1, np.int64)
        done = np.zeros(npx, np.bool_)
        n_done = 0
        for k in range(offsets[t], offsets[t + 1]):
            g = gauss[k]
            mx, my, o, zc = mean2d[g, 0], mean2d[g, 1], opac[g], zcs[g]
            a0, b0, a1, b1 = rays[g, 0], rays[g, 1], rays[g, 2], rays[g, 3]
            a2, b2, c2 = rays[g, 4], rays[g, 5], rays[g, 6]
            f0, f1, f2, f3, f4, f5 = feat[g, 0], feat[g, 1], feat[g, 2], feat[g, 3], feat[g, 4], feat[g, 5]
            r2 = 2.0 * (np.log(np.float64(o)) + _LOG255)
            al, be1, be0, ga2, ga1, ga0, full = _span_coeffs(a0, b0, a1, b1, a2, b2, c2, r2)
            i0, i1 = max(box[g, 0], x0), min(box[g, 1], x1 - 1)
            for j in range(max(box[g, 2], y0), min(box[g, 3], y1 - 1) + 1):
                dy = (_F(j) + _HALF) - my
                dy64 = np.float64(j) + 0.5 - np.float64(my)
                lo, hi = _row_span(mx, dy64, al, be1, be0, ga2, ga1, ga0, full, r2, i0, i1)
                q0y, q1y, q2y, dy2 = b0 * dy, b1 * dy, b2 * dy + c2, dy * dy
                for i in range(lo, hi + 1):
                    p = (j - y0) * tw + i - x0
                    if done[p]:
                        continue
                    dx = (_F(i) + _HALF) - mx
                    q0, q1, q2 = a0 * dx + q0y, a1 * dx + q1y, a2 * dx + q2y
                    rho2 = _TWO * (dx * dx + dy2)
                    rho, _, z, _, _, _ = _sample(q0, q1, q2, rho2, zc, c2)
                    if centre:
                        z = zc
                    a = min(_AMAX, o * np.exp(-_HALF * rho))
                    if a < _AMIN:
                        continue
                    tb = trans[p]
                    t_next = tb * (_ONE - a)
                    if t_next < _TMIN:
                        done[p] = True
                        n_done += 1
                        continue
                    w = a * tb
                    acc[p, 0] += w * f0
                    acc[p, 1] += w * f1
                    acc[p, 2] += w * f2
                    acc[p, 3] += w * f3
                    acc[p, 4] += w * f4
                    acc[p, 5] += w * f5
                    dist[p] += _TWO * w * (z * (_ONE - tb) - acc[p, _NC])
                    acc[p, _NC] += w * z
                    if tb > _HALF and t_next <= _HALF:
                        med[p] = z
                        medk[p] = k
                    trans[p] = t_next
                    last[p] = k
            if n_done == npx:
                break
        for j in range(y0, y1):
            for i in range(x0, x1):
                p = (j - y0) * tw + i - x0
                out_t[j, i] = trans[p]
                out_dist[j, i] = dist[p]
                out_med[j, i] = med[p]
                out_last[j, i] = last[p]
                out_medk[j, i] = medk[p]
                for c in range(_NO):
                    out_feat[j, i, c] = acc[p, c]


@njit(cache=True, parallel=True)
def _backward(mean2d, rays, zcs, opac, feat, box, gauss, offsets, width, height, tiles_x, centre,
              sums, final_t, last, medk, g_feat, g_t, g_dist, g_med, out):
    for t in prange(offsets.shape[0] - 1):
        x0, y0, x1, y1 = _tile_box(t, tiles_x, width, height)
        tw = x1 - x0
        npx = tw * (y1 - y0)
        trans = np.empty(npx, np.float32)  # transmittance after the surfel being visited
        behind = np.zeros((npx, _NO), np.float32)  # sum of w_j f_j over the surfels behind it
        behind_d = np.zeros(npx, np.float32)  # sum of w_j dD/dw_j over the surfels behind it
        z_upto = np.empty(npx, np.float32)  # sum of w_j z_j over the surfels up to it
        a_tot = np.empty(npx, np.float32)
        z_tot = np.empty(npx, np.float32)
        k_last = np.empty(npx, np.int64)
        k_med = np.empty(npx, np.int64)
        gpix = np.empty((npx, _NO), np.float32)  # dL/d(sums) of the tile's pixels
        gtf = np.empty(npx, np.float32)  # dL/dT_final * T_final
        gd = np.empty(npx, np.float32)
        gm = np.empty(npx, np.float32)
        k_max = -1
        for j in range(y0, y1):
            for i in range(x0, x1):
                p = (j - y0) * tw + i - x0
                trans[p] = final_t[j, i]
                gtf[p] = g_t[j, i] * final_t[j, i]
                for c in range(_NO):
                    gpix[p, c] = g_feat[j, i, c]
                a_tot[p] = _ONE - final_t[j, i]
                z_tot[p] = sums[j, i, _NC]
                z_upto[p] = z_tot[p]
                gd[p] = g_dist[j, i]
                gm[p] = g_med[j, i]
                k_last[p] = last[j, i]
                k_med[p] = medk[j, i]
                k_max = max(k_max, last[j, i])
        for k in range(k_max, offsets[t] - 1, -1):
            g = gauss[k]
            mx, my, o, zc = mean2d[g, 0], mean2d[g, 1], opac[g], zcs[g]
            a0, b0, a1, b1 = rays[g, 0], rays[g, 1], rays[g, 2], rays[g, 3]
            a2, b2, c2 = rays[g, 4], rays[g, 5], rays[g, 6]
            f0, f1, f2, f3, f4, f5 = feat[g, 0], feat[g, 1], feat[g, 2], feat[g, 3], feat[g, 4], feat[g, 5]
            r2 = 2.0 * (np.log(np.float64(o)) + _LOG255)
            al, be1, be0, ga2, ga1, ga0, full = _span_coeffs(a0, b0, a1, b1, a2, b2, c2, r2)
            gmx = gmy = gzc = go = _ZERO
            gf0 = gf1 = gf2 = gf3 = gf4 = gf5 = _ZERO
            ga0_ = gb0 = ga1_ = gb1 = ga2_ = gb2 = gc2 = _ZERO
            i0, i1 = max(box[g, 0], x0), min(box[g, 1], x1 - 1)
            for j in range(max(box[g, 2], y0), min(box[g, 3], y1 - 1) + 1):
                dy = (_F(j) + _HALF) - my
                dy64 = np.float64(j) + 0.5 - np.float64(my)
                lo, hi = _row_span(mx, dy64, al, be1, be0, ga2, ga1, ga0, full, r2, i0, i1)
                q0y, q1y, q2y, dy2 = b0 * dy, b1 * dy, b2 * dy + c2, dy * dy
                for i in range(lo, hi + 1):
                    p = (j - y0) * tw + i - x0
                    if k > k_last[p]:
                        continue
                    dx = (_F(i) + _HALF) - mx
                    q0, q1, q2 = a0 * dx + q0y, a1 * dx + q1y, a2 * dx + q2y
                    rho2 = _TWO * (dx * dx + dy2)
                    rho, on_plane, z, inv2, s, tt = _sample(q0, q1, q2, rho2, zc, c2)
                    if centre:
                        z = zc
                    vis = np.exp(-_HALF * rho)
                    a = min(_AMAX, o * vis)
                    if a < _AMIN:
                        continue
                    inv = _ONE / (_ONE - a)
                    tb = trans[p] * inv
                    trans[p] = tb
                    w = a * tb
                    # dL/da_i = sum_f g_f (f_i T_i - behind_f / (1 - a_i)) - g_T T_final / (1 - a_i)
                    #           + the distortion's term below
                    gp0, gp1, gp2, gp3 = gpix[p, 0], gpix[p, 1], gpix[p, 2], gpix[p, 3]
                    gp4, gp5, gpz = gpix[p, 4], gpix[p, 5], gpix[p, _NC]
                    gf0 += w * gp0
                    gf1 += w * gp1
                    gf2 += w * gp2
                    gf3 += w * gp3
                    gf4 += w * gp4
                    gf5 += w * gp5
                    g_a = (tb * (gp0 * f0 + gp1 * f1 + gp2 * f2 + gp3 * f3 + gp4 * f4 + gp5 * f5 + gpz * z)
                           - inv * (gtf[p] + gp0 * behind[p, 0] + gp1 * behind[p, 1] + gp2 * behind[p, 2]
                                    + gp3 * behind[p, 3] + gp4 * behind[p, 4] + gp5 * behind[p, 5]
                                    + gpz * behind[p, _NC]))
                    behind[p, 0] += w * f0
                    behind[p, 1] += w * f1
                    behind[p, 2] += w * f2
                    behind[p, 3] += w * f3
                    behind[p, 4] += w * f4
                    behind[p, 5] += w * f5
                    behind[p, _NC] += w * z
                    g_z = gpz * w
                    if gd[p] != 0:
                        a_before = _ONE - tb
                        z_before = z_upto[p] - w * z
                        dl_dw = _TWO * (_TWO * (z * a_before - z_before) + (z_tot[p] - z * a_tot[p]))
                        g_a += gd[p] * (dl_dw * tb - behind_d[p] * inv)
                        behind_d[p] += w * dl_dw
                        g_z += gd[p] * _TWO * w * (_TWO * a_before + w - a_tot[p])
                        z_upto[p] = z_before
                    if k == k_med[p]:
                        g_z += gm[p]
                    gq0 = gq1 = gq2 = _ZERO
                    if o * vis <= _AMAX:  # the clamp passes no gradient
                        go += vis * g_a
                        g_rho = -_HALF * o * vis * g_a
                        if on_plane:  # rho = s^2 + t^2, (s, t) = (q0, q1) / q2
                            gq0 = _TWO * g_rho * s * inv2
                            gq1 = _TWO * g_rho * tt * inv2
                            gq2 = -_TWO * g_rho * rho * inv2
                        else:  # rho = 2 (dx^2 + dy^2), dx = px - mx
                            gmx -= _TWO * _TWO * dx * g_rho
                            gmy -= _TWO * _TWO * dy * g_rho
                    if on_plane and not centre:  # z = zc C2 / q2
                        gzc += g_z * c2 * inv2
                        gc2 += g_z * zc * inv2
                        gq2 -= g_z * z * inv2
                    else:
                        gzc += g_z
                    ga0_ += gq0 * dx
                    gb0 += gq0 * dy
                    ga1_ += gq1 * dx
                    gb1 += gq1 * dy
                    ga2_ += gq2 * dx
                    gb2 += gq2 * dy
                    gc2 += gq2
                    gmx -= gq0 * a0 + gq1 * a1 + gq2 * a2
                    gmy -= gq0 * b0 + gq1 * b1 + gq2 * b2
            row = out[k]
            row[0], row[1] = gmx, gmy
            row[2], row[3], row[4], row[5], row[6], row[7], row[8] = ga0_, gb0, ga1_, gb1, ga2_, gb2, gc2
            row[9], row[10] = gzc, go
            row[11], row[12], row[13], row[14], row[15], row[16] = gf0, gf1, gf2, gf3, gf4, gf5


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, rays, depths, opacities, feats, box, gauss, offsets, width, height, tiles_x,
                centre):
        args = (_np32(means2d), _np32(rays), _np32(depths), _np32(opacities), _np32(feats),
                np.ascontiguousarray(box.numpy()), np.ascontiguousarray(gauss.numpy()),
                np.ascontiguousarray(offsets.numpy()), width, height, tiles_x, centre)
        out_feat = np.empty((height, width, _NO), np.float32)
        out_t = np.empty((height, width), np.float32)
        out_dist = np.empty((height, width), np.float32)
        out_med = np.empty((height, width), np.float32)
        out_last = np.empty((height, width), np.int64)
        out_medk = np.empty((height, width), np.int64)
        with _chunks():
            _forward(*args, out_feat, out_t, out_dist, out_med, out_last, out_medk)
        ctx.args, ctx.saved = args, (out_feat, out_t, out_last, out_medk)
        ctx.dtypes = [x.dtype for x in (means2d, rays, depths, opacities, feats)]
        ctx.n = len(opacities)
        dtype = feats.dtype
        return tuple(torch.from_numpy(x).to(dtype) for x in (out_feat, out_t, out_dist, out_med))

    @staticmethod
    def backward(ctx, g_feat, g_t, g_dist, g_med):
        height, width = ctx.saved[1].shape

        def grad(x, *shape):  # an output not in the loss has no gradient
            return _np32(x) if x is not None else np.zeros((height, width, *shape), np.float32)

        gauss = ctx.args[6]
        slots = np.zeros((len(gauss), _NG), np.float32)
        with _chunks():
            _backward(*ctx.args, *ctx.saved, grad(g_feat, _NO), grad(g_t), grad(g_dist), grad(g_med), slots)
        grads = torch.zeros(ctx.n, _NG, dtype=torch.float32)
        grads.index_add_(0, torch.from_numpy(gauss), torch.from_numpy(slots))
        m2, ry, zc, op, ft = ctx.dtypes
        return (grads[:, 0:2].to(m2), grads[:, 2:9].to(ry), grads[:, 9].to(zc), grads[:, 10].to(op),
                grads[:, 11:].to(ft), None, None, None, None, None, None, None)


def composite(proj: SurfelsProjected, opacities: torch.Tensor, colors: torch.Tensor, bins: Bins, width: int,
              height: int, centre: bool = False
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(sums [H, W, 7]: colour, normal, z, without background; final transmittance [H, W];
    distortion [H, W]; median depth [H, W]). `centre`: each sample's z is its surfel's centre z (gsplat's)."""
    feats = torch.cat([colors, proj.normals.to(colors.dtype)], -1)  # [N, 6]
    return _Composite.apply(proj.means2d, proj.rays, proj.depths, opacities, feats, proj.box, bins.gauss,
                            bins.offsets, width, height, bins.tiles_x, bool(centre))
