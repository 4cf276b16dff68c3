"""A user's survey in: a COLMAP model (text or binary), its images and the water level -> a dataset directory
in the data contract (`layout`), which training reads like any other.

What the import does, once per run directory:
- reads the model with pycolmap (any number of cameras, each with its own intrinsics);
- checks the frame: metric with z up is the user's job (COLMAP's `model_aligner` with GPS or ground control,
  or shoreline points fitted to the water plane), but a frame whose cameras look up or sideways, or a camera
  at or below the water level, is refused in one line;
- shifts UTM-sized coordinates to a local origin (float32 keeps about 0.1 mm at 1 km, 3 cm at 500 km); the
  offset and the CRS go into transforms.json's "georef" and back onto every product (`ragsplat export`);
- undistorts each image once to a pinhole camera with the same focal length and principal point (the
  rasterizer is a pinhole), optionally downscaled; pixels that fall outside the source image are masked out
  of the loss, like the user's own masks (COLMAP's convention: DIR/<image name>.png, zero = ignore);
- keeps the model's 3D points (local frame, colours in [0, 1]) for the initialisation, where the trainer
  multiplies submerged depths by n (`gaussians.init_points`); `triangulate` makes them for a dataset that has
  none (a model without points, or a rendered benchmark dataset): SIFT features, matching (every pair up to
  `TRACKS_EXHAUSTIVE_MAX` views, else each view with its `NEIGHBOURS` nearest) and triangulation with the
  known poses, all pycolmap on the CPU.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ragsplat.camera import Camera
from ragsplat.dataset import layout
from ragsplat.errors import DatasetError
from ragsplat.outputs import changed, locked, write_bytes, write_json

IMPORT = "import.json"  # what was imported and how (the rerun check)
POINTS = "points3D.npy"  # [P, 6] float64: x, y, z (local frame), r, g, b in [0, 1]
LOCAL_LIMIT = 1_000.0  # metres: an axis whose cameras lie farther from 0 is shifted to a local origin
MAX_OFF_NADIR = 60.0  # degrees: a survey's mean viewing direction is closer to straight down than this


@dataclass(frozen=True)
class Imported:
    """What `import_colmap` wrote: the dataset directory and a summary for the command line."""

    root: Path
    images: int
    cameras: int
    points: int  # 3D points kept for the initialisation (0: the model has none)
    undistorted: int  # images resampled (distortion or downscaling); the others were copied as they are
    georef: layout.Georef
    reused: bool  # True: the directory already held this import


# A photo is matched with this many nearest (`neighbour_pairs`), as COLMAP's spatial matcher does (its
# default: 50), so that the pairs grow with the photos, not with their square (1 000 photos: about 20 000
# pairs instead of 499 500).
NEIGHBOURS = 30
# A dataset's tracks match every pair of its training views up to this many: every dataset the tables were
# made on keeps its tracks (the `small` reaches' 107 views, the long development stretch's 103); above it,
# each view with its NEIGHBOURS nearest by its footprint (the long reach's 321 views: 5 259 pairs instead of
# 51 360; its middle tile's 206: 3 445 instead of 21 115).
TRACKS_EXHAUSTIVE_MAX = 120


def neighbour_pairs(centres: np.ndarray, k: int = NEIGHBOURS) -> np.ndarray:
    """[P, 2] the pairs (i < j, sorted) of photos to match: each photo with its `k` nearest by the horizontal
    distance between the points `centres` [N, 3] (metres: the camera centres, or where the views' optical axes
    meet the water, `footprint`; a drone's overlap is horizontal), each pair once; every pair when there are
    k + 1 photos or fewer."""
    from scipy.spatial import cKDTree

    n = len(centres)
    if n <= k + 1:
        i, j = np.triu_indices(n, 1)
        return np.column_stack([i, j])
    _, near = cKDTree(centres[:, :2]).query(centres[:, :2], k + 1)  # [N, k + 1], itself among them
    i, j = np.repeat(np.arange(n), k + 1), near.ravel()
    pairs = np.sort(np.column_stack([i, j])[i != j], axis=1)
    return np.unique(pairs, axis=0)


def footprint(camera: Camera, water) -> np.ndarray:
    """[3] where the camera's optical axis meets the water (the surface's height under the camera): the centre
    of what it sees, obliques included; the camera centre when the axis does not descend or there is no
    water."""
    centre = camera.camera_center
    axis = camera.R[2]  # the optical axis in the world: R^T (0, 0, 1)
    if water is None or axis[2] > -1e-6:
        return centre
    level = float(water.height(centre[None, :2])[0])
    return centre + axis * (level - centre[2]) / axis[2]


def read_model(model: Path):
    """pycolmap.Reconstruction of a COLMAP model directory (cameras/images/points3D, .bin or .txt)."""
    import pycolmap

    model = Path(model)
    if not model.is_dir():
        raise DatasetError(f"{model}: COLMAP model directory does not exist")
    kinds = [k for k in (".bin", ".txt") if all((model / f"{n}{k}").is_file() for n in ("cameras", "images"))]
    if not kinds:
        nested = sorted(p.parent for p in model.glob("**/cameras.*"))
        hint = f" (found one in {nested[0]})" if nested else ""
        raise DatasetError(f"{model}: not a COLMAP model (no cameras.bin/.txt and images.bin/.txt){hint}")
    rec = pycolmap.Reconstruction()
    try:
        (rec.read_binary if kinds[0] == ".bin" else rec.read_text)(str(model))
    except (RuntimeError, ValueError) as err:  # pycolmap reports a broken file as a RuntimeError
        raise DatasetError(f"{model}: not a readable COLMAP model "
                           f"({str(err).splitlines()[0] if str(err) else err})") \
            from None
    if not rec.num_reg_images():
        raise DatasetError(f"{model}: the model has no registered images")
    return rec


def _digest(paths: list[Path]) -> str:
    h = hashlib.sha256()
    for p in paths:
        h.update(p.name.encode() + b"\0" + p.read_bytes())
    return h.hexdigest()[:16]


def _offset(centres: np.ndarray) -> tuple[float, float, float]:
    """Per axis: the cameras' mean in whole metres where they lie beyond `LOCAL_LIMIT`, else 0."""
    big = np.abs(centres).max(0) > LOCAL_LIMIT
    return tuple(float(np.round(m)) if b else 0.0 for m, b in zip(centres.mean(0), big))


