"""The survey import (`dataset.colmap`): tiny COLMAP models written by pycolmap, text and binary, read back
through the data contract."""

import json
import shutil

import cv2
import numpy as np
import pycolmap
import pytest
import torch
from conftest import WATER, render_dataset

from ragsplat.bench.synthetic import bed_scene, ring_cameras
from ragsplat.cli.main import main
from ragsplat.dataset.colmap import IMPORT, POINTS, import_colmap
from ragsplat.dataset.load import load_dataset
from ragsplat.errors import DatasetError
from ragsplat.water_surface import WaterSurface

DOWN = np.diag([1.0, -1.0, -1.0])  # world -> camera of a nadir camera (x right = east, looking down -z)


def pattern(x, y):  # a smooth grey image over normalised image coordinates (x/z, y/z)
    return 127.5 + 90 * np.sin(6 * x + 1) * np.cos(5 * y)


def write_model(folder, images, centres, cams=None, R=DOWN, points=(), binary=False, size=(96, 72)):
    """A COLMAP model of nadir images at `centres` [V, 3] (world), their files in `images` showing `pattern`
    as each camera sees it (so undistortion can be checked), and 3D `points`. `cams`: pycolmap cameras
    (default: one PINHOLE)."""
    rec = pycolmap.Reconstruction()
    if cams is None:
        cams = [pycolmap.Camera.create_from_model_name(1, "PINHOLE", 80.0, *size)]
    for cam in cams:
        rec.add_camera_with_trivial_rig(cam)
    images.mkdir(parents=True, exist_ok=True)
    for i, c in enumerate(np.asarray(centres, float), start=1):
        cam = cams[(i - 1) % len(cams)]
        image = pycolmap.Image(name=f"img{i:02d}.jpg" if i % 2 else f"sub/img{i:02d}.png",
                               camera_id=cam.camera_id, image_id=i)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ c))
        u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
        xy = np.asarray(cam.cam_from_img(np.stack([u.ravel(), v.ravel()], 1))).reshape(
            cam.height, cam.width, 2)
        grey = np.clip(np.round(pattern(xy[..., 0], xy[..., 1])), 0, 255).astype(np.uint8)
        path = images / image.name
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), np.repeat(grey[..., None], 3, 2), [cv2.IMWRITE_JPEG_QUALITY, 100])
    for p in points:
        rec.add_point3D(np.asarray(p, float), pycolmap.Track(), np.array([200, 100, 50], dtype=np.uint8))
    folder.mkdir(parents=True, exist_ok=True)
    (rec.write_binary if binary else rec.write_text)(str(folder))
    return rec


CENTRES = [(0, 0, 5), (1, 0, 5), (0, 1, 5.2)]


@pytest.mark.parametrize("binary", [False, True])
def test_import_reads_poses_intrinsics_and_points(tmp_path, binary):
    rec = write_model(tmp_path / "model", tmp_path / "img", CENTRES, points=[(0, 0, -1), (1, 1, 0.5)],
                      binary=binary)
    done = import_colmap(tmp_path / "model", tmp_path / "img", tmp_path / "data", WaterSurface(0.2))
    assert (done.images, done.cameras, done.points, done.undistorted) == (3, 1, 2, 0)
    ds = load_dataset(tmp_path / "data")
    assert ds.water.level == 0.2 and ds.water.n == 1.33
    assert {v.name for v in ds.views} == {im.name for im in rec.images.values()}
    for view in ds.views:
        im = rec.find_image_with_name(view.name)
        np.testing.assert_allclose(view.camera.camera_center, im.projection_center(), atol=1e-12)
        assert (view.camera.fx, view.camera.cx, view.camera.width) == (80.0, 48.0, 96)
        source = cv2.imread(str(tmp_path / "img" / view.name))[..., ::-1]
        assert torch.equal(view.rgb, torch.from_numpy(source.copy()))  # pinhole: the image as it is
    pts = np.load(tmp_path / "data" / POINTS)
    np.testing.assert_allclose(pts[:, :3], [[0, 0, -1], [1, 1, 0.5]])  # as COLMAP has them: x n is init's job
    np.testing.assert_allclose(pts[0, 3:], [200 / 255, 100 / 255, 50 / 255])


