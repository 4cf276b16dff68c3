"""Physical cross-check: emissive markers on the bed, rendered by Cycles through the water, land where the
refraction model (`apparent_points`) projects them; the naive pinhole misses by pixels. Under a sloping
surface (a plane tilted as a river's, steeper than one so that the tilt is worth a pixel) the tilted model
lands them too, and the flat one at the same level misses. Through a lens with radial distortion (the survey's
lens photos, Cycles' polynomial lens) they land where the refracted projection, distorted by COLMAP's RADIAL
model, puts them."""

import math

import cv2
import numpy as np
import pytest
import torch
from scipy import ndimage

from ragsplat.camera import Camera
from ragsplat.datagen.build import run_blender
from ragsplat.datagen.job import (
    Emission,
    Intrinsics,
    Refraction,
    RenderJob,
    RenderSettings,
    SceneObject,
    Task,
)
from ragsplat.refraction import apparent_points
from ragsplat.water_surface import WaterSurface

pytestmark = pytest.mark.blender

WIDTH, FOV, ALTITUDE, DEPTH, N = 160, 70.0, 3.0, 2.0, 1.33
MARKER_RADIUS = 0.06  # m: about 3 px across at this scale
SLOPE = (-0.08, 0.04)  # dz/dx, dz/dy of the tilted surface: the flat model misses by about a pixel
CPU_64 = RenderSettings(samples=64, device="CPU", threads=0, seed=0, filter_width=1.5, depth_filter=0.01,
                        exposure=0.0)


def disc(centre, radius, segments=32):
    """Horizontal disc as a triangle fan [V, 3], [F, 3]: its centroid is exactly `centre`."""
    a = 2 * np.pi * np.arange(segments) / segments
    ring = np.stack([centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a),
                     np.full(segments, centre[2])], -1)
    verts = np.concatenate([np.asarray(centre, float)[None], ring])
    tris = np.stack([np.zeros(segments, int), 1 + np.arange(segments),
                     1 + (np.arange(segments) + 1) % segments], -1)
    return verts, tris


def views():
    nadir = Camera.look_at([0.1, -0.05, ALTITUDE], [0.1, -0.05, 0.0], WIDTH, WIDTH, FOV)
    tilt = math.radians(40)
    # Axis enters the water h tan(40) from the camera, towards the origin (as in the flight plan).
    eye = np.array([ALTITUDE * math.tan(tilt) + DEPTH * math.tan(math.asin(math.sin(tilt) / N)), 0.0,
                    ALTITUDE])
    oblique = Camera.look_at(eye, [eye[0] - ALTITUDE * math.tan(tilt), 0.0, 0.0], WIDTH, WIDTH, FOV,
                             up=(0, 0, 1))
    return {"nadir": nadir, "oblique40": oblique}


def centroids(image_srgb: np.ndarray) -> np.ndarray:
    """Radiance-weighted centroids [K, 2] of the bright blobs, in our pixel convention (centres at i +
    0.5)."""
    c = image_srgb.astype(np.float64).mean(-1) / 255.0
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    labels, count = ndimage.label(lin > 0.01)
    com = ndimage.center_of_mass(lin, labels, range(1, count + 1))  # (row, col) of pixel indices
    return np.array([[col + 0.5, row + 0.5] for row, col in com])


def render_markers(work, water: WaterSurface, far: float, lens: tuple[float, float] | None = None,
                   spread: float = 0.9):
    """(marker centres [16, 3], cameras, images): horizontal discs DEPTH below `water` (a bed that falls
    with it) in a 4 x 4 grid out to +-spread, under the surface's plane out to +-far, rendered by Cycles from
    `views` (through a lens with radial distortion `lens`, k1 and k2, when given:
    `ragsplat.datagen.survey.lens_polynomial`)."""
    from ragsplat.datagen.survey import lens_polynomial

    xs = spread * np.array([-1, -1 / 3, 1 / 3, 1])
    xy = np.array([[x, y] for x in xs for y in xs])
    centres = np.column_stack([xy, water.height(xy) - DEPTH])  # 16 markers on the bed plane
    parts = [disc(c, MARKER_RADIUS) for c in centres]
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    corners = np.array([[-far, -far], [far, -far], [far, far], [-far, far]], float)
    np.savez(work / "geometry.npz",
             markers_verts=np.concatenate([v for v, _ in parts]),
             markers_tris=np.concatenate([t + o for (_, t), o in zip(parts, offsets)]),
             water_verts=np.column_stack([corners, water.height(corners)]),
             water_tris=np.array([[0, 1, 2], [0, 2, 3]]))
    cams = views()
    cam = cams["nadir"]
    job = RenderJob(
        geometry=str(work / "geometry.npz"),
        objects=(SceneObject("markers", Emission(0.6)), SceneObject("water", Refraction(water.n, 1.0))),
        water="water", light=None, render=CPU_64,
        camera=Intrinsics(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy,
                          lens_polynomial(cam, *lens) if lens else None),
        tasks=tuple(Task("wet", name, c.c2w_gl, str(work / f"{name}.png")) for name, c in cams.items()))
    run_blender(job, work)
    return centres, cams, {name: cv2.imread(str(work / f"{name}.png"))[..., ::-1] for name in cams}


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    return render_markers(tmp_path_factory.mktemp("markers"), WaterSurface(0.0, N), far=100.0)


