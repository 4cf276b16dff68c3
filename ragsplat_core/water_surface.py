"""The water surface, in world metres with z up: a horizontal plane z = level by default, a tilted plane for
a river whose surface falls along the reach, plus a profile where it curves along the reach (steps down its
riffles, nearly level over its pools), with the refractive index n of the water relative to air. Refraction
depends on the interface's normal alone, so the refraction of a tilted or curved surface is the flat one in
the surface's own frame (`plane_frame`, `frames`): rotate the world so that the normal is +z, transform,
rotate back; gradients reach the level and the slope through the rotation."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import torch


def array_lib(x):  # the array library of x: torch for tensors, numpy otherwise
    if torch.is_tensor(x):
        return torch
    import numpy

    return numpy


@dataclass(frozen=True)
class Profile:
    """Heights added to a surface's plane along a reach's main axis: r(s) at s = (xy - origin) . direction,
    through the knots (stations [K] increasing, offsets [K]) by a C1 cubic Hermite curve (Catmull-Rom
    tangents, one-sided at the ends), flat beyond the ends. A river's surface steps down its riffles and
    lies nearly level over its pools: the plane takes the mean fall, the profile the rest."""

    origin: tuple[float, float]
    direction: tuple[float, float]  # unit, in the xy plane
    stations: tuple[float, ...]
    offsets: tuple[float, ...]

    def __post_init__(self):
        for name in ("origin", "direction", "stations", "offsets"):
            object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))
        s, u = self.stations, self.direction
        if not (len(s) == len(self.offsets) >= 2 and all(b > a for a, b in itertools.pairwise(s))
                and all(math.isfinite(v) for v in (*s, *self.offsets, *self.origin, *u))
                and abs(math.hypot(*u) - 1) < 1e-9):
            raise ValueError("a water profile needs >= 2 increasing stations, as many finite offsets and a "
                             "unit direction")

    def _knots(self, like):
        lib = array_lib(like)
        if lib is torch:
            return (torch.tensor(self.stations, dtype=like.dtype, device=like.device),
                    torch.tensor(self.offsets, dtype=like.dtype, device=like.device))
        return lib.asarray(self.stations), lib.asarray(self.offsets)

    def along(self, xy):  # [...] the station of horizontal points xy [..., 2]
        return ((xy[..., 0] - self.origin[0]) * self.direction[0]
                + (xy[..., 1] - self.origin[1]) * self.direction[1])

    def value_and_slope(self, s):
        """(r(s), dr/ds) at stations s [...] (tensors or numpy arrays)."""
        lib = array_lib(s)
        ks, kr = self._knots(s)
        K = len(self.stations)
        dr = (kr[1:] - kr[:-1]) / (ks[1:] - ks[:-1])  # [K-1] the chords' slopes
        tangent = lib.concatenate([dr[:1], (dr[1:] + dr[:-1]) / 2, dr[-1:]])  # [K] Catmull-Rom at the knots
        inside = (s >= ks[0]) & (s <= ks[-1])
        clipped = lib.clip(s, ks[0], ks[-1]) if lib is not torch else s.clamp(ks[0], ks[-1])
        i = lib.searchsorted(ks, clipped, side="right") if lib is not torch else \
            torch.searchsorted(ks, clipped.contiguous(), right=True)
        i = (i - 1).clip(0, K - 2) if lib is not torch else (i - 1).clamp(0, K - 2)
        h = ks[i + 1] - ks[i]
        t = (clipped - ks[i]) / h
        t2, t3 = t * t, t * t * t
        value = (2 * t3 - 3 * t2 + 1) * kr[i] + (t3 - 2 * t2 + t) * h * tangent[i] \
            + (-2 * t3 + 3 * t2) * kr[i + 1] + (t3 - t2) * h * tangent[i + 1]
        slope = ((6 * t2 - 6 * t) * kr[i] + (3 * t2 - 4 * t + 1) * h * tangent[i]
                 + (-6 * t2 + 6 * t) * kr[i + 1] + (3 * t2 - 2 * t) * h * tangent[i + 1]) / h
        return value, slope * inside

    def shifted(self, offset_xy) -> Profile:
        return Profile((self.origin[0] - offset_xy[0], self.origin[1] - offset_xy[1]), self.direction,
                       self.stations, self.offsets)


@dataclass(frozen=True)
class WaterSurface:
    """The water surface z = level + slope[0] x + slope[1] y (world metres; `level` is its height at x = y =
    0) with refractive index n relative to air: a horizontal plane by default, a tilted one for a river whose
    surface falls along the reach (slope = (dz/dx, dz/dy): a 1 % fall along +x is (-0.01, 0)), plus, for a
    surface that curves along the reach, a `profile` (`Profile`) added to the plane.

    `level`, `n` and `slope` may be tensors that require grad (0-d; slope [2]), for calibrating them.
    """

    level: float = 0.0
    n: float = 1.33
    slope: tuple[float, float] = (0.0, 0.0)
    profile: Profile | None = None

    def __post_init__(self):
        if isinstance(self.slope, list):  # as JSON gives it; a tuple keeps the dataclass hashable
            object.__setattr__(self, "slope", tuple(self.slope))
        if isinstance(self.profile, dict):
            object.__setattr__(self, "profile", Profile(**self.profile))
        if not math.isfinite(float_value(self.level)):
            raise ValueError(f"water level must be finite, got {self.level}")
        if not (math.isfinite(float_value(self.n)) and float_value(self.n) >= 1.0):
            raise ValueError(f"refractive index must be finite and >= 1, got {self.n}")
        sx, sy = (float_value(v) for v in self.slope)
        if not (math.isfinite(sx) and math.isfinite(sy) and math.hypot(sx, sy) < 1):
            raise ValueError(f"water surface slope must be finite and under 1 (45 degrees), got {self.slope}")

    @property
    def is_identity(self) -> bool:
        """True when refraction is exactly the identity: n == 1 and nothing asks for its gradient."""
        return float_value(self.n) == 1.0 and not (torch.is_tensor(self.n) and self.n.requires_grad)

    @property
    def tilted(self) -> bool:
        """False for the horizontal plane z = level (a zero slope that nothing asks the gradient of), which
        keeps today's transform and its arithmetic exactly."""
        return (torch.is_tensor(self.slope) and self.slope.requires_grad
                or any(float_value(v) != 0 for v in self.slope))

    @property
    def curved(self) -> bool:
        """A surface with a profile along the reach: refracted through the tangent plane above each point."""
        return self.profile is not None

    def height(self, xy):
        """[...] surface height at horizontal points xy [..., 2] (tensors or numpy arrays)."""
        if not (self.tilted or self.curved):
            return self.level + 0 * xy[..., 0]
        z = self.level + self.slope[0] * xy[..., 0] + self.slope[1] * xy[..., 1]
        return z if self.profile is None else z + self.profile.value_and_slope(self.profile.along(xy))[0]

    def gradient(self, xy):
        """[..., 2] (dz/dx, dz/dy) of the surface at horizontal points xy [..., 2]."""
        lib = array_lib(xy)
        g = lib.stack([self.slope[0] + 0 * xy[..., 0], self.slope[1] + 0 * xy[..., 1]], -1)
        if self.profile is None:
            return g
        ds = self.profile.value_and_slope(self.profile.along(xy))[1]
        return g + ds[..., None] * lib.asarray(self.profile.direction) if lib is not torch else \
            g + ds[..., None] * torch.tensor(self.profile.direction, dtype=xy.dtype, device=xy.device)

    def depth(self, points):
        """[...] vertical depth of points [..., 3] below the surface (negative above it): height - z."""
        if not (self.tilted or self.curved):
            return self.level - points[..., 2]
        return self.height(points[..., :2]) - points[..., 2]

    def shifted(self, offset) -> WaterSurface:
        """The same surface in a frame whose origin lies at `offset` [3] of this one (x_new = x - offset)."""
        ox, oy, oz = (float(v) for v in offset)
        sx, sy = (float_value(v) for v in self.slope)
        return WaterSurface(float_value(self.level) + sx * ox + sy * oy - oz, float_value(self.n), (sx, sy),
                            None if self.profile is None else self.profile.shifted((ox, oy)))


