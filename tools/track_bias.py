"""What a survey's tracks say with everything else exact: each track of RUN/model (the photos' keypoints),
carried to the truth by a similarity of its cameras, triangulated again with the twin's true cameras,
through its true water surface where the track is over the wet bed, and its height compared with the
truth's (gt/bed_grid.npy, gt/bank_grid.npy) at the same place. The cameras, the frame and the level then
take no part: an offset left is in the keypoints (or the render). Printed as JSON: the dry and the
submerged tracks' mean and median height error (m), the submerged ones by true depth.

With --synthetic, the same for SIFT alone: a flat bed of random texture DEPTH under a calm surface,
ray-traced here (numpy: Snell at the surface, the texture sampled bilinearly, 3 x 3 samples a pixel) into
four nadir photos of a mapping flight's geometry (the river-mapping twin's 1200 x 900 px, 81 degrees, 80 /
70 % overlap), and once more in air at the same depth; pycolmap's SIFT (doubled, as the survey runs photos
of this size) matches every pair and each match is triangulated with the true cameras: no renderer, frame
or level involved. With --cycles the photos of that bed come from the benchmark's renderer instead.

With --in-air, the twin's own bed with and without its water: the photos PHOTOS of the stretch DATA are
rendered again without the water (the "dry" pass, from the scene the stretch was cut from), both sets are
SIFT-matched pair by pair and triangulated with the true cameras, through the true surface and in air; the
points over the river (true depth over 10 cm) and over the banks against the exact mesh (gt/bed_surface.npz).
What the river's points are off in air is the bed's relief and texture, not the water.

    python -m tools.track_bias RUN DATA [--tracks 4000]   # DATA: the dataset (or stretch) of the photos
    python -m tools.track_bias --synthetic [--cycles] [--altitude 30] [--depth 1.5] [--work DIR]
    python -m tools.track_bias --in-air DATA [--photos 0004,0005,0006,0013,0014,0015] [--work DIR]
"""

from __future__ import annotations

import argparse
import itertools
import json
import tempfile
from pathlib import Path

import numpy as np

NEAR = 0.03  # m: a track counts where a truth node lies this close to it
WET = 0.1  # m: submerged tracks at least this deep, clear of the waterline's mixed neighbours
W, H, FOV, N, SUPERSAMPLE = 1200, 900, 81.0, 1.33, 3  # the river-mapping twin's photos
TEXEL, HALF = 0.01, 32.0  # m: the texture's grid and half its extent


def _observations(rec, names, points):
    """(track index [K], camera index [K], keypoints [K, 2]) of the tracks `points` (ids)."""
    index = {n: i for i, n in enumerate(names)}
    track, camera, xy = [], [], []
    for k, pid in enumerate(points):
        for el in rec.points3D[pid].track.elements:
            im = rec.images[el.image_id]
            track.append(k)
            camera.append(index[Path(im.name).stem])
            xy.append(im.points2D[el.point2D_idx].xy)
    return np.array(track), np.array(camera), np.array(xy)


def triangulate(start, track, camera, xy, cams, water, iterations: int = 8):
    """Tracks [T, 3] refined from `start` by Gauss-Newton on their reprojection through `water` (None: in air)
    into the true cameras `cams` (a list, indexed by `camera`). Central differences for the 3 x 3 blocks."""
    import torch

    from ragsplat.refraction import apparent_points_each

    R = torch.tensor(np.array([c.R for c in cams]))[camera]
    t = torch.tensor(np.array([c.t for c in cams]))[camera]
    centre = torch.tensor(np.array([c.camera_center for c in cams]))[camera]
    f = torch.tensor([[c.fx, c.fy] for c in cams])[camera]
    pp = torch.tensor([[c.cx, c.cy] for c in cams])[camera]
    track, uv, X = torch.tensor(track), torch.tensor(xy), torch.tensor(start)

    def residual(X):  # [K, 2] pixels
        P = X[track] if water is None else apparent_points_each(X[track], centre, water)
        pc = (R @ P[:, :, None])[..., 0] + t
        return f * pc[:, :2] / pc[:, 2:] + pp - uv

    for _ in range(iterations):
        r = residual(X)
        steps = 1e-6 * torch.eye(3, dtype=X.dtype)
        J = torch.stack([(residual(X + e) - residual(X - e)) / 2e-6 for e in steps], -1)  # [K, 2, 3]
        Jt = J.transpose(1, 2)
        JtJ = torch.zeros(len(X), 3, 3, dtype=X.dtype).index_add_(0, track, Jt @ J)
        Jtr = torch.zeros(len(X), 3, dtype=X.dtype).index_add_(0, track, (Jt @ r[:, :, None])[..., 0])
        # damped: a wrong match's point may run where its rays barely constrain it (sorted out by the caller)
        X = X - torch.linalg.solve(JtJ + 1e-9 * torch.eye(3, dtype=X.dtype), torch.nan_to_num(Jtr))
    return X.numpy()


