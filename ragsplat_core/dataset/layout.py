"""The dataset directory: paths, file formats and the builders of its two JSON files (the data contract).

DIR/
  transforms.json            nerfstudio-readable cameras + frames (`transforms_json`, `frame`)
  scene.json                 the generator's spec, eval_region, null-model scores and figures (`scene_json`)
  images/wet/NNNN.png        with-water render (8-bit sRGB): the training input (absent for a dry scene)
  images/dry/NNNN.png        the same pose without water
  masks/NAME.png             optional (an imported survey): zero where a pixel is left out of the loss
  gt/depth/NNNN.exr          dry z-depth in metres along the optical axis: one float32 channel "Y" (the
                             name OpenCV reads as grey), pixel centres exact (pixel filter 0.01 px); 1e10
                             where no surface was hit
  gt/bed.ply                 the exact bed mesh (double vertices, world metres)
  gt/bed_surface.npz         the same surface as a height grid (`Surface`): the exact height function
  gt/bed_grid.npy            float64 [N, 3] submerged bed points on a 5 cm horizontal grid over eval_region
  gt/bank_grid.npy           the same for the emerged ground (banks, bars) over eval_region (a reach)
  gt/bed_elevation.tif       bed_grid as a GeoTIFF raster: local metric CRS, nodata outside the wet area
  gt/waterline.json          GeoJSON MultiLineString where the bed meets the water plane (a reach)
  gt/ortho_dry.png           the scene without the water seen straight down (Cycles' orthographic camera) over
                             eval_region, GT_GRID_STEP a pixel, pixel centres on its multiples; its world file
                             gt/ortho_dry.pgw (local metres); outside the manifest and the fingerprint
  colmap/                    COLMAP text model: cameras.txt (one PINHOLE), images.txt, empty points3D.txt,
                             and the split as image lists train.txt and test.txt
  manifest.json              size and sha256 of every rendered image and depth file (`file_digest`)
  scene/                     generator inputs and state: spec.json, geometry.npz, albedo.png, render log

Every writer of a dataset (the Blender generator in `datagen`, the small in-memory scenes of
`ragsplat.bench.synthetic`) writes through this module (its GeoTIFFs and world files through
`dataset.rasters`, a survey's photos through `dataset.photos`) and every reader reads through
`ragsplat.dataset.load`. numpy and OpenCV only, no torch: Blender's process imports it.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ragsplat.errors import ConfigError, DatasetError
from ragsplat.outputs import atomic_path, write_bytes, write_json

TRANSFORMS = "transforms.json"
SCENE = "scene.json"
MANIFEST = "manifest.json"
GT_MESH = "gt/bed.ply"
GT_SURFACE = "gt/bed_surface.npz"
GT_GRID = "gt/bed_grid.npy"
GT_BANKS = "gt/bank_grid.npy"
GT_ELEVATION = "gt/bed_elevation.tif"
GT_WATERLINE = "gt/waterline.json"
# field conditions: the rendered ground control targets' centres [T, 3], exact
GT_TARGETS = "gt/gcp_targets.npy"
GT_GRID_STEP = 0.05  # metres between ground-truth grid points
GT_ORTHO = "gt/ortho_dry.png"
GT_ORTHO_WORLD = "gt/ortho_dry.pgw"
# Not colmap/sparse/0: nerfstudio's loader finds a model there and stops at an interactive question.
COLMAP = "colmap"
PASSES = ("wet", "dry", "depth")
DEPTH_CHANNEL = "Y"  # a single channel named "Y" is what OpenCV reads back as a grey float image
NO_HIT = 1e10  # Cycles' depth where a ray escapes; far beyond any scene distance
# The dataset's own local frame, for rasters: metres, x east, y north (no geodetic datum).
LOCAL_CRS = ('LOCAL_CS["ragsplat scene (local metres, z up)",LOCAL_DATUM["scene origin",0],UNIT["metre",1],'
             'AXIS["X",EAST],AXIS["Y",NORTH]]')
NODATA = -9999.0  # raster cells without a value
# What a surveyor hands over, beside a rendered dataset (`ragsplat.datagen.survey`) or from the field: the
# photos as the drone writes them (JPEG with the focal length in EXIF), the camera centres as its RTK receiver
# records them and the water level; no poses. `ragsplat survey` reads only these.
SURVEY_IMAGES = "survey/images"  # with EXIF GPS and DJI-style XMP: the positions.csv centres, RTK fixed
SURVEY_IMAGES_GPS = "survey/images-gps"  # the same photos geotagged by consumer GPS (metres, no RTK flag)
SURVEY_IMAGES_LENS = "survey/images-lens"  # the RTK-tagged photos through a lens with radial distortion
SURVEY_POSITIONS = "survey/positions.csv"  # header name,x,y,z: image file name, metres, z up
SURVEY_LEVEL = "survey/water_level.txt"  # one number: the water surface height, same frame
SURVEY_EDGE = "survey/water_edge.csv"  # header x,y,z: points on the water's edge along both banks, same frame
SURVEY_GCP = "survey/gcp.csv"  # header name,x,y,z: ground control points as surveyed, same frame
SURVEY_GCP_PIXELS = "survey/gcp_pixels.csv"  # header image,name,u,v: where each target is in each photo
SURVEY_RECORD = "survey/survey.json"  # how a synthetic survey was made (seed, noise), for the evaluation only


@dataclass(frozen=True)
class Georef:
    """The dataset frame -> a CRS: absolute = local + offset (x0, y0, z0), in `crs` (EPSG:32633, WKT...).

    transforms.json's "georef" (an imported survey; a rendered scene has none: zero offset, `LOCAL_CRS`).
    Coordinates are stored shifted so float32 training keeps millimetres at UTM-sized values."""

    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    crs: str = LOCAL_CRS

    def __post_init__(self):
        # an unusable CRS is refused before any work; the local one is this module's own text, so a rendered
        # scene loads where rasterio is not installed
        if self.crs != LOCAL_CRS:
            self.wkt()

    def wkt(self) -> str:
        from rasterio.crs import CRS  # only here: Blender's process imports this module
        from rasterio.errors import CRSError

        try:
            return CRS.from_user_input(self.crs).to_wkt()
        except CRSError as err:
            raise ConfigError(f"CRS {self.crs!r} is not usable: {err}") from None

    def to_json(self) -> dict:
        return {"offset": [float(x) for x in self.offset], "crs": self.crs}


def relative_path(kind: str, name: str) -> str:
    """Where pass `kind` ("wet" | "dry" | "depth", or "lens": the survey's photo through a lens) of view
    `name` lives, relative to the dataset root."""
    return f"gt/depth/{name}.exr" if kind == "depth" else f"images/{kind}/{name}.png"


def output_path(root: Path, kind: str, name: str) -> Path:
    return Path(root) / relative_path(kind, name)


# ---------------------------------------------------------------- file formats


def write_npy(path: Path, array: np.ndarray) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, array)


def write_ply(path: Path, verts: np.ndarray, tris: np.ndarray | None = None, comment: str = "") -> None:
    """Binary little-endian PLY of vertices [N, 3] as doubles (exact, also at UTM-sized coordinates) and,
    when given, triangles [F, 3] as int32 vertex lists. (Trained Gaussians: `ragsplat.ply`.)"""
    header = "ply\nformat binary_little_endian 1.0\n" + (f"comment {comment}\n" if comment else "")
    header += f"element vertex {len(verts)}\nproperty double x\nproperty double y\nproperty double z\n"
    if tris is not None:
        header += f"element face {len(tris)}\nproperty list uchar int vertex_indices\n"
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write((header + "end_header\n").encode("ascii"))
        f.write(np.ascontiguousarray(verts, dtype="<f8").tobytes())
        if tris is not None:
            face = np.empty(len(tris), dtype=[("n", "u1"), ("v", "<i4", (3,))])
            face["n"], face["v"] = 3, tris
            f.write(face.tobytes())


def write_depth(path: Path, depth: np.ndarray) -> None:
    """z-depth [H, W] (row 0 at the top) -> single-channel float32 EXR, written atomically."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    channels = {DEPTH_CHANNEL: np.ascontiguousarray(depth, dtype=np.float32)}
    with atomic_path(path) as tmp, OpenEXR.File(header, channels) as f:
        f.write(str(tmp))


def depth_tiff(root: Path, name: str) -> Path:
    """The float32 TIFF twin of view `name`'s depth EXR: every image library reads a float TIFF, while OpenCV
    reads EXR only with an environment variable set (and, as reported, 5.0's wheels not at all)."""
    return output_path(root, "depth", name).with_suffix(".tif")


def write_depth_tiff(path: Path, depth: np.ndarray) -> None:
    """z-depth [H, W] -> single-band float32 TIFF (deflate), written atomically."""
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(np.ascontiguousarray(depth, dtype=np.float32)).save(tmp, format="TIFF",
                                                                           compression="tiff_adobe_deflate")


def read_depth(path) -> np.ndarray:
    """z-depth [H, W] float32 (metres, row 0 at the top; NO_HIT where the ray escaped)."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        channels = f.channels()
        name = next((c for c in (DEPTH_CHANNEL, "Z") if c in channels), None)  # "Z": older datasets
        if name is None:
            raise ValueError(f"{path}: no channel {DEPTH_CHANNEL!r} (has {sorted(channels)})")
        return np.array(channels[name].pixels, dtype=np.float32)


def read_png(path: Path) -> np.ndarray:
    """An 8-bit RGB(A) or grey PNG -> [H, W, 3] uint8 RGB (alpha dropped). Raises ValueError."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: not a readable image")
    if img.dtype != np.uint8:
        raise ValueError(f"{path}: expected an 8-bit image, got {img.dtype}")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    elif img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    else:
        raise ValueError(f"{path}: unsupported channel count {img.shape[2]}")
    return np.ascontiguousarray(img)


