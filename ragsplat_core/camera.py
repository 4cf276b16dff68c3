"""Pinhole camera: the one place where camera conventions are defined and converted.

Conventions (also in the README):
- World frame: z up, metres.
- Pose: OpenCV world-to-camera, x_cam = R @ x_world + t; the camera looks down its +z, +x right, +y down.
- Intrinsics K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]; pixel (i, j) has its centre at (i + 0.5, j + 0.5),
  row 0 at the top, so a principal point at the image centre is (W / 2, H / 2).
- Depth is z-depth along the optical axis (x_cam[2]), not distance along the ray.
- Blender and nerfstudio store camera-to-world with OpenGL axes (camera looks down -z, +y up):
  c2w_gl = inverse([R | t]) @ diag(1, -1, -1, 1). Only `from_c2w_gl` and `c2w_gl` convert.

Points may be numpy arrays or torch tensors; results come back in the same kind, dtype and device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

_GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips camera y and z; its own inverse
_ORTHO_TOL = 1e-6


def _as_like(camera: Camera, name: str, like):
    """The camera's `name` (e.g. "R") in the container, dtype and device of `like` (numpy or torch)."""
    array = getattr(camera, name)
    if isinstance(like, np.ndarray):
        return array.astype(like.dtype if like.dtype.kind == "f" else np.float64)
    import torch  # only when a tensor was passed in

    return camera.tensor(name, like.dtype if like.is_floating_point() else torch.float64, like.device)


def _check_rotation(R: np.ndarray) -> None:
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError(f"rotation must be a finite 3x3 matrix, got {R.tolist()}")
    if np.abs(R.T @ R - np.eye(3)).max() > _ORTHO_TOL or np.linalg.det(R) < 0:
        raise ValueError(f"rotation is not orthonormal with det +1: {R.tolist()}")