@pytest.fixture(scope="module")
def rendered_sloping(tmp_path_factory):
    # +-30 m: the tilted plane stays below the cameras everywhere they look
    return render_markers(tmp_path_factory.mktemp("markers_sloping"), WaterSurface(0.0, N, SLOPE), far=30.0)


@pytest.fixture(scope="module")
def rendered_lens(tmp_path_factory):
    from ragsplat.datagen.survey import LENS

    # out towards the corners, where the lens moves them most
    return render_markers(tmp_path_factory.mktemp("markers_lens"), WaterSurface(0.0, N), far=100.0, lens=LENS,
                          spread=2.4)


def distort(cam: Camera, uv: np.ndarray, k1: float, k2: float) -> np.ndarray:
    """Pixels [K, 2] of the pinhole `cam` as a lens with radial distortion k1, k2 (COLMAP's RADIAL) sees
    them."""
    x = (uv - [cam.cx, cam.cy]) / [cam.fx, cam.fy]
    r2 = (x * x).sum(1, keepdims=True)
    return x * (1 + k1 * r2 + k2 * r2 * r2) * [cam.fx, cam.fy] + [cam.cx, cam.cy]


def errors(rendered, name: str, water: WaterSurface, other: WaterSurface | None = None,
           lens: tuple[float, float] = (0.0, 0.0), other_lens: tuple[float, float] = (0.0, 0.0)):
    """Pixel distances from each predicted marker (the model with `water` through `lens`; the naive pinhole,
    or the model with `other`, through `other_lens`) to the nearest detected blob, over the markers well
    inside the image."""
    centres, cams, images = rendered
    cam = cams[name]
    found = centroids(images[name])

    def predict(surface, k):
        seen = centres if surface is None else apparent_points(
            torch.tensor(centres), torch.tensor(cam.camera_center), surface).numpy()
        return distort(cam, cam.project(seen)[0], *k)

    expected, alternative = predict(water, lens), predict(other, other_lens)
    inside = np.all((expected > 4) & (expected < WIDTH - 4), axis=1)
    assert inside.sum() >= 8 and len(found) == inside.sum()

    def match(pred):  # distance from each predicted marker to the nearest detected blob
        return np.linalg.norm(pred[inside, None] - found[None], axis=-1).min(1)

    return match(expected), match(alternative), int(inside.sum())


@pytest.mark.parametrize("name", ["nadir", "oblique40"])
def test_markers_land_on_the_refracted_projection(rendered, name):
    err, err_naive, count = errors(rendered, name, WaterSurface(0.0, N))
    print(f"\n{name}: {count} markers, refracted-model error max {err.max():.3f} px "
          f"(mean {err.mean():.3f}); naive pinhole error max {err_naive.max():.2f} px (mean "
          f"{err_naive.mean():.2f})")
    assert err.max() <= 0.15
    assert err_naive.mean() > 2.0  # the refraction is large at this scale: the check has teeth


@pytest.mark.parametrize("name", ["nadir", "oblique40"])
def test_markers_under_a_sloping_surface_land_on_the_tilted_projection(rendered_sloping, name):
    err, err_flat, count = errors(rendered_sloping, name, WaterSurface(0.0, N, SLOPE), WaterSurface(0.0, N))
    print(f"\n{name}, slope {SLOPE}: {count} markers, tilted-model error max {err.max():.3f} px "
          f"(mean {err.mean():.3f}); flat model at the same level: max {err_flat.max():.2f} px "
          f"(mean {err_flat.mean():.2f})")
    assert err.max() <= 0.15
    assert err_flat.mean() > 0.5  # the tilt moves every marker: the check has teeth


@pytest.mark.parametrize("name", ["nadir", "oblique40"])
def test_markers_through_a_lens_land_on_the_distorted_refracted_projection(rendered_lens, name):
    from ragsplat.datagen.survey import LENS

    water = WaterSurface(0.0, N)
    err, err_pinhole, count = errors(rendered_lens, name, water, water, LENS, (0.0, 0.0))
    print(f"\n{name}, lens {LENS}: {count} markers, distorted refracted-model error max {err.max():.3f} px "
          f"(mean {err.mean():.3f}); undistorted: max {err_pinhole.max():.2f} px (mean "
          f"{err_pinhole.mean():.2f})")
    assert err.max() <= 0.15
    assert err_pinhole.max() > 1.5  # the lens moves the outer markers by pixels: the check has teeth
