"""The bed from rendered depth: depth maps of the training views fused into a projective TSDF (truncated
signed distance), then read as a height grid on the ground truth's nodes and as a triangle mesh. The second
geometry extraction beside `surface.py`'s volume sampling of the Gaussians (the paper's field
pipeline fuses depth the same way, with a voxel of about 3x the ground sample distance and a truncation of
about 3 voxels).

1. `integrate`: a voxel grid over the region (plus a voxel of margin) and a z range; every voxel centre is
   projected into every view, the view's depth there (`_sample`: inverse depth interpolated between the four
   nearest pixel centres, at i + 0.5, or the pixel's own across a depth edge) gives the projective signed
   distance sdf = depth - voxel z-depth (positive between the camera and the surface),
   truncated to sdf / trunc in [-1, 1]; voxels more than `trunc` behind the surface, outside the image or
   under a pixel without depth (0) are left alone; each observation weighs 1 in a running average.
2. `height_grid`: at each node origin + (i, j) * cell inside the region, the TSDF column interpolated
   bilinearly from the four voxel columns around it (a voxel counts once all four are observed), and the
   topmost crossing from + (above) to - (below) interpolated linearly between voxels: the bed is 2.5-D, so
   the first surface met from above is the one that counts. Crossings with a clamped value (|t| = 1) on
   either side are inconsistent depth edges (the distance jumps by more than the band over one voxel) and
   are skipped.
3. `height_mesh`: the height grid triangulated (two triangles per cell whose four nodes exist).

Why not open3d's `ScalableTSDFVolume`: its wheel is about 450 MB and pulls GUI libraries, while ragsplat
installs on a fresh CPU machine; the bed is a 2.5-D height field on a fixed grid, which needs neither hashed
blocks nor marching cubes. Here: torch on the CPU, chunked over voxels so the temporaries stay a few
[chunk] tensors whatever the grid (the `small` reach: 87 views of 256 x 256 over a 10 x 8 m region a few
metres deep). Arrays or tensors in, numpy arrays out, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
import torch

from ragsplat.camera import Camera
from ragsplat.errors import ConfigError
from ragsplat.surface import in_region

NEAR = 1e-6  # voxels at or behind a camera's plane are not observed by it


@dataclass(frozen=True)
class FuseConfig:
    voxel_gsd: float = 3.0  # voxel edge in ground sample distances of the views at the bed (`ground_sample`)
    voxel: float | None = None  # metres; replaces voxel_gsd when given
    trunc_voxels: float = 3.0  # truncation distance in voxels
    z_quantile: float = 0.001  # z range: these quantiles of the depth points in the region ...
    z_pad_voxels: float = 6.0  # ... widened by this many voxels on either side

    def __post_init__(self):
        for name in ("voxel_gsd", "trunc_voxels"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"FuseConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.voxel is not None and not self.voxel > 0:
            raise ConfigError(f"FuseConfig.voxel must be > 0 or None, got {self.voxel}")
        if not (0 <= self.z_quantile < 0.5 and self.z_pad_voxels >= 0):
            raise ConfigError(f"FuseConfig.z_quantile must be in [0, 0.5) and z_pad_voxels >= 0, got "
                              f"{self.z_quantile} and {self.z_pad_voxels}")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Tsdf:
    """A fused volume: voxel (i, j, k) has its centre at origin + (i, j, k) * voxel."""

    values: np.ndarray  # [X, Y, Z] float32 in [-1, 1]: sdf / trunc, + above (in front of) the surface
    weights: np.ndarray  # [X, Y, Z] float32: observations (0 = never observed)
    origin: np.ndarray  # [3] float64
    voxel: float
    trunc: float


def _depth(d) -> torch.Tensor:  # [H, W] float32 on the CPU
    return (d.detach().to("cpu", torch.float32) if torch.is_tensor(d)
            else torch.as_tensor(d, dtype=torch.float32))


def _check(depths: Sequence, cameras: Sequence[Camera]) -> list[torch.Tensor]:
    if len(depths) != len(cameras) or not cameras:
        raise ValueError(f"fusion needs one depth map per camera and at least one, got {len(depths)} depth "
                         f"maps and {len(cameras)} cameras")
    out = []
    for d, cam in zip(depths, cameras):
        d = _depth(d)
        if tuple(d.shape) != (cam.height, cam.width):
            raise ValueError(f"a depth map of shape {list(d.shape)} for a {cam.width} x {cam.height} camera")
        out.append(torch.where(torch.isfinite(d) & (d > 0), d, torch.zeros_like(d)))  # no depth: 0
    return out


def ground_sample(depths: Sequence, cameras: Sequence[Camera]) -> float:
    """The views' ground sample distance (m per pixel) at what they see: per view the median depth of its
    pixels with depth over fx, then the median over the views (0 when no pixel has depth)."""
    per_view = [float(d[d > 0].median()) / cam.fx for d, cam in zip(_check(depths, cameras), cameras)
                if (d > 0).any()]
    return float(np.median(per_view)) if per_view else 0.0


def z_range(depths: Sequence, cameras: Sequence[Camera], region: dict, quantile: float = 0.001
            ) -> tuple[float, float] | None:
    """(low, high) quantiles of the height of every depth pixel that lands inside `region` (None if none
    does): the z span the volume needs, from the depth maps alone (no ground truth)."""
    z = []
    for d, cam in zip(_check(depths, cameras), cameras):
        j, i = torch.nonzero(d > 0, as_tuple=True)
        if len(j):
            pix = torch.stack([i, j], -1).double() + 0.5
            pts = cam.unproject(pix.numpy(), d[j, i].double().numpy())  # [P, 3]
            z.append(pts[in_region(pts, region), 2])
    z = np.concatenate(z) if z else np.zeros(0)
    if not len(z):
        return None
    lo, hi = np.quantile(z, [quantile, 1 - quantile])
    return float(lo), float(hi)


def integrate(depths: Sequence, cameras: Sequence[Camera], region: dict, zlim: tuple[float, float],
              voxel: float, trunc: float, chunk: int = 1 << 18) -> Tsdf:
    """Fuses z-depth maps (one [H, W] per camera, 0 = no depth) into a TSDF over `region` {xmin, xmax, ymin,
    ymax} grown by one voxel (so nodes at its edge have voxel columns on both sides) and z in `zlim`."""
    if not (voxel > 0 and trunc > 0 and zlim[1] >= zlim[0]):
        raise ValueError(f"integrate needs voxel > 0, trunc > 0 and zlim low <= high, got {voxel}, {trunc}, "
                         f"{zlim}")
    maps = [torch.nn.functional.pad(d, (1, 1, 1, 1)) for d in _check(depths, cameras)]  # [H + 2, W + 2]
    origin = np.array([region["xmin"] - voxel, region["ymin"] - voxel, zlim[0]])
    span = np.array([region["xmax"] - region["xmin"] + 2 * voxel, region["ymax"] - region["ymin"] + 2 * voxel,
                     zlim[1] - zlim[0]])
    # [X, Y, Z]: voxel centres cover the span, with two layers at least (a crossing lies between two)
    shape = tuple(max(2, math.ceil(s / voxel - 1e-9) + 1) for s in span)
    n = shape[0] * shape[1] * shape[2]
    values, weights = torch.zeros(n), torch.zeros(n)
    # per camera: R, t relative to the volume's origin (float32 keeps millimetres at tens of metres from it)
    poses = [(torch.tensor(c.R, dtype=torch.float32), torch.tensor(c.R @ origin + c.t, dtype=torch.float32))
             for c in cameras]
    strides = torch.tensor([shape[1] * shape[2], shape[2], 1])
    for s in range(0, n, chunk):
        flat = torch.arange(s, min(s + chunk, n))
        ijk = (flat[:, None] // strides) % torch.tensor(shape)  # [C, 3]
        p = ijk.to(torch.float32) * voxel  # [C, 3] from the origin
        val, w = values[s: s + chunk], weights[s: s + chunk]  # views: updated in place
        for cam, (R, t), d in zip(cameras, poses, maps):
            pc = p @ R.T + t  # [C, 3] camera frame
            z = pc[:, 2]
            front = z > NEAR
            zs = torch.where(front, z, torch.ones_like(z))
            got = _sample(d, cam.fx * pc[:, 0] / zs + cam.cx, cam.fy * pc[:, 1] / zs + cam.cy, trunc)  # [C]
            sdf = got - z
            ok = front & (got > 0) & (sdf >= -trunc)
            if not ok.any():
                continue
            obs = torch.clamp(sdf / trunc, max=1.0)
            w_new = w + ok.float()
            val.copy_(torch.where(ok, (val * w + obs) / w_new.clamp(min=1.0), val))
            w.copy_(w_new)
    return Tsdf(values.reshape(shape).numpy(), weights.reshape(shape).numpy(), origin, float(voxel),
                float(trunc))


def _sample(pad: torch.Tensor, u: torch.Tensor, v: torch.Tensor, trunc: float) -> torch.Tensor:
    """Depth [C] at continuous pixel positions u, v [C] of a depth map zero-padded by one pixel ([H + 2,
    W + 2]): the inverse depth interpolated bilinearly between the four nearest pixel centres where all four
    have depth within `trunc` of each other (exact on a plane, whose 1 / z is affine in the pixel
    coordinates; a nearest-pixel read is off by up to half a pixel's depth change), else the depth of the
    pixel itself (across a depth edge); 0 outside the image or where that pixel has none."""
    H, W = pad.shape[0] - 2, pad.shape[1] - 2
    # pixel i: [i, i + 1)
    near = pad[torch.floor(v).clamp(-1, H).long() + 1, torch.floor(u).clamp(-1, W).long() + 1]
    x, y = u - 0.5, v - 0.5  # pixel centres on the integers
    i0, j0 = torch.floor(x).clamp(-1, W - 1), torch.floor(y).clamp(-1, H - 1)
    ax, ay = (x - i0).clamp(0, 1), (y - j0).clamp(0, 1)
    i0, j0 = i0.long() + 1, j0.long() + 1
    c = torch.stack([pad[j0, i0], pad[j0, i0 + 1], pad[j0 + 1, i0], pad[j0 + 1, i0 + 1]])  # [4, C]
    wgt = torch.stack([(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay])
    smooth = (c > 0).all(0) & (c.amax(0) - c.amin(0) < trunc)
    inv = (wgt / torch.where(c > 0, c, torch.ones_like(c))).sum(0)
    return torch.where(smooth, 1 / inv.clamp(min=1e-12), near)


def grid_nodes(region: dict, cell: float, origin: tuple[float, float]) -> np.ndarray:
    """[G, 2] the nodes origin + (i, j) * cell inside `region` (a rounding error past an edge still counts),
    sorted by i then j."""
    ox, oy = origin
    tol = 1e-6
    i = np.arange(math.ceil((region["xmin"] - ox) / cell - tol),
                  math.floor((region["xmax"] - ox) / cell + tol) + 1)
    j = np.arange(math.ceil((region["ymin"] - oy) / cell - tol),
                  math.floor((region["ymax"] - oy) / cell + tol) + 1)
    ii, jj = np.meshgrid(i, j, indexing="ij")
    return np.column_stack([ox + ii.ravel() * cell, oy + jj.ravel() * cell])


def height_grid(tsdf: Tsdf, nodes: np.ndarray, chunk: int = 1 << 14) -> np.ndarray:
    """[G, 3] the nodes [N, 2] that have a surface, each at the height of its column's topmost + to -
    crossing (see the module's step 2), in the order of `nodes`."""
    X, Y, Z = tsdf.values.shape
    vals, obs = torch.from_numpy(tsdf.values), torch.from_numpy(tsdf.weights > 0)
    out = []
    for s in range(0, len(nodes), chunk):
        xy = nodes[s: s + chunk]
        f = (xy - tsdf.origin[:2]) / tsdf.voxel  # [C, 2] fractional voxel coordinates
        lo = np.floor(f).astype(np.int64)
        inside = (lo >= 0).all(1) & (lo[:, 0] < X - 1) & (lo[:, 1] < Y - 1)
        lo = np.clip(lo, 0, [X - 2, Y - 2])
        fx, fy = [torch.from_numpy(np.clip(f[:, a] - lo[:, a], 0, 1)).float()[:, None] for a in (0, 1)]
        i, j = torch.from_numpy(lo[:, 0]), torch.from_numpy(lo[:, 1])
        col = torch.zeros(len(xy), Z)  # [C, Z] bilinear TSDF column
        seen = torch.from_numpy(inside)[:, None].expand(len(xy), Z).clone()  # [C, Z]
        for di, dj, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy),
                            (1, 1, fx * fy)):
            col += wgt * vals[i + di, j + dj]
            seen &= obs[i + di, j + dj]
        below, above = col[:, :-1], col[:, 1:]  # voxel k and k + 1 (z grows with k)
        cross = seen[:, :-1] & seen[:, 1:] & (above > 0) & (below <= 0) & (above < 1) & (below > -1)
        has = cross.any(1)
        k = (Z - 2) - torch.argmax(cross.flip(1).to(torch.uint8), 1)  # topmost crossing
        t0, t1 = below.gather(1, k[:, None])[:, 0], above.gather(1, k[:, None])[:, 0]
        z = tsdf.origin[2] + (k.double() + (-t0 / (t1 - t0).clamp(min=1e-12)).double()) * tsdf.voxel
        keep = has.numpy()
        out.append(np.column_stack([xy[keep], z.numpy()[keep]]))
    return np.concatenate(out) if out else np.zeros((0, 3))