def _check_frame(names: list[str], centres: np.ndarray, axes: np.ndarray, water, model: Path) -> None:
    """One line for a frame that cannot be a z-up survey over `water` (centres, axes: [V, 3])."""
    mean = axes.mean(0)
    off_nadir = np.degrees(np.arccos(np.clip(-mean[2] / max(np.linalg.norm(mean), 1e-12), -1, 1)))
    if mean[2] > 0 and off_nadir > 90 + MAX_OFF_NADIR / 2:
        raise DatasetError(f"{model}: the cameras look up (mean viewing direction {off_nadir:.0f} deg from "
                           "straight down): the model is upside down; align it so z points up (colmap "
                           "model_aligner)")
    if off_nadir > MAX_OFF_NADIR:
        raise DatasetError(f"{model}: the cameras look {off_nadir:.0f} deg away from straight down on "
                           "average: the model's z axis is not up; align it metric with z up (colmap "
                           "model_aligner)")
    low = int(np.argmax(water.depth(centres)))
    if not water.depth(centres[low]) < 0:
        raise DatasetError(f"{model}: camera {names[low]} is at z = {centres[low, 2]:.4g}, not above the "
                           f"water surface ({float(water.height(centres[low, :2])):g} there); give the water "
                           "in the model's frame (metric, z up)")


def _mask_file(masks: Path, name: str) -> Path:
    """COLMAP's convention DIR/<image name>.png, else DIR/<image stem>.png."""
    for path in (masks / f"{name}.png", (masks / name).with_suffix(".png")):
        if path.is_file():
            return path
    raise DatasetError(f"{masks}: no mask for image {name} (expected {masks / name}.png)")


def _pinhole(cam, scale: float) -> tuple[int, int, float, float, float, float]:
    """(w, h, fx, fy, cx, cy) of the undistorted camera: the model's focal length and principal point, the
    image scaled by `scale` (pixel centres at i + 0.5 scale with the image)."""
    fx, fy = cam.focal_length_x, cam.focal_length_y
    w, h = round(cam.width * scale), round(cam.height * scale)
    sx, sy = w / cam.width, h / cam.height
    return w, h, fx * sx, fy * sy, cam.principal_point_x * sx, cam.principal_point_y * sy