def track_bias(run: Path, truth: Path, tracks: int = 4000) -> dict:
    import pycolmap
    from scipy.spatial import cKDTree

    from ragsplat.dataset.layout import GT_SURFACE, Surface
    from ragsplat.dataset.load import load_dataset
    from ragsplat.eval.score_file import survey_geotags
    from ragsplat.survey.georef import fit_similarity
    from ragsplat.water_surface import WaterSurface

    views = load_dataset(truth, splits=("train",), load_dry=False)
    by_name = {Path(v.file_path).stem: v.camera for v in views.train}
    names = sorted(by_name)
    cams = [by_name[n] for n in names]
    rec = pycolmap.Reconstruction(str(run / "model"))
    # the model carried to the truth by its cameras' similarity: a start and a place for each track
    geotags = survey_geotags(truth)
    offset = np.asarray(geotags.offset) if geotags is not None else np.zeros(3)
    seen = [i for i in rec.reg_image_ids() if Path(rec.images[i].name).stem in by_name]
    fit = fit_similarity(np.array([rec.images[i].projection_center() for i in seen]) - offset,
                         np.array([by_name[Path(rec.images[i].name).stem].camera_center for i in seen]))
    w = json.loads((truth / "scene.json").read_text())["water"]
    water = WaterSurface(w["level"], w["n"], tuple(w.get("slope", (0.0, 0.0))))
    exact = Surface.load(truth / GT_SURFACE) if (truth / GT_SURFACE).exists() else None
    out = {}
    for kind, grid in (("dry", "bank_grid.npy"), ("submerged", "bed_grid.npy")):
        truth_z = np.load(truth / "gt" / grid)
        tree = cKDTree(truth_z[:, :2])
        ids = [pid for pid, p in rec.points3D.items() if len(p.track.elements) >= 3
               and all(Path(rec.images[el.image_id].name).stem in by_name for el in p.track.elements)]
        start = fit.apply(np.array([rec.points3D[i].xyz for i in ids]) - offset)
        dist, near = tree.query(start[:, :2])
        keep = dist < NEAR
        if kind == "submerged":
            keep &= water.height(start[:, :2]) - truth_z[near, 2] > WET
        rows = np.flatnonzero(keep)[:tracks]
        if not len(rows):
            continue
        track, camera, xy = _observations(rec, names, [ids[i] for i in rows])
        X = triangulate(start[rows], track, camera, xy, cams,
                        water if kind == "submerged" else None)
        dist, near = tree.query(X[:, :2])
        ok = dist < NEAR
        err = X[ok, 2] - truth_z[near[ok], 2]
        row = {"tracks": int(ok.sum()), "mean_m": float(err.mean()), "median_m": float(np.median(err))}
        if exact is not None:  # the mesh's own height under each point, not the nearest node's
            off = X[ok, 2] - exact.height_at(X[ok, :2])
            row |= {"mean_to_mesh_m": float(off.mean()), "median_to_mesh_m": float(np.median(off))}
        if kind == "submerged":
            depth = water.height(X[ok, :2]) - truth_z[near[ok], 2]
            bands = [WET, 0.5, 1.0, 2.0, np.inf]
            row["mean_by_true_depth_m"] = {f"{lo:g}-{hi:g} m": float(err[(depth >= lo) & (depth < hi)].mean())
                                           for lo, hi in itertools.pairwise(bands)
                                           if ((depth >= lo) & (depth < hi)).any()}
        out[kind] = row
    return out

