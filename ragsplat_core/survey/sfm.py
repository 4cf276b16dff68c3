"""Structure from motion of a survey's photos with pycolmap on the CPU, and the model as tensors for the
bundle adjustment through the water (`bundle.adjust`) and back.

SIFT features with the focal length from each photo's EXIF (one camera per size and EXIF, COLMAP's AUTO
mode), matching (every pair up to `EXHAUSTIVE_MAX` photos; beyond, each photo with its `NEIGHBOURS` nearest
by the positions, `neighbour_pairs`), incremental mapping. The intrinsics are held at the EXIF focal length,
the image centre and no distortion: refined by a pinhole bundle adjustment they absorb part of the refraction
(on a synthetic survey SIMPLE_RADIAL's k came out at 0.012 for a distortion-free camera, and the poses'
tilt stayed 0.28 degrees after the adjustment through the water instead of under 0.1). The model comes out in
an arbitrary frame and scale: `georef` fixes both.
"""

from __future__ import annotations

import contextlib
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

# the pairing a dataset's tracks share; the survey's stage reads them here (`sfm.NEIGHBOURS`)
from ragsplat.dataset.colmap import NEIGHBOURS, neighbour_pairs  # noqa: F401
from ragsplat.errors import DatasetError

CAMERA_MODEL = "SIMPLE_PINHOLE"  # one focal length, the principal point at the centre, no distortion
# pycolmap's SIFT doubles a photo first (its first octave is -1), which finds the finest keypoints where a
# small photo has few. A larger photo is scaled to at most FEATURE_MAX_SIZE pixels on its longer side
# (COLMAP's own cap) and not doubled: SIFT keeps its coarsest levels up to 8 192 features, so a drone photo's
# doubled levels cost most of the time and are dropped; its keypoints come back in the photo's pixels.
DOUBLED_MAX = 2048
FEATURE_MAX_SIZE = 3200
# Every pair is matched up to this many photos (4 950 pairs, a few minutes on 2 cores); a larger survey
# matches each photo with its NEIGHBOURS nearest by the positions (`colmap.neighbour_pairs`)
EXHAUSTIVE_MAX = 100


def reconstruct(images: Path, names: list[str], work: Path, camera_model: str = CAMERA_MODEL,
                threads: int = -1, progress=None, pairs: np.ndarray | None = None,
                timings: dict | None = None):
    """The largest pycolmap Reconstruction of the photos `names` in `images`; `work` holds the feature
    database and the mapper's models (made anew). `pairs` [P, 2] (indices into `names`, `neighbour_pairs`)
    are the pairs matched; None: every pair. `progress(desc, total, unit)`, when given, makes a bar
    (`update(n)`, `close()`) for each stage: the photos with features, the pairs matched (both counted in
    the database as pycolmap fills it), the photos registered. `timings`, when given, receives each stage's
    seconds ("features_s", "matching_s", "mapping_s") and "pairs". Raises DatasetError when fewer than half of
    the photos (or fewer than 3) are registered."""
    import pycolmap

    timings = {} if timings is None else timings
    work = Path(work)
    shutil.rmtree(work, ignore_errors=True)
    (work / "sparse").mkdir(parents=True)
    pycolmap.logging.minloglevel = int(pycolmap.logging.Level.ERROR.value)  # no progress chatter, errors only
    pycolmap.set_random_seed(0)
    extraction, matching = pycolmap.FeatureExtractionOptions(), pycolmap.FeatureMatchingOptions()
    extraction.num_threads = matching.num_threads = threads
    extraction.max_image_size = FEATURE_MAX_SIZE
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    db = work / "database.db"
    t0 = time.perf_counter()
    with _counted(progress, "features", len(names), "photo", db, "descriptors"):
        for first_octave, group in first_octaves(images, names).items():
            extraction.sift.first_octave = first_octave
            pycolmap.extract_features(db, images, group, camera_mode=pycolmap.CameraMode.AUTO,
                                      reader_options=reader,
                                      extraction_options=extraction, device=pycolmap.Device.cpu)
    t1 = time.perf_counter()
    count = len(names) * (len(names) - 1) // 2 if pairs is None else len(pairs)
    with _counted(progress, "matching (every pair)" if pairs is None else "matching (neighbours)", count,
                  "pair", db, "two_view_geometries"):
        if pairs is None:
            pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
        else:
            listed = work / "pairs.txt"
            listed.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in pairs))
            pycolmap.match_image_pairs(db, matching_options=matching, device=pycolmap.Device.cpu,
                                       pairing_options=pycolmap.ImportedPairingOptions(match_list_path=str(listed)))
    t2 = time.perf_counter()
    timings.update(pairs=count, features_s=t1 - t0, matching_s=t2 - t1)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads, options.random_seed = threads, 0
    options.ba_refine_focal_length = options.ba_refine_principal_point = False
    options.ba_refine_extra_params = False
    bar = None if progress is None else progress("mapping", len(names), "photo")
    try:
        models = pycolmap.incremental_mapping(
            db, images, work / "sparse", options=options,
            initial_image_pair_callback=None if bar is None else (lambda: bar.update(2)),
            next_image_callback=None if bar is None else (lambda: bar.update(1)))
        rec = max(models.values(), key=lambda r: r.num_reg_images(), default=None)
        registered = 0 if rec is None else rec.num_reg_images()
        if bar is not None:  # the callbacks count every model's images; the largest model's is what is kept
            bar.n = registered
            bar.refresh()
    finally:
        if bar is not None:
            bar.close()
    timings["mapping_s"] = time.perf_counter() - t2
    if registered < max(3, len(names) / 2):
        raise DatasetError(f"{images}: structure from motion registered only {registered} of {len(names)} "
                           "photos (too little overlap or texture, or photos of different places?)")
    return rec