def height_mesh(grid: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """A height grid [G, 3] on a `cell` lattice -> (vertices [G, 3] = the grid, triangles [F, 3] int64): two
    per lattice square whose four corners are in the grid, counter-clockwise seen from above (normals up)."""
    if not len(grid):
        return grid.reshape(0, 3), np.zeros((0, 3), np.int64)
    ij = np.round((grid[:, :2] - grid[:, :2].min(0)) / cell).astype(np.int64)  # [G, 2]
    index = np.full(tuple(ij.max(0) + 2), -1, np.int64)  # one spare row and column: corners past the edge
    index[ij[:, 0], ij[:, 1]] = np.arange(len(grid))
    a = index[ij[:, 0], ij[:, 1]]
    b, c, d = index[ij[:, 0] + 1, ij[:, 1]], index[ij[:, 0] + 1, ij[:, 1] + 1], index[ij[:, 0], ij[:, 1] + 1]
    full = (b >= 0) & (c >= 0) & (d >= 0)
    tris = np.concatenate([np.column_stack([a, b, c])[full], np.column_stack([a, c, d])[full]])
    return grid, tris


def fuse(depths: Sequence, cameras: Sequence[Camera], region: dict, cell: float, origin: tuple[float, float],
         cfg: FuseConfig = FuseConfig()) -> tuple[np.ndarray, dict]:
    """Depth maps (z-depth [H, W] per camera, 0 = no depth) -> the height grid [G, 3] on the nodes
    origin + (i, j) * cell inside `region` (`grid_nodes`, `height_grid`) and what was chosen: the ground
    sample distance, voxel, truncation and z range (`z_range` of the depth maps, widened by
    `cfg.z_pad_voxels`). An empty grid when no depth lands in the region."""
    gsd = ground_sample(depths, cameras)
    voxel = cfg.voxel if cfg.voxel is not None else cfg.voxel_gsd * gsd
    stats = {"config": cfg.to_dict(), "gsd_m": gsd, "voxel_m": voxel, "trunc_m": cfg.trunc_voxels * voxel,
             "views": len(cameras)}
    found = z_range(depths, cameras, region, cfg.z_quantile) if voxel > 0 else None
    if found is None:
        return np.zeros((0, 3)), {**stats, "z_range_m": None, "voxels": 0, "grid_points": 0}
    zlim = (found[0] - cfg.z_pad_voxels * voxel, found[1] + cfg.z_pad_voxels * voxel)
    tsdf = integrate(depths, cameras, region, zlim, voxel, cfg.trunc_voxels * voxel)
    grid = height_grid(tsdf, grid_nodes(region, cell, origin))
    return grid, {**stats, "z_range_m": list(zlim), "voxels": int(tsdf.values.size),
                  "observed_voxels": int((tsdf.weights > 0).sum()), "grid_points": len(grid)}