def write_positions(path: Path, names: list[str], xyz: np.ndarray) -> None:
    """`name,x,y,z` CSV (metres, millimetre precision) of camera centres or ground control points."""
    rows = "".join(f"{n},{x:.4f},{y:.4f},{z:.4f}\n" for n, (x, y, z) in zip(names, np.asarray(xyz, float)))
    write_bytes(path, ("name,x,y,z\n" + rows).encode())


def _read_csv(path: Path, columns: str) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """(header, [(line number, cells)]) of a CSV whose header (its first non-blank line) holds every one of
    `columns` ("a,b,c", any order); blank lines are skipped, line numbers are the file's. Raises
    DatasetError."""
    import csv

    try:
        with open(path, newline="") as f:
            lines = [(k, cells) for k, cells in enumerate(csv.reader(f), start=1)
                     if any(c.strip() for c in cells)]
    except OSError as err:
        raise DatasetError(f"{path}: {err.strerror}") from None
    header = [h.strip() for h in lines[0][1]] if lines else []
    if not set(columns.split(",")) <= set(header):
        raise DatasetError(f"{path}: expected the header {columns}, got {','.join(header) or 'nothing'}")
    return header, lines[1:]


def read_positions(path: Path) -> dict[str, np.ndarray]:
    """{name: [3]} from a `name,x,y,z` CSV (header required, any column order). Raises DatasetError."""
    path = Path(path)
    header, lines = _read_csv(path, "name,x,y,z")
    out = {}
    for k, cells in lines:
        row = dict(zip(header, (c.strip() for c in cells)))
        if len(cells) != len(header):
            raise DatasetError(f"{path}:{k}: {len(cells)} values for the {len(header)} columns of the header")
        try:
            xyz = np.array([float(row[c]) for c in "xyz"])
        except ValueError:
            raise DatasetError(f"{path}:{k}: x, y, z must be numbers, got {row['x']}, {row['y']}, "
                               f"{row['z']}") from None
        if not np.isfinite(xyz).all() or not row["name"]:
            raise DatasetError(f"{path}:{k}: a name and three finite numbers are needed")
        if row["name"] in out:
            raise DatasetError(f"{path}:{k}: {row['name']} appears twice")
        out[row["name"]] = xyz
    if not out:
        raise DatasetError(f"{path}: no rows")
    return out