def bed_texture(seed: int = 1) -> np.ndarray:
    """[n, n] grey values in [0, 1]: white noise blurred to about 3 cm, a stony bed's scale of detail."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    n = int(2 * HALF / TEXEL)
    tex = ndimage.gaussian_filter(rng.random((n, n), dtype=np.float32), 3.0)
    return np.clip(0.5 + 0.18 * (tex - tex.mean()) / tex.std(), 0, 1)


def render(cam, tex: np.ndarray, depth: float, water: bool) -> np.ndarray:
    """[H, W] uint8 photo of the bed at z = -depth, through the surface z = 0 (index N) or in air."""
    from scipy import ndimage

    j, i = np.meshgrid((np.arange(W * SUPERSAMPLE) + 0.5) / SUPERSAMPLE,
                       (np.arange(H * SUPERSAMPLE) + 0.5) / SUPERSAMPLE)
    d = np.stack([(j - cam.cx) / cam.fx, (i - cam.cy) / cam.fy, np.ones_like(j)], -1) @ cam.R  # world rays
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    C = cam.camera_center
    if water:
        P = C + (-C[2] / d[..., 2])[..., None] * d  # on the surface
        cos_i, eta = -d[..., 2], 1 / N
        bend = eta * cos_i - np.sqrt(1 - eta ** 2 * (1 - cos_i ** 2))
        d = eta * d + bend[..., None] * np.array([0, 0, 1.0])
    else:
        P = C
    B = P + ((-depth - P[..., 2]) / d[..., 2])[..., None] * d
    u, v = (B[..., 0] + HALF) / TEXEL - 0.5, (B[..., 1] + HALF) / TEXEL - 0.5
    img = ndimage.map_coordinates(tex, [v.ravel(), u.ravel()], order=1).reshape(u.shape)
    img = img.reshape(H, SUPERSAMPLE, W, SUPERSAMPLE).mean((1, 3))
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def matches(work: Path, cams, images) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(track [K], camera [K], keypoints [K, 2]) of every pair's verified SIFT matches, two views a track;
    `images`: [H, W] uint8 arrays or photo files, one for each of `cams`, in order."""
    import shutil

    import cv2
    import pycolmap

    (work / "img").mkdir(parents=True, exist_ok=True)
    for k, img in enumerate(images):
        if isinstance(img, Path):
            shutil.copy(img, work / "img" / f"{k}{img.suffix}")
        else:
            cv2.imwrite(str(work / "img" / f"{k}.png"), img)
    db = work / "database.db"
    db.unlink(missing_ok=True)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.first_octave = -1
    c = cams[0]
    reader = pycolmap.ImageReaderOptions(camera_model="PINHOLE", camera_params=f"{c.fx},{c.fy},{c.cx},{c.cy}")
    pycolmap.extract_features(db, work / "img", camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction)
    pycolmap.match_exhaustive(db)
    data = pycolmap.Database.open(str(db))
    photo = {im.image_id: int(Path(im.name).stem) for im in data.read_all_images()}
    ids = sorted(photo, key=photo.get)  # the extraction's threads number the photos in any order
    track, camera, xy = [], [], []
    for a, ia in enumerate(ids):
        for ib in ids[a + 1:]:
            pairs = data.read_two_view_geometry(ia, ib).inlier_matches
            if pairs is None or not len(pairs):
                continue
            ka, kb = data.read_keypoints(ia)[:, :2], data.read_keypoints(ib)[:, :2]
            # the extraction's threads also order each photo's keypoints in any order: the pairs by pixel
            pairs = pairs[np.lexsort((*kb[pairs[:, 1]].T[::-1], *ka[pairs[:, 0]].T[::-1]))]
            first = len(track) // 2
            track += np.repeat(np.arange(first, first + len(pairs)), 2).tolist()
            camera += [photo[ia], photo[ib]] * len(pairs)
            xy += np.stack([ka[pairs[:, 0]], kb[pairs[:, 1]]], 1).reshape(-1, 2).tolist()
    data.close()
    return np.array(track), np.array(camera), np.array(xy)


