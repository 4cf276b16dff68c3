"""Field conditions, each seen in Cycles' pixels at smoke scale: turbid water darkens deep bed more than
shallow bed (and red most); the surface reflects more sky at 40 degrees than at nadir and shows the sun's
glint where the geometry puts it; ripples give every photo its own surface; every ground control target is a
checker in the photos that see it; the depth maps also come as float32 TIFF that OpenCV reads."""

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest
from test_blender_markers import CPU_64, centroids, disc

from ragsplat.camera import Camera
from ragsplat.datagen import conditions
from ragsplat.datagen.build import generate, run_blender
from ragsplat.datagen.job import (
    Diffuse,
    Emission,
    Intrinsics,
    Refraction,
    RenderJob,
    Ripples,
    SceneObject,
    Task,
)
from ragsplat.datagen.spec import LightSpec, preset, with_conditions
from ragsplat.dataset import layout

pytestmark = pytest.mark.blender

SUN_ELEVATION, SUN_AZIMUTH = 50.0, 180.0  # in -x, 40 degrees from the zenith


@pytest.fixture(scope="module")
def renders(tmp_path_factory):
    """{"ideal", "turbid", "field"} -> dataset root, all from the smoke reach, seed 0."""
    base = preset("smoke")
    specs = {"ideal": base, "turbid": with_conditions(base, turbidity=1.0), "field": preset("smoke-field")}
    roots = {}
    for name, spec in specs.items():
        roots[name] = tmp_path_factory.mktemp(name)
        assert generate(spec, roots[name])["complete"]
    return roots


def frames(root):
    tf = json.loads((root / layout.TRANSFORMS).read_text())
    for f in tf["frames"]:
        cam = Camera.from_c2w_gl(f["transform_matrix"], tf["w"], tf["h"],
                                 intrinsics=(tf["fl_x"], tf["fl_y"], tf["cx"], tf["cy"]))
        yield f, cam