def read_points(path: Path) -> np.ndarray:
    """[K, 3] from an `x,y,z` CSV (header required, any column order; other columns ignored), e.g. the water's
    edge as a surveyor measured it. Raises DatasetError."""
    path = Path(path)
    header, lines = _read_csv(path, "x,y,z")
    out = []
    for k, cells in lines:
        row = dict(zip(header, (c.strip() for c in cells)))
        try:
            out.append([float(row[c]) for c in "xyz"])
        except (KeyError, ValueError):
            raise DatasetError(f"{path}:{k}: x, y, z must be three numbers") from None
    pts = np.array(out, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(pts).all():
        raise DatasetError(f"{path}: every x, y, z must be finite")
    return pts


def write_points(path: Path, points: np.ndarray) -> None:
    """An `x,y,z` CSV of points [K, 3] (millimetres), as `read_points` reads it."""
    write_bytes(path, ("x,y,z\n" + "".join(f"{x:.3f},{y:.3f},{z:.4f}\n" for x, y, z in points)).encode())


def write_gcp_pixels(path: Path, rows: list[tuple[str, str, float, float]]) -> None:
    """`image,name,u,v` CSV: ground control point `name` seen in photo `image` at pixel (u, v) (column, row;
    the image's top-left corner at (0, 0), so the first pixel's centre is at (0.5, 0.5))."""
    body = "".join(f"{image},{name},{u:.3f},{v:.3f}\n" for image, name, u, v in rows)
    write_bytes(path, ("image,name,u,v\n" + body).encode())


def read_gcp_pixels(path: Path) -> list[tuple[str, str, np.ndarray]]:
    """[(image, name, [u, v])] from an `image,name,u,v` CSV (header required). Raises DatasetError."""
    path = Path(path)
    header, lines = _read_csv(path, "image,name,u,v")
    out = []
    for k, cells in lines:
        row = dict(zip(header, (c.strip() for c in cells)))
        try:
            uv = np.array([float(row["u"]), float(row["v"])])
        except (KeyError, ValueError):
            raise DatasetError(f"{path}:{k}: u and v must be numbers") from None
        out.append((row["image"], row["name"], uv))
    if not out:
        raise DatasetError(f"{path}: no rows")
    return out


def write_png(path: Path, image) -> None:
    """[H, W, 3] RGB, float in [0, 1] (rounded to nearest) or uint8; numpy or a CPU/GPU tensor."""
    import cv2

    if hasattr(image, "detach"):  # a torch tensor, without importing torch here
        image = image.detach().cpu().numpy()
    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        arr = (np.clip(arr, 0, 1) * 255 + 0.5).astype(np.uint8)
    ok, png = cv2.imencode(".png", cv2.cvtColor(arr, cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(f"{path}: could not encode PNG")
    write_bytes(path, png.tobytes())


class Surface:
    """The exact bed: heights on a square vertex grid, each cell split along the same diagonal into
    (00, 10, 11) and (00, 11, 01), so the height between vertices is the triangulated mesh's (`gt/bed.ply`).

    x0: world x (= y) of vertex 0; cell: vertex spacing (m); heights [K, K] world z, index [j (y), i (x)].
    """

    def __init__(self, x0: float, cell: float, heights: np.ndarray):
        self.x0, self.cell, self.heights = float(x0), float(cell), np.asarray(heights, np.float64)

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """Exact height [N] at horizontal points [N, 2] (clamped to the mesh's edge cells outside it)."""
        h = self.heights
        fx, fy = (np.asarray(xy, float) - self.x0).T / self.cell
        i = np.clip(np.floor(fx).astype(int), 0, h.shape[1] - 2)
        j = np.clip(np.floor(fy).astype(int), 0, h.shape[0] - 2)
        s, t = fx - i, fy - j
        h00, h10, h01, h11 = h[j, i], h[j, i + 1], h[j + 1, i], h[j + 1, i + 1]
        lower = s >= t  # triangle (00, 10, 11)
        return np.where(lower, h00 + s * (h10 - h00) + t * (h11 - h10),
                        h00 + t * (h01 - h00) + s * (h11 - h01))

    def save(self, path: Path) -> None:
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez(f, x0=self.x0, cell=self.cell, heights=self.heights)

    @classmethod
    def load(cls, path: Path) -> Surface:
        with np.load(path) as d:
            return cls(float(d["x0"]), float(d["cell"]), d["heights"])


def write_waterline(path: Path, lines: list[np.ndarray], level: float) -> None:
    """Polylines [K, 2] ([K, 3] under a sloping surface: the height too) where the bed crosses the water
    surface, as a GeoJSON MultiLineString (local metres)."""
    write_json(path, {"type": "Feature",
                      "properties": {"level": level, "crs": "local metres (see LOCAL_CRS)"},
                      "geometry": {"type": "MultiLineString",
                                   "coordinates": [np.round(line, 6).tolist() for line in lines]}})


def file_digest(path: Path) -> list:
    """[size in bytes, sha256 hex] of a file, the manifest's entry."""
    data = Path(path).read_bytes()
    return [len(data), hashlib.sha256(data).hexdigest()]


def intact(path: Path, expected: list | None = None) -> bool:
    """Whether a rendered file is whole: its manifest entry matches when there is one, else it decodes."""
    path = Path(path)
    if not path.is_file():
        return False
    if expected is not None:
        return file_digest(path) == list(expected)
    try:
        if path.suffix == ".exr":
            read_depth(path)
        else:
            read_png(path)
    except Exception:  # noqa: BLE001 (any decoder failure means damaged; OpenEXR and OpenCV raise many kinds)
        return False
    return True


# ---------------------------------------------------------------- transforms.json and scene.json


def fingerprint(root: Path) -> str:
    """Identifies a dataset by its content: sha256 over transforms.json, scene.json, every file a frame
    names (training, dry and depth images, masks) and the ground-truth files (not the targets' centres,
    which the spec in scene.json fixes, nor the depth TIFFs, copies of the EXRs), so changing any one gives
    another fingerprint (the ablation's row key, the trainer's checkpoint check). Reads every byte once:
    about a second for the 200 MB small reach."""
    root = Path(root)
    names = [TRANSFORMS, SCENE]
    try:
        frames = json.loads((root / TRANSFORMS).read_text()).get("frames", [])
    except (OSError, ValueError, AttributeError):
        frames = []
    for f in frames if isinstance(frames, list) else []:
        if isinstance(f, dict):
            names += [str(f[k]) for k in ("file_path", "dry_file_path", "gt_depth_file_path", "mask_path")
                  if f.get(k)]
    names += [GT_MESH, GT_SURFACE, GT_GRID, GT_BANKS, GT_ELEVATION, GT_WATERLINE]
    h = hashlib.sha256()
    for name in dict.fromkeys(names):  # in order, once each
        path = root / name
        h.update(name.encode() + b"\0")
        if path.is_file():
            with open(path, "rb") as fh:
                for block in iter(lambda: fh.read(1 << 20), b""):
                    h.update(block)
        else:
            h.update(b"-")
        h.update(b"\0")
    return h.hexdigest()[:16]


def frame(name: str, camera, split: str, kind: str, file_path: str, dry_file_path: str | None = None,
          gt_depth_file_path: str | None = None, mask_path: str | None = None) -> dict:
    """One `frames` entry: both pose forms (nerfstudio `transform_matrix` and OpenCV `w2c`), the split
    ("train" | "test"), the view kind ("nadir", "oblique20", ...) and the image paths. The dry ground-truth
    depth (metres) has a key of our own: nerfstudio reads `depth_file_path` as training depth in mm.
    `mask_path` (nerfstudio's key): an image, zero where pixels are left out of the loss (glint, people)."""
    out = {"file_path": file_path, "dry_file_path": dry_file_path, "gt_depth_file_path": gt_depth_file_path,
           "mask_path": mask_path,
           "transform_matrix": camera.c2w_gl.tolist(), "w2c": camera.w2c.tolist(), "split": split,
           "name": name, "kind": kind}
    return {k: v for k, v in out.items() if v is not None}


def water_json(water) -> dict | None:
    """The data contract's water, as transforms.json and scene.json hold it: None for a dry scene, else
    {"level", "n"} and, for a sloping surface, "slope": [dz/dx, dz/dy] (the plane z = level + sx x + sy y;
    a flat surface's files stay as they were). `water`: anything with `level`, `n` and optionally `slope`."""
    if water is None:
        return None
    out = {"level": float(water.level), "n": float(water.n)}
    slope = [float(v) for v in getattr(water, "slope", (0.0, 0.0))]
    if any(slope):
        out["slope"] = slope
    profile = getattr(water, "profile", None)
    if profile is not None:  # a surface curved along the reach: `water_surface.Profile`
        out["profile"] = {k: list(getattr(profile, k))
                          for k in ("origin", "direction", "stations", "offsets")}
    return out


def transforms_json(camera, frames: list[dict], water, georef: Georef | None = None) -> dict:
    """transforms.json: shared pinhole intrinsics of `camera` (no distortion; a frame may carry its own),
    `water` (see `water_json`; None for a dry scene), the frames and, for an imported survey,
    its `georef`. For nerfstudio: poses are used as they are (identity `applied_transform`, no
    re-orientation) and the split is given by file lists."""
    out = {
        "camera_model": "OPENCV",
        "fl_x": camera.fx, "fl_y": camera.fy, "cx": camera.cx, "cy": camera.cy, "w": camera.width,
        "h": camera.height, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "applied_transform": np.eye(4)[:3].tolist(), "orientation_override": "none",
        "train_filenames": [f["file_path"] for f in frames if f["split"] == "train"],
        "test_filenames": [f["file_path"] for f in frames if f["split"] == "test"],
        "water": water_json(water),
        "frames": frames,
    }
    if georef is not None:
        out["georef"] = georef.to_json()
    return out


def scene_json(spec: dict, eval_region: dict | None, **figures) -> dict:
    """scene.json: the generator's `spec` (the contract reads `spec.bed.depth`, the mean bed depth below
    the water, and `spec.bed.size`, the side of the square bed centred on the origin), the evaluation
    region {xmin, xmax, ymin, ymax} and whatever else the generator reports."""
    out = {"spec": spec, **figures}
    if eval_region is not None:
        out["eval_region"] = eval_region
    return out


# ---------------------------------------------------------------- COLMAP


def _quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (COLMAP's convention)."""
    w = np.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = np.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2
    y = np.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2
    z = np.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2
    x = np.copysign(x, R[2, 1] - R[1, 2])
    y = np.copysign(y, R[0, 2] - R[2, 0])
    z = np.copysign(z, R[1, 0] - R[0, 1])
    q = np.array([w, x, y, z])
    return q / np.linalg.norm(q)


def write_colmap(folder: Path, views, image_kind: str) -> None:
    """COLMAP text model of `views` (objects with `name`, `split` and `camera`, all sharing intrinsics), and
    the split as image lists `train.txt` / `test.txt`. Same pixel convention as ours: the top-left pixel's
    centre is (0.5, 0.5). Image names are relative to DIR/images."""
    cam = views[0].camera
    write_bytes(folder / "cameras.txt", (
        "# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"1 PINHOLE {cam.width} {cam.height} {cam.fx!r} {cam.fy!r} {cam.cx!r} {cam.cy!r}\n").encode())
    lines = ["# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "# POINTS2D (none)"]
    for i, v in enumerate(views, start=1):
        q, t = _quaternion(v.camera.R), v.camera.t
        lines.append(f"{i} {' '.join(repr(float(x)) for x in (*q, *t))} 1 {image_kind}/{v.name}.png")
        lines.append("")
    write_bytes(folder / "images.txt", ("\n".join(lines) + "\n").encode())
    write_bytes(folder / "points3D.txt", b"# 3D point list: empty (poses are known exactly)\n")
    for split in ("train", "test"):
        names = [f"{image_kind}/{v.name}.png" for v in views if v.split == split]
        write_bytes(folder / f"{split}.txt", "".join(f"{n}\n" for n in names).encode())