def test_text_and_binary_give_the_same_dataset(tmp_path):
    for kind in ("txt", "bin"):
        write_model(tmp_path / kind, tmp_path / "img", CENTRES, binary=kind == "bin")
        import_colmap(tmp_path / kind, tmp_path / "img", tmp_path / f"data-{kind}", WaterSurface(0.0))
    a, b = (json.loads((tmp_path / f"data-{k}" / "transforms.json").read_text()) for k in ("txt", "bin"))
    assert a == b  # the same poses, read from text (17 digits: lossless) or binary, through the same code


def test_distorted_images_are_undistorted_to_the_pinhole_and_the_border_masked(tmp_path):
    cam = pycolmap.Camera.create_from_model_name(1, "OPENCV", 80.0, 160, 120)
    cam.params = [80.0, 82.0, 81.0, 59.0, 0.25, 0.05, 0.002, -0.001]  # strong pincushion distortion
    write_model(tmp_path / "model", tmp_path / "img", CENTRES[:1], cams=[cam])
    done = import_colmap(tmp_path / "model", tmp_path / "img", tmp_path / "data", WaterSurface(0.0))
    assert done.undistorted == 1
    (view,) = load_dataset(tmp_path / "data").views
    c = view.camera
    assert (c.fx, c.fy, c.cx, c.cy, c.width, c.height) == (80.0, 82.0, 81.0, 59.0, 160, 120)
    u, v = np.meshgrid(np.arange(160) + 0.5, np.arange(120) + 0.5)
    expected = pattern((u - c.cx) / c.fx, (v - c.cy) / c.fy)  # what a pinhole camera sees
    got = view.rgb[..., 0].numpy().astype(float)
    used = view.mask.numpy()
    assert 0.5 < used.mean() < 1.0  # pincushion: the pinhole's corners lie outside the source image
    assert not used[0, 0] and used[60, 80]
    err = np.abs(got - expected)[used]
    assert np.percentile(err, 99) < 4 and err.mean() < 1.5  # bilinear resampling of an 8-bit image
    # without undistortion the same comparison is far off: the test can fail
    raw = cv2.imread(str(tmp_path / "img" / "img01.jpg"))[..., 0].astype(float)
    assert np.abs(raw - expected)[used].mean() > 5 * err.mean()


def test_each_camera_keeps_its_own_intrinsics(tmp_path):
    wide = pycolmap.Camera.create_from_model_name(1, "PINHOLE", 80.0, 96, 72)
    tele = pycolmap.Camera.create_from_model_name(2, "SIMPLE_RADIAL", 150.0, 120, 90)
    tele.params = [150.0, 61.0, 44.0, 0.0]  # no distortion: copied as it is
    write_model(tmp_path / "model", tmp_path / "img", CENTRES, cams=[wide, tele])
    done = import_colmap(tmp_path / "model", tmp_path / "img", tmp_path / "data", WaterSurface(0.0))
    assert (done.cameras, done.undistorted) == (2, 0)
    got = {v.name: (v.camera.fx, v.camera.cx, v.camera.cy, v.camera.width)
           for v in load_dataset(tmp_path / "data").views}
    assert got == {"img01.jpg": (80.0, 48.0, 36.0, 96), "sub/img02.png": (150.0, 61.0, 44.0, 120),
                   "img03.jpg": (80.0, 48.0, 36.0, 96)}


def test_downscale_and_user_masks(tmp_path):
    write_model(tmp_path / "model", tmp_path / "img", CENTRES[:1], size=(96, 72))
    masks = tmp_path / "masks"
    masks.mkdir()
    m = np.full((72, 96), 255, np.uint8)
    m[:, :24] = 0  # glint on the left quarter
    cv2.imwrite(str(masks / "img01.jpg.png"), m)
    import_colmap(tmp_path / "model", tmp_path / "img", tmp_path / "data", WaterSurface(0.0), masks=masks,
                  max_size=48)
    (view,) = load_dataset(tmp_path / "data").views
    c = view.camera
    assert (c.width, c.height, c.fx, c.cx, c.cy) == (48, 36, 40.0, 24.0, 18.0)
    assert not view.mask[:, :12].any() and view.mask[:, 12:].all()