def render_cycles(work: Path, cams, tex: np.ndarray, depth: float, samples: int = 16) -> dict[bool, list]:
    """{through the water: [H, W] uint8 photos} of the same bed rendered by the benchmark's Cycles renderer
    (`ragsplat.datagen.build.run_blender`): the texture as the bed's albedo under the default sun, the
    surface a `Refraction` plane; the "wet" pass, and the "dry" one that leaves the water out."""
    import cv2

    from ragsplat.datagen.build import run_blender
    from ragsplat.datagen.job import (
        Intrinsics,
        Refraction,
        RenderJob,
        RenderSettings,
        SceneObject,
        Task,
        Texture,
    )
    from ragsplat.datagen.spec import LightSpec

    work.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(work / "bed.png"), (np.clip(tex[::-1], 0, 1) * 255 + 0.5).astype(np.uint8))  # rows: +y up
    corners = np.array([[-HALF, -HALF], [HALF, -HALF], [HALF, HALF], [-HALF, HALF]])
    far = 100 * HALF
    np.savez(work / "geometry.npz", bed_verts=np.column_stack([corners, np.full(4, -depth)]),
             bed_tris=np.array([[0, 1, 2], [0, 2, 3]]), bed_uv=(corners + HALF) / (2 * HALF),
             water_verts=np.column_stack([corners / HALF * far, np.zeros(4)]),
             water_tris=np.array([[0, 1, 2], [0, 2, 3]]))
    c = cams[0]
    job = RenderJob(geometry=str(work / "geometry.npz"),
                    objects=(SceneObject("bed", Texture(str(work / "bed.png"))),
                             SceneObject("water", Refraction(N, 1.0))),
                    water="water", light=LightSpec(),
                    render=RenderSettings(samples=samples, device="CPU", threads=0, seed=0, filter_width=1.5,
                                          depth_filter=0.01, exposure=0.0),
                    camera=Intrinsics(c.width, c.height, c.fx, c.fy, c.cx, c.cy),
                    tasks=tuple(Task(kind, f"{kind}{k}", cam.c2w_gl, str(work / f"{kind}{k}.png"))
                                for kind in ("wet", "dry") for k, cam in enumerate(cams)))
    run_blender(job, work)
    return {wet: [cv2.imread(str(work / f"{'wet' if wet else 'dry'}{k}.png"), cv2.IMREAD_GRAYSCALE)
                  for k in range(len(cams))] for wet in (True, False)}


def sift_through_water(work: Path, altitude: float = 30.0, depth: float = 1.5, cycles: bool = False) -> dict:
    from ragsplat.camera import Camera
    from ragsplat.water_surface import WaterSurface

    # 80 % forward and 70 % side overlap of these photos' footprint at this altitude
    across = 2 * altitude * np.tan(np.radians(FOV / 2))  # the footprint along the photo's width
    fx, fy = 0.2 * across, 0.3 * across * H / W
    cams = [Camera.look_at([x, y, altitude], [x, y, 0.0], W, H, FOV)
            for x in (-fx / 2, fx / 2) for y in (-fy / 2, fy / 2)]
    tex = bed_texture()
    out = {"altitude_m": altitude, "depth_m": depth, "renderer": "Cycles" if cycles else "numpy"}
    photos = render_cycles(work / "cycles", cams, tex, depth) if cycles else None
    for kind, water in (("through_water", True), ("in_air", False)):
        images = photos[water] if cycles else [render(c, tex, depth, water) for c in cams]
        track, camera, xy = matches(work / kind, cams, images)
        start = np.tile([0.0, 0.0, -depth], (int(track.max()) + 1, 1))
        surface = WaterSurface(0.0, N) if water else None
        X = triangulate(start, track, camera, xy, cams, surface, 1)  # one step from the bed's depth
        X = triangulate(X, track, camera, xy, cams, surface, 10)
        err = X[:, 2] + depth
        err = err[np.abs(err) < 0.3]  # a wrong match's height says nothing of a bias
        out[kind] = {"matches": len(err), "mean_m": float(err.mean()), "median_m": float(np.median(err))}
    return out