def first_octaves(images: Path, names: list[str]) -> dict[int, list[str]]:
    """The photos `names` by the first octave SIFT starts them at: -1 (doubled) up to DOUBLED_MAX pixels on
    the longer side, 0 beyond."""
    from PIL import Image

    groups: dict[int, list[str]] = {}
    for name in names:
        with Image.open(Path(images) / name) as photo:  # reads the header only
            groups.setdefault(-1 if max(photo.size) <= DOUBLED_MAX else 0, []).append(name)
    return groups


# Counts a table's rows twice a second, printing each count. It runs in another process: SQLite's locks hold
# between processes, not between two copies of SQLite in one (pycolmap links its own; reading its database
# from Python's sqlite3 in the same process crashed the matcher's writes with SIGBUS).
_POLL = """import sqlite3, sys, time
while True:
    try:
        with sqlite3.connect(sys.argv[1], uri=True, timeout=1) as con:
            print(con.execute("SELECT COUNT(*) FROM " + sys.argv[2]).fetchone()[0], flush=True)
    except sqlite3.Error:
        pass
    time.sleep(0.5)
"""


@contextlib.contextmanager
def _counted(progress, desc: str, total: int, unit: str, db: Path, table: str):
    """A bar (`progress`) of the rows of `table` in the database while pycolmap fills it (its extraction and
    matching take no callback), read by `_POLL` in a child process; nothing without `progress`."""
    if progress is None:
        yield
        return
    bar, seen = progress(desc, total, unit), [0]
    child = subprocess.Popen([sys.executable, "-c", _POLL, f"file:{db}?mode=ro", table],
                             stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)

    def follow():
        for line in child.stdout:
            rows = min(int(line), total)
            if rows > seen[0]:
                bar.update(rows - seen[0])
                seen[0] = rows

    thread = threading.Thread(target=follow, daemon=True)
    thread.start()
    try:
        yield
    finally:
        child.kill()
        child.wait()
        thread.join()
        bar.update(total - seen[0])
        bar.close()


@dataclass(frozen=True)
class Tracks:
    """A model's registered cameras and 3D points as tensors (float64), observations undistorted to each
    camera's pinhole (its focal length and principal point): what `bundle.adjust` takes."""

    names: list[str]  # [I] image names
    image_ids: list[int]  # [I] the model's image ids
    R: torch.Tensor  # [I, 3, 3] world -> camera
    C: torch.Tensor  # [I, 3] centres
    intrinsics: torch.Tensor  # [I, 4] fx, fy, cx, cy
    point_ids: list[int]  # [P] the model's point ids
    points: torch.Tensor  # [P, 3]
    point: torch.Tensor  # [M] index into points
    image: torch.Tensor  # [M] index into the cameras
    pixels: torch.Tensor  # [M, 2] undistorted, centres at i + 0.5


def cameras(rec) -> tuple[list[int], list[str], np.ndarray, np.ndarray, np.ndarray]:
    """(image ids, names, R [I, 3, 3] world -> camera, centres C [I, 3], pinhole intrinsics [I, 4] fx, fy, cx,
    cy) of a model's registered images, by name."""
    ids = sorted(rec.reg_image_ids(), key=lambda i: rec.images[i].name)
    R, C, K = [], [], []
    for i in ids:
        im, cam = rec.images[i], rec.images[i].camera
        R.append(im.cam_from_world().rotation.matrix())
        C.append(im.projection_center())
        K.append([cam.focal_length_x, cam.focal_length_y, cam.principal_point_x, cam.principal_point_y])
    return ids, [rec.images[i].name for i in ids], np.array(R).reshape(-1, 3, 3), \
        np.array(C).reshape(-1, 3), np.array(K, float).reshape(-1, 4)