def _undistort_maps(cam) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps [H, W] float32 from the pinhole image (same size, focal length, principal point) to
    the source image: OpenCV indexes pixel centres at i, COLMAP at i + 0.5."""
    w, h = cam.width, cam.height
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.stack([(u - cam.principal_point_x) / cam.focal_length_x,
                     (v - cam.principal_point_y) / cam.focal_length_y, np.ones_like(u)], -1).reshape(-1, 3)
    src = np.asarray(cam.img_from_cam(rays), dtype=np.float64).reshape(h, w, 2) - 0.5
    return src[..., 0].astype(np.float32), src[..., 1].astype(np.float32)


def _resample(image: np.ndarray, used: np.ndarray, maps,
              size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Undistort (maps, or None) then downscale to `size` (area average). `used`: [H, W] bool of the source;
    a target pixel stays used only if every source pixel under it was used and inside the image."""
    import cv2

    valid = used.astype(np.float32)
    if maps is not None:  # Lanczos: the photos' one resampling keeps their detail (bilinear cost a survey
        # through a barrel lens at 1 % of depth, docs/survey.md); its 8 x 8 support reads
        # the image reflected beyond its edge, not black (`valid` masks what lies outside)
        image = cv2.remap(image, *maps, cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REFLECT_101)
        valid = cv2.remap(valid, *maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if size != (image.shape[1], image.shape[0]):
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        valid = cv2.resize(valid, size, interpolation=cv2.INTER_AREA)
    return image, valid > 1 - 1e-4


def import_colmap(model: Path, images: Path, out: Path, water, masks: Path | None = None,
                  crs: str = layout.LOCAL_CRS, max_size: int | None = None) -> Imported:
    """Write the dataset directory `out` from a COLMAP model, its image folder and the water (`WaterSurface`,
    flat or sloping, in the model's frame, metres, z up). Splits from the model folder's train.txt / test.txt
    when present (image names, one per line), else every image trains. A second call with the same inputs
    reuses `out`; other inputs are refused. Raises DatasetError (model, images, frame), ConfigError (CRS)."""
    model, images, out = Path(model), Path(images), Path(out)
    sources = sorted(p for p in model.iterdir() if p.is_file()) if model.is_dir() else []
    # the model by its content, not its path: a run folder moved or copied (its tiles' models with it)
    # resumes
    key = {"model_digest": _digest(sources), "images": str(images.resolve()),
           **layout.water_json(water), "masks": None if masks is None else str(Path(masks).resolve()),
           "crs": crs, "max_size": max_size}
    if (out / IMPORT).is_file():
        return _reuse(out, key)
    rec = read_model(model)
    regs = _registered(rec, images)
    names = [im.name for im in regs]
    centres = np.stack([im.projection_center() for im in regs])  # [V, 3]
    axes = np.stack([im.viewing_direction() for im in regs])  # [V, 3] unit optical axes
    _check_frame(names, centres, axes, water, model)
    georef = layout.Georef(_offset(centres), crs)
    shift = np.asarray(georef.offset)
    splits = _splits(model, names)

    frames, first, maps, resampled = [], None, {}, 0
    for im in regs:
        view = _import_view(rec, im, model, images, out, None if masks is None else Path(masks), max_size,
                            shift, maps)
        resampled += view.resampled
        c = view.camera
        first = first or c
        entry = layout.frame(im.name, c, splits[im.name], "survey", view.image, mask_path=view.mask)
        frames.append({**entry, "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width,
                       "h": c.height})
    local = water.shifted(georef.offset)
    write_json(out / layout.TRANSFORMS, layout.transforms_json(first, frames, local, georef), indent=1)

    pts = _points(rec, shift)
    if len(pts):
        layout.write_npy(out / POINTS, pts)
    cameras = len({im.camera_id for im in regs})
    summary = {"images": len(regs), "cameras": cameras, "points": len(pts), "undistorted": resampled,
               "georef": georef.to_json()}
    write_json(out / IMPORT, {"key": key, **summary}, indent=1)  # last: marks the import complete
    return Imported(out, len(regs), cameras, len(pts), resampled, georef, False)


def _reuse(out: Path, key: dict) -> Imported:
    """The import already in `out`, where it was made from the inputs `key`; DatasetError naming what
    changed where it was not."""
    done = json.loads((out / IMPORT).read_text())
    old = done.get("key", {})
    stale = changed({k: old.get(k) for k in key}, key)  # an older import's other entries ("model"): unread
    if stale:
        raise DatasetError(f"{out} holds an import of other inputs ({', '.join(stale)} changed); use "
                           "another --out")
    return Imported(out, done["images"], done["cameras"], done["points"], done["undistorted"],
                    layout.Georef(tuple(done["georef"]["offset"]), done["georef"]["crs"]), True)


def _registered(rec, images: Path) -> list:
    """The model's registered images by name; DatasetError unless each is in the folder `images`."""
    if not images.is_dir():
        raise DatasetError(f"{images}: image directory does not exist")
    regs = sorted((rec.images[i] for i in rec.reg_image_ids()), key=lambda im: im.name)
    names = [im.name for im in regs]
    missing = [nm for nm in names if not (images / nm).is_file()]
    if missing:
        raise DatasetError(f"{images}: {len(missing)} of the model's {len(names)} images are missing, e.g. "
                           f"{missing[0]}")
    return regs


@dataclass(frozen=True)
class _View:
    """One imported image: its pinhole camera in the local frame, and its files in the dataset."""

    camera: Camera
    image: str  # relative to the dataset
    mask: str | None  # relative to the dataset; None: every pixel is used
    resampled: bool  # undistorted or downscaled (else copied as it is)


def _import_view(rec, im, model: Path, images: Path, out: Path, masks: Path | None, max_size: int | None,
                 shift: np.ndarray, maps: dict) -> _View:
    """The image `im` of the model into `out`: its pinhole camera (scaled to `max_size`, posed in the frame
    shifted by `shift`), the photo copied where it is that camera's already, else resampled
    (`_write_resampled`; `maps` caches each camera's undistortion)."""
    cam = rec.cameras[im.camera_id]
    if not cam.is_perspective():
        raise DatasetError(f"{model}: camera {im.camera_id} ({cam.model.name}) is not a perspective camera")
    longest = max(cam.width, cam.height)
    scale = min(1.0, max_size / longest) if max_size else 1.0
    w, h, fx, fy, cx, cy = _pinhole(cam, scale)
    pose = im.cam_from_world()
    R = np.asarray(pose.rotation.matrix(), dtype=np.float64)
    t = np.asarray(pose.translation, dtype=np.float64) + R @ shift  # x_cam = R (x_local + shift) + t
    camera = Camera(w, h, fx, fy, cx, cy, R, t)
    distorted = not cam.is_undistorted()
    mask_src = None if masks is None else _mask_file(masks, im.name)
    if not distorted and scale == 1.0 and mask_src is None:
        rel = f"images/wet/{im.name}"
        dst = out / rel  # a pinhole image at its size is used as it is
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(images / im.name, dst)
        return _View(camera, rel, None, False)
    rel, mask_rel = _write_resampled(cam, im, images, mask_src, maps if distorted else None, (w, h), out)
    return _View(camera, rel, mask_rel, True)


def _write_resampled(cam, im, images: Path, mask_src: Path | None, maps: dict | None, size: tuple[int, int],
                     out: Path) -> tuple[str, str | None]:
    """The photo of `im` in `images` (and its mask) undistorted to the pinhole (`maps`: each camera's
    undistortion, made here where missing; None: not distorted) and scaled to `size` (`_resample`), written
    as PNG in `out`, with a mask where some pixels are not to be used: (the image's path, the mask's or
    None), relative to `out`."""
    import cv2

    source = images / im.name
    img = cv2.imread(str(source), cv2.IMREAD_COLOR)
    if img is None or (img.shape[1], img.shape[0]) != (cam.width, cam.height):
        raise DatasetError(f"{source}: " + ("not a readable image" if img is None else
                    f"{img.shape[1]} x {img.shape[0]}, the model's camera is {cam.width} x {cam.height}"))
    used = np.ones(img.shape[:2], bool)
    if mask_src is not None:
        m = cv2.imread(str(mask_src), cv2.IMREAD_GRAYSCALE)
        if m is None or m.shape != used.shape:
            raise DatasetError(f"{mask_src}: " + ("not a readable image" if m is None else
                        f"mask is {m.shape[1]} x {m.shape[0]}, the image {cam.width} x {cam.height}"))
        used = m > 0
    if maps is not None and im.camera_id not in maps:
        maps[im.camera_id] = _undistort_maps(cam)
    img, used = _resample(img, used, None if maps is None else maps[im.camera_id], size)
    rel = str(Path(f"images/wet/{im.name}").with_suffix(".png"))
    _write(out / rel, img)
    mask_rel = None
    if not used.all():
        mask_rel = f"masks/{im.name}.png"
        _write(out / mask_rel, used.astype(np.uint8) * 255)
    return rel, mask_rel


def _write(path: Path, image: np.ndarray) -> None:
    import cv2

    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise DatasetError(f"{path}: could not encode the image")
    write_bytes(path, data.tobytes())


def _splits(model: Path, names: list[str]) -> dict[str, str]:
    """image name -> "train" | "test": the model folder's test.txt names the held-out images (our datasets
    write train.txt / test.txt there), else every image trains."""
    listed = model / "test.txt"
    held = set(listed.read_text().split()) if listed.is_file() else set()
    return {nm: "test" if nm in held else "train" for nm in names}


def _points(rec, shift: np.ndarray) -> np.ndarray:  # [P, 6]: the model's 3D points, local frame, colour
    if not rec.num_points3D():
        return np.zeros((0, 6))
    pts = [rec.points3D[i] for i in sorted(rec.point3D_ids())]  # by id: the model's own order
    xyz = np.stack([p.xyz for p in pts]) - shift
    rgb = np.stack([p.color for p in pts]).astype(np.float64) / 255.0
    return np.concatenate([xyz, rgb], 1)


def triangulate(root: Path, work: Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(points [P, 6] (x, y, z, r, g, b in [0, 1]), observations [M, 4] (point index, image index, pixel x,
    pixel y; centres at i + 0.5), image names) triangulated from the training images of the dataset `root`
    with its known cameras: pycolmap SIFT, matching (every pair up to `TRACKS_EXHAUSTIVE_MAX` views, else the
    `neighbour_pairs` of their footprints), `triangulate_points` (poses and intrinsics fixed). Points under
    water come out at their apparent depths, as in any photogrammetry through the water; the observations let
    `refracted_points` intersect the same tracks through it. `work` holds the feature database (kept: a rerun
    reuses nothing, it is a scratch folder). Raises DatasetError when nothing can be triangulated (no texture,
    no overlap)."""
    import pycolmap

    from ragsplat.dataset.load import load_dataset

    ds = load_dataset(root, splits=("train",), load_dry=False)
    views = ds.train
    work = Path(work)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    pycolmap.logging.minloglevel = int(pycolmap.logging.Level.ERROR.value)  # no progress chatter, errors only
    # One thread and a fixed seed: with COLMAP's default threads the same images gave different point counts.
    # Still not bit-reproducible from one process to the next: the approximate matcher and the verification's
    # RANSAC (its random_seed -1) draw their own, and a few runs in six differ by a few points
    # (OMP_NUM_THREADS=1 did not help).
    # The result is cached per dataset, so the rows of one dataset share one set of tracks.
    pycolmap.set_random_seed(0)
    extraction, matching = pycolmap.FeatureExtractionOptions(), pycolmap.FeatureMatchingOptions()
    extraction.num_threads = matching.num_threads = 1
    pipeline = pycolmap.IncrementalPipelineOptions()
    pipeline.num_threads, pipeline.random_seed = 1, 0
    db = work / "database.db"
    groups: dict[int, list[str]] = {}  # camera id -> the images it took
    with pycolmap.Database.open(db) as d:  # cameras first, with our ids and intrinsics
        ids: dict[tuple, int] = {}
        for v in views:
            c = v.camera
            key = (c.width, c.height, c.fx, c.fy, c.cx, c.cy)
            if key not in ids:
                cam = pycolmap.Camera.create_from_model_name(len(ids) + 1, "PINHOLE", c.fx, c.width, c.height)
                cam.params = [c.fx, c.fy, c.cx, c.cy]
                ids[key] = cam.camera_id
                d.write_camera(cam, use_camera_id=True)
            groups.setdefault(ids[key], []).append(v.file_path)
    reader = pycolmap.ImageReaderOptions()
    for cam_id, group in groups.items():
        reader.existing_camera_id = cam_id
        pycolmap.extract_features(db, root, group, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction,
                                  device=pycolmap.Device.cpu)
    if len(views) <= TRACKS_EXHAUSTIVE_MAX:
        pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    else:
        pairs = neighbour_pairs(np.stack([footprint(v.camera, ds.water) for v in views]))
        listed = work / "pairs.txt"
        listed.write_text("".join(f"{views[i].file_path} {views[j].file_path}\n" for i, j in pairs))
        pycolmap.match_image_pairs(db, matching_options=matching, device=pycolmap.Device.cpu,
                                   pairing_options=pycolmap.ImportedPairingOptions(match_list_path=str(listed)))
    with pycolmap.Database.open(db) as d:
        cams, images = d.read_all_cameras(), d.read_all_images()
    rec = pycolmap.Reconstruction()
    for cam in cams:
        rec.add_camera_with_trivial_rig(cam)
    names = {v.file_path: v for v in views}
    for im in images:
        v = names[im.name]
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=im.name, camera_id=im.camera_id, image_id=im.image_id),
                                         pycolmap.Rigid3d(pycolmap.Rotation3d(v.camera.R), v.camera.t))
    (work / "model").mkdir()
    rec = pycolmap.triangulate_points(rec, db, root, work / "model", options=pipeline,
                                      refine_intrinsics=False)
    pts = _points(rec, np.zeros(3))
    if not len(pts):
        raise DatasetError(f"{root}: no point could be triangulated from the training images (no texture or "
                           "overlap?)")
    names = sorted(rec.images[i].name for i in rec.reg_image_ids())
    index = {name: k for k, name in enumerate(names)}
    obs = [(row, index[rec.images[el.image_id].name], *rec.images[el.image_id].points2D[el.point2D_idx].xy)
           for row, pid in enumerate(sorted(rec.point3D_ids())) for el in rec.points3D[pid].track.elements]
    return pts, np.asarray(obs, dtype=np.float64), names


TRIANGULATED = "colmap/triangulated.npy"  # a dataset's cached `triangulate` result
TRACKS = "colmap/tracks.npy"  # its observations [M, 4]
STAMP = "colmap/triangulated.json"  # their key (the dataset's fingerprint), point count and image names


def triangulated_points(root: Path, fingerprint: str) -> Path:
    """The dataset's triangulated points as a .npy file [P, 6] (`triangulate`), computed once per dataset
    content (`fingerprint`) and cached inside it with their observations (`TRACKS`): a derived product, like
    COLMAP's own database, that every run on the dataset shares. Made under a lock in the dataset: two
    processes that need it at once (two rows of `ragsplat ablation --jobs 2`) do not both run pycolmap in
    the same folder (which crashed one of them inside SQLite); the second waits and reads the first's."""
    path, work, tracks = (Path(root) / TRIANGULATED, Path(root) / "colmap" / "triangulation",
                          Path(root) / TRACKS)
    stamp = Path(root) / STAMP

    def cached() -> bool:
        return path.is_file() and tracks.is_file() and stamp.is_file() \
            and json.loads(stamp.read_text()).get("fingerprint") == fingerprint

    if cached():
        return path
    with locked(Path(root) / "colmap" / ".lock"):
        if cached():  # made by the process that held the lock
            return path
        pts, obs, names = triangulate(root, work)
        layout.write_npy(path, pts)
        layout.write_npy(tracks, obs)
        write_json(stamp, {"fingerprint": fingerprint, "points": len(pts), "images": names})  # last: the mark
    return path


def refracted_points(root: Path, fingerprint: str, cameras: dict, water, robust: bool = False) -> np.ndarray:
    """[P', 6] the dataset's triangulated tracks intersected through the water instead of along straight rays:
    each observation's ray is bent at the plane (`snell.water_rays`) and the point is the least-squares
    intersection of its track's rays in the water (`snell.closest_points`; `robust`: weighted by the rays'
    angles and robust to strays, `snell.robust_closest_points`). A straight-ray point at or above the level
    is on dry ground and kept as it is (refraction only lifts submerged points); a submerged track whose rays
    span less than 1 degree is dropped. `cameras`: image name -> Camera.

    Why: the field's depth x n is exact only at nadir; with oblique views through 2-3 m of water the points
    x n come out too high (development reach: median +33 cm where the bed is 2-4 m deep, +4 cm under 1 m;
    these: under 1 cm), and training does not pull a bed that far down."""
    from ragsplat.snell import closest_points, robust_closest_points, water_rays

    path = triangulated_points(root, fingerprint)
    pts = np.load(path)
    obs = np.load(Path(root) / TRACKS)
    names = json.loads((Path(root) / STAMP).read_text())["images"]
    point, image = obs[:, 0].astype(np.int64), obs[:, 1].astype(np.int64)
    origins, dirs = np.zeros((len(obs), 3)), np.zeros((len(obs), 3))
    for k, name in enumerate(names):
        rows = image == k
        origins[rows], dirs[rows] = water_rays(cameras[name], obs[rows, 2:], water)
    wet = water.depth(pts[:, :3]) > 0
    use = wet[point] & np.isfinite(origins).all(1)
    xyz = (robust_closest_points(origins[use], dirs[use], point[use], len(pts))[0] if robust
           else closest_points(origins[use], dirs[use], point[use], len(pts)))
    out = pts.copy()
    out[wet, :3] = xyz[wet]
    return out[np.isfinite(out).all(1)]