def test_utm_sized_coordinates_train_near_the_origin_and_keep_the_offset(tmp_path):
    east, north = 512_345.678, 5_123_456.789
    centres = [(east + x, north + y, 105.0 + z) for x, y, z in CENTRES]
    write_model(tmp_path / "model", tmp_path / "img", centres, points=[(east, north, 99.0)])
    done = import_colmap(tmp_path / "model", tmp_path / "img", tmp_path / "data", WaterSurface(100.0),
                         crs="EPSG:32633")
    ds = load_dataset(tmp_path / "data")
    assert ds.georef.crs == "EPSG:32633" and ds.georef.offset == done.georef.offset
    x0, y0, z0 = ds.georef.offset
    assert (x0, y0, z0) == (round(east + 1 / 3), round(north + 1 / 3), 0.0)
    assert ds.water.level == 100.0
    for view in ds.views:
        assert np.abs(view.camera.camera_center[:2]).max() < 2  # local: float32 keeps sub-millimetres
    got = np.sort([v.camera.camera_center + np.array([x0, y0, z0]) for v in ds.views], axis=0)
    np.testing.assert_allclose(got, np.sort(centres, axis=0), atol=1e-6)  # the round trip
    np.testing.assert_allclose(np.load(tmp_path / "data" / POINTS)[0, :3] + [x0, y0, z0], [east, north, 99.0],
                               atol=1e-9)


def test_a_second_import_reuses_the_directory_and_refuses_other_inputs(tmp_path):
    write_model(tmp_path / "model", tmp_path / "img", CENTRES)
    import_colmap(tmp_path / "model", tmp_path / "img", tmp_path / "data", WaterSurface(0.0))
    stamp = (tmp_path / "data" / IMPORT).stat().st_mtime_ns
    assert import_colmap(tmp_path / "model", tmp_path / "img", tmp_path / "data", WaterSurface(0.0)).reused
    assert (tmp_path / "data" / IMPORT).stat().st_mtime_ns == stamp
    with pytest.raises(DatasetError, match="level changed"):
        import_colmap(tmp_path / "model", tmp_path / "img", tmp_path / "data", WaterSurface(0.3))
    # the model known by its content: a copy elsewhere (a run folder moved) is the same input, another not
    shutil.copytree(tmp_path / "model", tmp_path / "moved")
    assert import_colmap(tmp_path / "moved", tmp_path / "img", tmp_path / "data", WaterSurface(0.0)).reused
    with open(tmp_path / "moved" / "points3D.txt", "a") as f:
        f.write("# edited\n")
    with pytest.raises(DatasetError, match="model_digest changed"):
        import_colmap(tmp_path / "moved", tmp_path / "img", tmp_path / "data", WaterSurface(0.0))