def bed_in_air(work: Path, data: Path, photos: list[str]) -> dict:
    """{"through_water", "in_air": {"river", "bank": {points, mean_m, median_m}}} of the stretch `data`'s
    photos `photos`, the second set rendered again without the water (see the module docstring)."""
    from ragsplat.datagen.build import render_job, run_blender
    from ragsplat.datagen.job import Task
    from ragsplat.datagen.spec import SceneSpec
    from ragsplat.dataset.layout import GT_SURFACE, Surface
    from ragsplat.dataset.load import load_dataset
    from ragsplat.water_surface import WaterSurface

    scene = json.loads((data / "scene.json").read_text())
    source = Path(scene["stretch"]["of"]) if "stretch" in scene else data
    spec = SceneSpec.from_dict(json.loads((source / "scene" / "spec.json").read_text()))
    views = {Path(v.file_path).stem: v for v in load_dataset(data, splits=("train",), load_dry=False).train}
    cams = [views[p].camera for p in photos]
    dry = work / "dry"
    dry.mkdir(parents=True, exist_ok=True)
    run_blender(render_job(spec, source, cams[0], [Task("dry", p, c.c2w_gl, str(dry / f"{p}.png"))
                                                   for p, c in zip(photos, cams)]), dry)
    w = scene["water"]
    water = WaterSurface(w["level"], w["n"], tuple(w.get("slope", (0.0, 0.0))))
    mesh = Surface.load(data / GT_SURFACE)
    out = {"photos": photos}
    for kind, files in (("through_water", [data / views[p].file_path for p in photos]),
                        ("in_air", [dry / f"{p}.png" for p in photos])):
        track, camera, xy = matches(work / kind, cams, files)
        X = triangulate(np.tile([0.0, 0.0, w["level"]], (int(track.max()) + 1, 1)), track, camera, xy, cams,
                        None, 10)
        if kind == "through_water":  # from the classical depth-times-n correction of the pinhole point
            surface = water.height(X[:, :2])
            X[:, 2] = np.where(X[:, 2] < surface, surface - (surface - X[:, 2]) * w["n"], X[:, 2])
            X = triangulate(X, track, camera, xy, cams, water, 1)
            X = triangulate(X, track, camera, xy, cams, water, 10)
        truth = mesh.height_at(X[:, :2])
        depth, err = water.height(X[:, :2]) - truth, X[:, 2] - truth
        ok = np.abs(err) < 0.3  # a wrong match's height says nothing of a bias
        out[kind] = {region: {"points": int(sel.sum()), "mean_m": float(err[sel].mean()),
                              "median_m": float(np.median(err[sel]))}
                     for region, sel in (("river", ok & (depth > WET)), ("bank", ok & (depth < -0.05)))}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, nargs="?")
    parser.add_argument("data", type=Path, nargs="?")
    parser.add_argument("--tracks", type=int, default=4000, help="tracks of each kind (the model's first)")
    parser.add_argument("--synthetic", action="store_true", help="SIFT on a ray-traced bed instead of a run")
    parser.add_argument("--altitude", type=float, default=30.0, help="with --synthetic (m)")
    parser.add_argument("--depth", type=float, default=1.5, help="with --synthetic (m)")
    parser.add_argument("--cycles", action="store_true", help="with --synthetic: the photos by Cycles")
    parser.add_argument("--work", type=Path, help="with --synthetic or --in-air: keep the photos here")
    parser.add_argument("--in-air", type=Path, metavar="DATA", help="the bed with and without the water")
    parser.add_argument("--photos", default="0004,0005,0006,0013,0014,0015", help="with --in-air")
    args = parser.parse_args()
    if args.in_air is not None or args.synthetic:
        with tempfile.TemporaryDirectory() as tmp:
            work = args.work or Path(tmp)
            found = (bed_in_air(work, args.in_air, args.photos.split(",")) if args.in_air is not None
                     else sift_through_water(work, args.altitude, args.depth, args.cycles))
        print(json.dumps(found, indent=1))
    elif args.run is None or args.data is None:
        parser.error("RUN and DATA, or --synthetic")
    else:
        print(json.dumps(track_bias(args.run, args.data, args.tracks), indent=1))


if __name__ == "__main__":
    main()