@dataclass(frozen=True, eq=False)
class Camera:
    """Intrinsics plus an OpenCV world-to-camera pose. Build with `from_fov`, `look_at` or `from_c2w_gl`."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    R: np.ndarray  # [3, 3] world -> camera rotation
    t: np.ndarray  # [3] world -> camera translation

    def __post_init__(self):
        if (int(self.width) != self.width or int(self.height) != self.height
                or self.width < 1 or self.height < 1):
            raise ValueError(f"image size must be positive integers, got {self.width} x {self.height}")
        for name in ("fx", "fy", "cx", "cy"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite, got {getattr(self, name)}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        R = np.array(self.R, dtype=np.float64)
        t = np.array(self.t, dtype=np.float64).reshape(-1)
        _check_rotation(R)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise ValueError(f"translation must be 3 finite numbers, got {t.tolist()}")
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    # ---- constructors -------------------------------------------------------------------------------
    @staticmethod
    def intrinsics_from_fov(width: int, height: int, fov_x_deg: float) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) for square pixels, a horizontal field of view and a centred principal point."""
        if not (math.isfinite(fov_x_deg) and 0.0 < fov_x_deg < 180.0):
            raise ValueError(f"field of view must be in (0, 180) degrees, got {fov_x_deg}")
        f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
        return f, f, width / 2, height / 2

    @classmethod
    def from_fov(cls, width: int, height: int, fov_x_deg: float, R, t) -> Camera:
        fx, fy, cx, cy = cls.intrinsics_from_fov(width, height, fov_x_deg)
        return cls(width, height, fx, fy, cx, cy, np.asarray(R, float), np.asarray(t, float))

    @classmethod
    def from_c2w_gl(cls, c2w, width: int, height: int, fov_x_deg: float | None = None,
                    intrinsics: tuple[float, float, float, float] | None = None) -> Camera:
        """From a Blender / nerfstudio camera-to-world matrix ([3,4] or [4,4], OpenGL camera axes)."""
        c2w = np.asarray(c2w, dtype=np.float64)
        if c2w.shape not in ((3, 4), (4, 4)) or not np.all(np.isfinite(c2w)):
            raise ValueError(f"camera-to-world must be a finite 3x4 or 4x4 matrix, got shape {c2w.shape}")
        if (fov_x_deg is None) == (intrinsics is None):
            raise ValueError("give exactly one of fov_x_deg or intrinsics=(fx, fy, cx, cy)")
        if intrinsics is None:
            intrinsics = cls.intrinsics_from_fov(width, height, fov_x_deg)
        c2w_cv = np.eye(4)
        c2w_cv[:3, :4] = c2w[:3, :4]
        c2w_cv = c2w_cv @ _GL_FROM_CV
        R_c2w = c2w_cv[:3, :3]
        _check_rotation(R_c2w)
        R = R_c2w.T
        t = -R @ c2w_cv[:3, 3]
        return cls(width, height, *intrinsics, R, t)

    @classmethod
    def look_at(cls, eye, target, width: int, height: int, fov_x_deg: float, up=(0.0, 1.0, 0.0)) -> Camera:
        """Camera at `eye` looking at `target`; image 'up' (-y_cam) leans towards world `up`.

        The default up is world +y, which stays valid for a nadir view (looking straight down -z);
        pass another `up` only if it is not parallel to the viewing direction.
        """
        eye = np.asarray(eye, float)
        forward = np.asarray(target, float) - eye
        norm = np.linalg.norm(forward)
        if not np.isfinite(norm) or norm == 0:
            raise ValueError(f"look_at needs distinct finite eye and target, got {eye} and {target}")
        z = forward / norm
        x = np.cross(z, np.asarray(up, float))  # right = forward x up
        if np.linalg.norm(x) < 1e-9:
            raise ValueError(f"up {up} is parallel to the viewing direction {z}")
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        return cls.from_fov(width, height, fov_x_deg, R, -R @ eye)

    def __getstate__(self):  # pickled without the device copies (`tensor`)
        return {k: v for k, v in self.__dict__.items() if k != "_tensors"}

    def tensor(self, name: str, dtype, device):
        """The camera's `name` ("R", "t", "K", "w2c" or "camera_center") as a tensor of `dtype` on `device`,
        made there once and kept: a copy from the host to a GPU waits for every kernel queued before it, so
        a training step that made its view's matrices anew would wait for the device several times a step.
        Read only (shared by every caller)."""
        import torch  # only when a tensor is asked for

        cache = self.__dict__.setdefault("_tensors", {})  # frozen: the fields cannot change under it
        key = (name, dtype, torch.device(device))
        if key not in cache:
            cache[key] = torch.tensor(getattr(self, name), dtype=dtype, device=device)
        return cache[key]

    # ---- derived quantities -------------------------------------------------------------------------
    @property
    def K(self) -> np.ndarray:  # [3, 3]
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def w2c(self) -> np.ndarray:  # [4, 4] OpenCV world -> camera
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    @property
    def c2w_gl(self) -> np.ndarray:  # [4, 4] Blender / nerfstudio `transform_matrix`
        c2w_cv = np.eye(4)
        c2w_cv[:3, :3] = self.R.T
        c2w_cv[:3, 3] = self.camera_center
        return c2w_cv @ _GL_FROM_CV

    @property
    def camera_center(self) -> np.ndarray:  # [3] world
        return -self.R.T @ self.t

    @property
    def fov_x_deg(self) -> float:
        return math.degrees(2 * math.atan(0.5 * self.width / self.fx))

    # ---- mapping points ------------------------------------------------------------------------------
    def to_camera(self, points):
        """World points [N, 3] -> camera-frame points [N, 3] (OpenCV axes)."""
        return points @ _as_like(self, "R", points).T + _as_like(self, "t", points)

    def project(self, points):
        """World points [N, 3] -> (pixels [N, 2] as continuous (u, v), z-depth [N]).

        Points at or behind the camera get non-finite or meaningless pixels: check depth > 0.
        """
        pc = self.to_camera(points)
        z = pc[..., 2]
        u = self.fx * pc[..., 0] / z + self.cx
        v = self.fy * pc[..., 1] / z + self.cy
        stack = np.stack if isinstance(points, np.ndarray) else _torch_stack
        return stack([u, v], -1), z

    def unproject(self, pixels, depth):
        """Pixels [N, 2] (continuous, centres at i + 0.5) and z-depth [N] -> world points [N, 3]."""
        x = (pixels[..., 0] - self.cx) / self.fx * depth
        y = (pixels[..., 1] - self.cy) / self.fy * depth
        stack = np.stack if isinstance(pixels, np.ndarray) else _torch_stack
        pc = stack([x, y, depth], -1)
        return (pc - _as_like(self, "t", pc)) @ _as_like(self, "R", pc)

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy, "cx": self.cx,
                "cy": self.cy, "R": self.R.tolist(), "t": self.t.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        return cls(int(d["width"]), int(d["height"]), float(d["fx"]), float(d["fy"]), float(d["cx"]),
                   float(d["cy"]), np.asarray(d["R"], float), np.asarray(d["t"], float))


def ground_sample_distance(cameras, level: float) -> float | None:
    """Metres per pixel at the plane z = `level` (the water surface) of `cameras` (`sample_distance`)."""
    if not cameras:
        return None
    return sample_distance(np.array([c.R for c in cameras]), np.array([c.camera_center for c in cameras]),
                           np.array([c.fx for c in cameras]), level)


def sample_distance(R: np.ndarray, centres: np.ndarray, fx: np.ndarray, level: float) -> float | None:
    """Metres per pixel at the plane z = `level` of the cameras R [V, 3, 3] (world -> camera), centres [V, 3]
    and focal lengths fx [V] (px): per camera, the z-depth where its optical axis meets the plane over fx;
    the median over the cameras that look down onto it from above (None when none does). Refraction is left
    out: the bed below looks farther, by at most d / n."""
    height, down = centres[:, 2] - level, -R[:, 2, 2]  # R[2] = the optical axis in the world
    seen = (height > 0) & (down > 0)
    return float(np.median(height[seen] / down[seen] / fx[seen])) if seen.any() else None


def _torch_stack(tensors, dim):
    import torch

    return torch.stack(tensors, dim)