def linear(path) -> np.ndarray:
    c = cv2.imread(str(path))[..., ::-1].astype(np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def bed_points(root, f, cam) -> np.ndarray:
    """World points [H*W, 3] of the dry scene under each pixel (from the exact depth)."""
    depth = layout.read_depth(root / f["gt_depth_file_path"])
    j, i = np.indices(depth.shape)
    return cam.unproject(np.stack([i.ravel() + 0.5, j.ravel() + 0.5], -1), depth.ravel())


def test_turbid_water_darkens_deep_bed_more_than_shallow_and_red_most(renders):
    ratios = {"deep": [], "shallow": []}
    for f, cam in frames(renders["ideal"]):
        depth = -bed_points(renders["ideal"], f, cam)[:, 2]  # below the level (0)
        clear = linear(renders["ideal"] / f["file_path"]).reshape(-1, 3)
        turbid = linear(renders["turbid"] / f["file_path"]).reshape(-1, 3)
        for key, where in (("deep", depth > 1.2), ("shallow", (depth > 0.05) & (depth < 0.4))):
            ratios[key].append(turbid[where].sum(0) / clear[where].sum(0))  # per channel
    deep, shallow = np.nanmean(ratios["deep"], 0), np.nanmean(ratios["shallow"], 0)
    print(f"\nturbid / clear, per RGB channel: shallow {np.round(shallow, 3)}, deep {np.round(deep, 3)}")
    assert (deep < shallow - 0.1).all()  # Beer-Lambert: the deeper, the darker
    assert deep[0] < deep[1] and deep[0] < 0.6  # red is absorbed most
    assert shallow.min() > 0.6  # shallow bed stays visible


def test_sky_reflection_grows_towards_oblique_views_and_the_glint_falls_where_the_sun_puts_it(tmp_path):
    """A dark bed 1 m under a flat surface, the sun at 50 degrees in -x, seen at nadir and from a 40 degree
    oblique east of the centre looking west, whose view ray at the image centre mirrors onto the sun. Many
    samples: Cycles picks the mirror for about R = 2 % of a pixel's samples, and the sun is a 1 degree
    disc."""
    far, width = 100.0, 64
    np.savez(tmp_path / "geometry.npz",
             bed_verts=np.array([[-far, -far, -1], [far, -far, -1], [far, far, -1], [-far, far, -1]], float),
             bed_tris=np.array([[0, 1, 2], [0, 2, 3]]),
             water_verts=np.array([[-far, -far, 0], [far, -far, 0], [far, far, 0], [-far, far, 0]], float),
             water_tris=np.array([[0, 1, 2], [0, 2, 3]]))
    height, tilt = 3.0, np.radians(90 - SUN_ELEVATION)
    cams = {"nadir": Camera.look_at([0, 0, height], [0, 0, 0], width, width, 70.0),
            "oblique40": Camera.look_at([height * np.tan(tilt), 0, height], [0, 0, 0], width, width, 70.0,
                                        up=(0, 0, 1)),
            # Looking away from the sun, 50 degrees down: the view rays meet the water at 15 to 85 degrees.
            "away": Camera.look_at([0, 0, height], [height * np.tan(np.radians(50)), 0, 0], width, width,
                                   70.0, up=(0, 0, 1))}
    light = LightSpec(sun_elevation=SUN_ELEVATION, sun_azimuth=SUN_AZIMUTH, sun_strength=3.0, sun_angle=1.0,
                      sky_strength=0.3)
    images = {}
    for reflect in (False, True):
        tasks = tuple(Task("wet", name, c.c2w_gl, str(tmp_path / f"{name}{reflect}.png"))
                      for name, c in cams.items())
        run_blender(RenderJob(
            geometry=str(tmp_path / "geometry.npz"),
            objects=(SceneObject("bed", Diffuse(0.05)),
                     SceneObject("water", Refraction(1.33, 1 / 1.33**2, reflect))),
            water="water", light=light, glossy_bounces=1, render=replace(CPU_64, samples=512),
            camera=Intrinsics(width, width, cams["nadir"].fx, cams["nadir"].fy, width / 2, width / 2),
            tasks=tasks), tmp_path)
        images[reflect] = {name: linear(tmp_path / f"{name}{reflect}.png") for name in cams}
    glint = {name: images[True][name].min(-1) > 0.95 for name in cams}
    added = {name: (images[True][name] - images[False][name])[~glint[name]].mean() for name in cams}
    print(f"\nsky reflection added (linear, mean): nadir {added['nadir']:.4f}, oblique40 "
          f"{added['oblique40']:.4f}; glint pixels: nadir {glint['nadir'].sum()}, oblique40 "
          f"{glint['oblique40'].sum()}")
    assert 0 < added["nadir"] and added["oblique40"] > 1.5 * added["nadir"]
    # Fresnel, not a constant mirror share: R is about 0.02 up to 40 degrees and 0.3 at 80. Away from the
    # sun the sky itself changes far less between the image's top rows (grazing) and its bottom rows.
    gain = images[True]["away"] - images[False]["away"]
    top, bottom = gain[: width // 6].mean(), gain[-width // 6:].mean()
    print(f"looking away from the sun: added {top:.4f} near the horizon, {bottom:.4f} at the bottom")
    assert top > 5 * bottom > 0
    # at the centre
    assert glint["oblique40"][width // 2 - 2:width // 2 + 2, width // 2 - 2:width // 2 + 2].any()
    assert glint["oblique40"].sum() <= 16 and not glint["nadir"].any()  # a 1 degree sun: a small glint
    assert all(images[False][name].max() < 0.5 for name in cams)  # no reflection, no glint


def test_ripples_give_every_photo_its_own_surface(tmp_path):
    """Emissive markers 1 m under rippled water, one nadir camera, the surfaces of photos 0, 1 and 0 again:
    the markers move between the two surfaces and not between the same surface rendered twice."""
    spec = preset("smoke")
    c = replace(spec.conditions or preset("smoke-field").conditions, ripple_amplitude=0.01)
    spec = replace(spec, conditions=c)
    size, depth = 6.0, 1.0
    xs = np.linspace(-0.75, 0.75, 4)
    parts = [disc([x, y, -depth], 0.04) for x in xs for y in xs]
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    water_verts, water_tris, weight = conditions.water_surface(spec, size, 100.0)
    np.savez(tmp_path / "geometry.npz", markers_verts=np.concatenate([v for v, _ in parts]),
             markers_tris=np.concatenate([t + o for (_, t), o in zip(parts, offsets)]),
             water_verts=water_verts, water_tris=water_tris, water_weight=weight)
    cam = Camera.look_at([0.05, -0.03, 3.0], [0.05, -0.03, 0.0], 160, 160, 70.0)
    k, amplitude = conditions.ripple_waves(c, spec.seed)
    tasks = tuple(Task("wet", f"{i}", cam.c2w_gl, str(tmp_path / f"{i}.png"),
                       conditions.ripple_phases(c, spec.seed, view)) for i, view in enumerate((0, 1, 0)))
    job = RenderJob(geometry=str(tmp_path / "geometry.npz"),
                    objects=(SceneObject("markers", Emission(0.6)),
                             SceneObject("water", Refraction(1.33, 1.0))),
                    water="water", light=None, ripples=Ripples(k, amplitude, 0.0), render=CPU_64,
                    camera=Intrinsics(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy), tasks=tasks)
    run_blender(job, tmp_path)
    found = [centroids(cv2.imread(str(tmp_path / f"{i}.png"))[..., ::-1]) for i in range(3)]
    assert len(found[0]) == len(found[1]) == len(found[2]) == len(parts)
    a = found[0]
    b, again = (f[np.linalg.norm(a[:, None] - f[None], axis=-1).argmin(1)] for f in found[1:])  # nearest blob
    moved = np.linalg.norm(a - b, axis=1)
    slope = conditions.ripple_slope(k, amplitude)
    # A ray bends by about (1 - 1/n) times the surface slope; over 1 m of water that is the marker's shift,
    # and two independent surfaces differ by sqrt(2) of one. Four rms slopes: a bound, not a fit.
    scale = (1 - 1 / 1.33) * 4 * np.sqrt(2) * slope * depth * cam.fx / 3.0  # px
    print(f"\nmarkers moved between two photos' surfaces: median {np.median(moved):.3f} px, max "
          f"{moved.max():.3f} px (bound {scale:.2f} px); same surface twice: {np.abs(a - again).max():.2e} "
          "px")
    assert np.median(moved) > 0.05 and moved.max() < scale
    assert np.abs(a - again).max() < 0.02


def test_every_ground_control_target_shows_its_checker(renders):
    root = renders["field"]
    spec = preset("smoke-field")
    targets = np.load(root / layout.GT_TARGETS)
    quarter = spec.conditions.target_size / 4
    black = targets[:, None] + np.array([[-quarter, -quarter, 0], [quarter, quarter, 0]])
    white = targets[:, None] + np.array([[quarter, -quarter, 0], [-quarter, quarter, 0]])
    seen = np.zeros(len(targets), int)
    for f, cam in frames(root):
        grey = cv2.imread(str(root / f["file_path"]), cv2.IMREAD_GRAYSCALE).astype(np.float32)
        depth = layout.read_depth(root / f["gt_depth_file_path"])
        for t in range(len(targets)):
            (uv, z) = cam.project(np.concatenate([targets[t:t + 1], black[t], white[t]]))
            if not ((uv >= 3) & (uv < cam.width - 3)).all() or (z <= 0).any():
                continue
            if depth[int(uv[0, 1]), int(uv[0, 0])] < z[0] - 0.1:  # something stands in front of it
                continue
            if np.linalg.norm(uv[1:] - uv[0], axis=1).min() < 1.5:  # a square under 3 px: seen, not resolved
                continue
            sample = [cv2.getRectSubPix(grey, (1, 1), tuple(p - 0.5))[0, 0] for p in uv[1:]]
            assert max(sample[:2]) + 40 < min(sample[2:]), (f["file_path"], t, sample)
            seen[t] += 1
    print(f"\nresolved sightings per target: {seen.tolist()}")
    # At 64 px the targets the flight sees only from afar are a few pixels wide; most are resolved twice.
    assert (seen >= 2).sum() >= 4


def test_field_dataset_records_its_conditions_and_depth_tiffs_match_the_exr(renders):
    root = renders["field"]
    scene = json.loads((root / layout.SCENE).read_text())
    assert scene["conditions"]["reflection"] and scene["conditions"]["targets"] == 6
    assert scene["conditions"]["extinction_per_m"][0] > scene["conditions"]["extinction_per_m"][1]
    survey = (root / layout.SURVEY_GCP).read_text().splitlines()
    assert len(survey) == 1 + len(np.load(root / layout.GT_TARGETS))  # the rendered targets are the GCPs
    for f, _ in frames(root):
        exr = layout.read_depth(root / f["gt_depth_file_path"])
        tiff = cv2.imread(str(root / f["gt_depth_file_path"].replace(".exr", ".tif")), cv2.IMREAD_UNCHANGED)
        assert tiff.dtype == np.float32
        np.testing.assert_array_equal(tiff, exr)  # lossless: the same float32 values