@pytest.mark.parametrize("case, phrase", [
    ("no images", "3 of the model's 3 images are missing"),
    ("under water", "camera img01.jpg is at z = 5, not above the water surface (6 there)"),
    ("upside down", "upside down"),
    ("z not up", "z axis is not up"),
    ("not a model", "not a COLMAP model"),
])
def test_bad_surveys_get_one_line(tmp_path, capsys, case, phrase):
    R = {"upside down": np.diag([1.0, 1.0, 1.0]),  # looking up
         "z not up": np.array([[0.0, 1, 0], [0, 0, -1], [-1, 0, 0]])}.get(case, DOWN)  # looking along +x
    write_model(tmp_path / "model", tmp_path / "img", CENTRES, R=R)
    images = tmp_path / ("empty" if case == "no images" else "img")
    images.mkdir(exist_ok=True)
    model = tmp_path / ("img" if case == "not a model" else "model")
    level = "6" if case == "under water" else "0"
    rc = main(["train", "--colmap", str(model), "--images", str(images), "--water-level", level,
               "--init-depth", "1", "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and phrase in err[0], err


def test_colmap_needs_images_and_a_level(tmp_path, capsys):
    write_model(tmp_path / "model", tmp_path / "img", CENTRES)
    rc = main(["train", "--colmap", str(tmp_path / "model"), "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err == ["ragsplat train: error: --colmap needs --images and --water-level"]
    assert not (tmp_path / "run").exists()  # refused before anything is written


def test_survey_to_dem_and_laz_in_the_survey_crs(tmp_path):
    """The surveyor's path on a rendered bed 1 m under water, moved to UTM-sized coordinates and handed over
    as a COLMAP model with its apparent points: import + train (2 steps: this checks the path, not the
    depths), export; the products carry the CRS and absolute coordinates."""
    import laspy
    import rasterio

    shift = np.array([512_345.0, 5_123_456.0, 100.0])  # local -> UTM (the water is at z = 100)
    scene = bed_scene(300, half=1.0, depth=1.0, seed=2)
    cams = ring_cameras(5, 20, 1.5, 0.8, target=(0, 0, -1))
    render_dataset(tmp_path / "local", scene, cams, WATER, 0, {"xmin": -1, "xmax": 1, "ymin": -1, "ymax": 1})
    rec = pycolmap.Reconstruction()
    c = cams[0]
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera.create_from_model_name(1, "PINHOLE", c.fx, c.width, c.height))
    rec.cameras[1].params = [c.fx, c.fy, c.cx, c.cy]
    for i, view in enumerate(load_dataset(tmp_path / "local").views, start=1):
        R, t = view.camera.R, view.camera.t
        rec.add_image_with_trivial_frame(pycolmap.Image(name=view.file_path, camera_id=1, image_id=i),
                                         pycolmap.Rigid3d(pycolmap.Rotation3d(R), t - R @ shift))
    apparent = scene["means"].double().numpy() * [1, 1, 1 / WATER.n]  # what MVS finds through the water
    for p in apparent + shift:
        rec.add_point3D(p, pycolmap.Track(), np.array([120, 110, 90], dtype=np.uint8))
    (tmp_path / "model").mkdir()
    rec.write_text(str(tmp_path / "model"))
    run = tmp_path / "run"
    assert main(["train", "--colmap", str(tmp_path / "model"), "--images", str(tmp_path / "local"),
                 "--water-level", "100", "--crs", "EPSG:32633", "--out", str(run), "--preset", "smoke",
                 "--iterations", "2", "--no-progress"]) == 0
    config = json.loads((run / "config.json").read_text())["config"]
    assert config["init"] == "points" and config["init_points"].endswith(POINTS)
    assert main(["export", str(run), "--dem", str(tmp_path / "dem.tif"), "--las", str(tmp_path / "bed.laz"),
                 "--resolution", "0.1", "--min-opacity", "0.05", "--max-scale-gsd", "inf"]) == 0  # 2 steps
    east, north = shift[:2]
    with rasterio.open(tmp_path / "dem.tif") as tif:
        assert tif.crs.to_epsg() == 32633
        assert east - 1.5 < tif.bounds.left < tif.bounds.right < east + 1.5
        assert north - 1.5 < tif.bounds.bottom < tif.bounds.top < north + 1.5
        depth = tif.read(2, masked=True)
    assert abs(float(np.ma.median(depth)) - 1.0) < 0.15  # the points' apparent depths x n: the true 1 m
    las = laspy.read(tmp_path / "bed.laz")
    assert rasterio.crs.CRS.from_wkt(las.header.vlrs[0].string).to_epsg() == 32633
    assert abs(float(np.median(las.x)) - east) < 1 and abs(float(np.median(las.z)) - 99.0) < 0.15


def test_triangulation_with_known_poses_finds_a_plane(tmp_path, monkeypatch):
    """A textured plane at z = 1 (dry: the water is at 0) photographed by six nadir cameras at z = 5 (each
    image an exact homography of one texture): the triangulated points lie on the plane; matched by the
    views' neighbours instead of every pair (above `TRACKS_EXHAUSTIVE_MAX`: here every pair again, six views
    being fewer than NEIGHBOURS), the same plane."""
    from ragsplat.dataset import colmap
    from ragsplat.dataset.colmap import triangulate

    rng = np.random.default_rng(1)
    texture = sum(cv2.resize(rng.uniform(0, 255, (k, k)).astype(np.float32), (512, 512)) / 3
                  for k in (16, 64, 256))
    texture = cv2.GaussianBlur(texture, (0, 0), 1.0).astype(np.uint8)
    s, z_plane = 4 / 512, 1.0  # the texture covers [-2, 2]^2 m
    centres = [(x, y, 5.0) for x in (-0.6, 0, 0.6) for y in (-0.4, 0.4)]
    write_model(tmp_path / "model", tmp_path / "img", centres, size=(160, 160))
    rec = pycolmap.Reconstruction()
    rec.read_text(str(tmp_path / "model"))
    plane_from_texture = np.array([[s, 0, -2 + s / 2], [0, -s, 2 - s / 2], [0, 0, 1]])  # pixel centres at i
    to_opencv = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1]])  # COLMAP's pixel centres are at i + 0.5
    for im in rec.images.values():
        pose = im.cam_from_world()
        R, t = pose.rotation.matrix(), pose.translation
        K = im.camera.calibration_matrix()
        H = to_opencv @ K @ np.column_stack([R[:, 0], R[:, 1], R[:, 2] * z_plane + t]) @ plane_from_texture
        grey = cv2.warpPerspective(texture, H, (160, 160), flags=cv2.INTER_LINEAR)
        cv2.imwrite(str(tmp_path / "img" / im.name), np.repeat(grey[..., None], 3, 2),
                    [cv2.IMWRITE_JPEG_QUALITY, 100])
    import_colmap(tmp_path / "model", tmp_path / "img", tmp_path / "data", WaterSurface(0.0))
    pts, obs, names = triangulate(tmp_path / "data", tmp_path / "work")
    again = triangulate(tmp_path / "data", tmp_path / "work2")
    # the same twice on this small, clean case (across processes a large reach's count can differ by a few:
    # the comment in `triangulate`)
    assert np.array_equal(pts, again[0]) and np.array_equal(obs, again[1]) and names == again[2]
    assert len(pts) > 50
    # every observation is its point's pixel (COLMAP's pixel centres at i + 0.5, as ours)
    cams = {v.file_path: v.camera for v in load_dataset(tmp_path / "data", splits=("train",)).train}
    for k, name in enumerate(names):
        rows = obs[:, 1] == k
        px, _ = cams[name].project(pts[obs[rows, 0].astype(int), :3])
        assert np.median(np.abs(px - obs[rows, 2:])) < 0.5
    assert (np.median(np.abs(pts[:, 2] - z_plane)) < 0.005
            and np.percentile(np.abs(pts[:, 2] - z_plane), 90) < 0.02)
    monkeypatch.setattr(colmap, "TRACKS_EXHAUSTIVE_MAX", 5)
    near, _, near_names = triangulate(tmp_path / "data", tmp_path / "work3")
    listed = (tmp_path / "work3" / "pairs.txt").read_text().splitlines()
    assert len(listed) == 15 and all(len(line.split()) == 2 for line in listed) and near_names == names
    assert abs(len(near) - len(pts)) <= 0.02 * len(pts)  # the same pairs (round-off in SIFT's matching aside)
    assert np.median(np.abs(near[:, 2] - z_plane)) < 0.005


def test_footprint_is_where_the_optical_axis_meets_the_water():
    from ragsplat.camera import Camera
    from ragsplat.dataset.colmap import footprint

    nadir = Camera.look_at((1.0, 2.0, 12.0), (1.0, 2.0, 0.0), 64, 64, 60.0)
    assert np.allclose(footprint(nadir, WaterSurface(0.5)), (1.0, 2.0, 0.5))
    # 40 degrees off nadir towards +x, 11.5 m above the water: 11.5 tan(40 deg) ahead
    oblique = Camera.look_at((1.0, 2.0, 12.0), (1.0 + 12 * np.tan(np.radians(40)), 2.0, 0.0), 64, 64, 60.0)
    assert np.allclose(footprint(oblique, WaterSurface(0.5)), (1.0 + 11.5 * np.tan(np.radians(40)), 2.0, 0.5))
    assert np.allclose(footprint(oblique, None), (1.0, 2.0, 12.0))  # no water: the camera's centre
    level = Camera.look_at((0.0, 0.0, 12.0), (10.0, 0.0, 12.0), 64, 64, 60.0, up=(0.0, 0.0, 1.0))
    assert np.allclose(footprint(level, WaterSurface(0.5)), (0.0, 0.0, 12.0))  # the axis never descends