def tracks(rec) -> Tracks:
    ids, names, R, C, K = cameras(rec)
    index = {i: k for k, i in enumerate(ids)}
    pids = sorted(rec.point3D_ids())
    pts = np.array([rec.points3D[p].xyz for p in pids]).reshape(-1, 3)
    point, image, xy = [], [], []
    for row, p in enumerate(pids):
        for el in rec.points3D[p].track.elements:
            if el.image_id in index:
                point.append(row)
                image.append(index[el.image_id])
                xy.append(rec.images[el.image_id].points2D[el.point2D_idx].xy)
    point, image, xy = (np.array(point, np.int64), np.array(image, np.int64),
                        np.array(xy, float).reshape(-1, 2))
    pixels = np.zeros_like(xy)
    for k, i in enumerate(ids):  # undistort: the camera's normalised coordinates, then its pinhole
        rows = image == k
        cam, (fx, fy, cx, cy) = rec.images[i].camera, K[k]
        uv = np.asarray(cam.cam_from_img(xy[rows]), float)[:, :2]
        pixels[rows] = np.column_stack([fx * uv[:, 0] + cx, fy * uv[:, 1] + cy])
    t = lambda a, dt=torch.float64: torch.as_tensor(np.asarray(a), dtype=dt)
    return Tracks(names, ids, t(R), t(C), t(K), pids, t(pts), t(point, torch.int64),
                  t(image, torch.int64), t(pixels))


def set_poses(rec, trk: Tracks, R: torch.Tensor, C: torch.Tensor, points: torch.Tensor,
              lens: tuple[float, float] | None = None) -> None:
    """Writes poses R [I, 3, 3], C [I, 3] and points [P, 3] (in `trk`'s order) into the model `rec`, and with
    `lens` (k1, k2) makes every camera COLMAP's RADIAL with that distortion (its focal length and principal
    point kept): what an import then undistorts the photos by."""
    import pycolmap

    if lens is not None:
        for cam in rec.cameras.values():
            f, cx, cy = cam.focal_length, cam.principal_point_x, cam.principal_point_y
            cam.model = pycolmap.CameraModelId.RADIAL
            cam.params = [f, cx, cy, float(lens[0]), float(lens[1])]

    for i, Ri, Ci in zip(trk.image_ids, R.double().numpy(), C.double().numpy()):
        rec.frames[rec.images[i].frame_id].rig_from_world = pycolmap.Rigid3d(
            pycolmap.Rotation3d(Ri), -Ri @ Ci)
    for p, xyz in zip(trk.point_ids, points.double().numpy()):
        rec.points3D[p].xyz = xyz


def control_points(rec, trk: Tracks, pixels: list[tuple[str, str, np.ndarray]]) -> dict:
    """{target name: (xyz [3] in the model's frame, NaN when its rays do not meet; [(camera index in `trk`,
    undistorted pixel [2])])} for the ground control targets seen at `pixels` [(image name, target, [u, v])]
    in the registered photos: their straight rays (the targets stand on dry ground) intersected by least
    squares, at least 2 photos at least a degree apart."""
    from ragsplat.snell import closest_points

    index = {name: k for k, name in enumerate(trk.names)}
    seen: dict[str, list] = {}
    for image, name, uv in pixels:
        k = index.get(image)
        if k is None:
            continue
        cam, (fx, fy, cx, cy) = rec.images[trk.image_ids[k]].camera, trk.intrinsics[k].tolist()
        xy = np.asarray(cam.cam_from_img(np.asarray(uv, float)[None]), float)[0, :2]
        seen.setdefault(name, []).append((k, np.array([fx * xy[0] + cx, fy * xy[1] + cy]), xy))
    names = sorted(seen)
    origins, dirs, group = [], [], []
    for g, name in enumerate(names):
        for k, _, xy in seen[name]:
            d = trk.R[k].numpy().T @ np.array([xy[0], xy[1], 1.0])
            origins.append(trk.C[k].numpy())
            dirs.append(d / np.linalg.norm(d))
            group.append(g)
    xyz = closest_points(np.array(origins).reshape(-1, 3), np.array(dirs).reshape(-1, 3),
                         np.array(group, int), len(names)) if names else np.zeros((0, 3))
    return {name: (xyz[g], [(k, uv) for k, uv, _ in seen[name]]) for g, name in enumerate(names)}