def plane_frame(water: WaterSurface, like):
    """(R [3, 3], p0 [3]) of a tilted surface's own frame: q = R (p - p0) puts the surface at q_z = 0 with
    its normal along +z. R is the smallest rotation taking the normal to +z (Rodrigues), p0 the surface
    point above the origin; both carry gradients to level and slope. `like`: a tensor for dtype and device."""
    kw = {"dtype": like.dtype, "device": like.device}
    sx, sy = (torch.as_tensor(v, **kw) for v in water.slope)
    zero = torch.zeros((), **kw)
    return rotations(sx, sy), torch.stack([zero, zero, torch.as_tensor(water.level, **kw)])


def rotations(sx, sy):
    """[..., 3, 3] the smallest rotations taking the upward normals of planes with gradients (sx, sy) [...] to
    +z (Rodrigues: v = normal x e_z, R = I + [v]x + [v]x^2 / (1 + normal . e_z))."""
    norm = torch.sqrt(1 + sx * sx + sy * sy)
    nx, ny, nz = -sx / norm, -sy / norm, 1 / norm  # the upward unit normal
    zero = torch.zeros_like(nx)
    vx = torch.stack([torch.stack([zero, zero, -nx], -1), torch.stack([zero, zero, -ny], -1),
                      torch.stack([nx, ny, zero], -1)], -2)
    eye = torch.eye(3, dtype=nx.dtype, device=nx.device)
    return eye + vx + vx @ vx / (1 + nz)[..., None, None]


def tangent_frames(water: WaterSurface, points):
    """(R [N, 3, 3], p0 [N, 3]): the frame of the tangent plane of a curved surface above each of points
    [N, 3] (p0 the surface point straight above, R its normal to +z)."""
    xy = points[:, :2]
    g = water.gradient(xy)
    return rotations(g[:, 0], g[:, 1]), torch.cat([xy, water.height(xy)[:, None]], -1)


def frames(water: WaterSurface, points):
    """(R, p0) of a tilted or curved surface's own frame: one plane's (R [3, 3], p0 [3]), or the tangent
    plane's above each of points [N, 3] (R [N, 3, 3], p0 [N, 3]). In it the flat transform applies
    (`into_frame`)."""
    return tangent_frames(water, points) if water.curved else plane_frame(water, points)


def into_frame(R, p0, x):  # [..., 3] world -> the frame(s): R (x - p0); R [3, 3] or one per row
    return (R @ (x - p0)[..., None])[..., 0]


def out_of_frame(R, p0, q):  # the frame(s) -> world: R^T q + p0
    return (R.transpose(-1, -2) @ q[..., None])[..., 0] + p0


def float_value(x) -> float:
    return float(x.detach()) if torch.is_tensor(x) else float(x)
