"""Camera positions from the photos' own metadata (`dataset.exif`): EXIF GPS and DJI's XMP written by
`photos.write_jpeg` and read back, the conversion to UTM against the projection's definition, the zone
chosen, a photo without GPS refused in one line, and `ragsplat survey PHOTOS` with no positions file on a
small synthetic survey geotagged by the generator (`ragsplat.datagen.survey.write_survey`): RTK-fixed photos,
and the same photos with consumer GPS (a bias per flight line), every camera kept."""

import json
import math
import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch
from conftest import channel_scene, survey_cameras

from ragsplat.bench.synthetic import bed_scene, render_views, write_dataset
from ragsplat.camera import Camera
from ragsplat.cli.main import main
from ragsplat.datagen.flight import Pose
from ragsplat.datagen.spec import WaterSpec
from ragsplat.datagen.survey import (
    LENS,
    ConsumerGPS,
    GeoOrigin,
    SurveyNoise,
    flight_lines,
    gimbal_angles,
    write_survey,
)
from ragsplat.dataset import exif, layout, photos
from ragsplat.errors import ConfigError, DatasetError
from ragsplat.water_surface import WaterSurface

IMAGE = (np.random.default_rng(0).random((36, 48, 3)) * 255).astype(np.uint8)


def test_gps_and_dji_xmp_round_trip(tmp_path):
    path = tmp_path / "DJI_0001.JPG"
    xmp = {"AbsoluteAltitude": 241.337, "RelativeAltitude": 38.5, "GimbalRollDegree": 0.0,
           "GimbalYawDegree": -153.2, "GimbalPitchDegree": -89.9, "FlightRollDegree": 1.5,
           "FlightYawDegree": -150.0, "FlightPitchDegree": -2.0, "RtkFlag": 50, "RtkStdLon": 0.011,
           "RtkStdLat": 0.014, "RtkStdHgt": 0.023}
    photos.write_jpeg(path, IMAGE, 40.0, gps=(-33.912345678, -70.123456789, 241.3371), xmp=xmp)
    p = exif.read_photo(path)
    assert (p.name == "DJI_0001.JPG" and p.source == "EXIF GPS"
            and p.altitude_source == "DJI XMP AbsoluteAltitude")
    assert abs(p.lat + 33.912345678) < 1e-9 and abs(p.lon + 70.123456789) < 1e-9  # 1e-6 arc seconds
    assert p.altitude == pytest.approx(241.337, abs=1e-6) and p.relative_altitude == 38.5
    assert p.rtk_flag == 50 and p.rtk_fixed and p.std_horizontal == 0.014 and p.std_vertical == 0.023
    assert p.gimbal == (-153.2, -89.9, 0.0) and p.flight == (-150.0, -2.0, 1.5)
    from PIL import Image

    with Image.open(path) as im:  # still a plain JPEG with its focal length
        assert im.size == (48, 36) and float(im.getexif().get_ifd(0x8769)[0x920A]) == pytest.approx(0.4)


def test_exif_gps_alone_and_xmp_as_elements(tmp_path):
    """No XMP: the height is the EXIF GPSAltitude (below sea level here), no RTK; DJI properties written as
    elements rather than attributes are read too."""
    path = tmp_path / "a.jpg"
    photos.write_jpeg(path, IMAGE, 40.0, gps=(46.5, 13.25, -3.25))
    p = exif.read_photo(path)
    assert (p.lat, p.lon, p.altitude) == (pytest.approx(46.5), pytest.approx(13.25), pytest.approx(-3.25))
    assert (p.altitude_source == "EXIF GPSAltitude" and p.rtk_flag is None and not p.rtk_fixed
            and p.gimbal is None)
    packet = (b'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF '
              b'xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#"><rdf:Description '
              b'xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/"><drone-dji:RtkFlag>34</drone-dji:RtkFlag>'
              b'<drone-dji:GpsLatitude>+1.5</drone-dji:GpsLatitude></rdf:Description>'
              b'</rdf:RDF></x:xmpmeta>')
    assert (exif.dji_tags(exif.xmp_packet(b"junk" + packet + b"junk"))
            == {"RtkFlag": "34", "GpsLatitude": "+1.5"})
    assert exif.dji_tags(b"<x:xmpmeta not xml") == {}


def test_a_photo_without_gps_is_one_line_naming_it(tmp_path, capsys):
    for k in range(3):
        photos.write_jpeg(tmp_path / "images" / f"IMG_{k}.JPG", IMAGE, 40.0,
                          gps=None if k == 1 else (46.0, 13.0, 200.0))
    with pytest.raises(DatasetError) as err:
        exif.read_photos(sorted((tmp_path / "images").iterdir()))
    assert "IMG_1.JPG: no GPS position in its metadata" in str(err.value) and "\n" not in str(err.value)
    argv = ["survey", str(tmp_path / "images"), "--water-level", "0", "--out", str(tmp_path / "run")]
    assert main(argv) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "IMG_1.JPG: no GPS position" in lines[0] and "--positions" in lines[0]
    assert not (tmp_path / "run").exists()
    assert main([*argv, "--gcp-pixels", str(tmp_path / "pixels.csv")]) == 2  # no --gcp: not the photos' GPS
    assert "--gcp-pixels needs --gcp" in capsys.readouterr().err


def meridian_arc(lat_deg: float) -> float:
    """Length (m) of the WGS 84 meridian from the equator to lat_deg: the integral of the meridian's radius of
    curvature a (1 - e^2) / (1 - e^2 sin^2 phi)^(3/2), by Simpson's rule (independent of pyproj)."""
    a, f = 6378137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    phi = np.linspace(0, math.radians(lat_deg), 2001)
    m = a * (1 - e2) / (1 - e2 * np.sin(phi) ** 2) ** 1.5
    h = phi[1] - phi[0]
    return float(h / 3 * (m[0] + m[-1] + 4 * m[1:-1:2].sum() + 2 * m[2:-1:2].sum()))


def test_utm_against_its_definition_and_back():
    """On a zone's central meridian UTM is easting 500 000 m and northing 0.9996 times the meridian arc
    (plus 10 000 km south of the equator); anywhere, back to degrees within a millimetre."""
    xyz = exif.to_metric([45.0, 0.0, -30.0], [15.0, 15.0, 15.0], [1.0, 2.0, 3.0], "EPSG:32633")
    np.testing.assert_allclose(xyz[:2], [[500000.0, 0.9996 * meridian_arc(45.0), 1.0], [500000.0, 0.0, 2.0]],
                               atol=1e-3)
    south = exif.to_metric(-30.0, 15.0, 3.0, "EPSG:32733")[0]
    assert south == pytest.approx([500000.0, 1e7 - 0.9996 * meridian_arc(30.0), 3.0], abs=1e-3)
    assert meridian_arc(45.0) == pytest.approx(4984944.38, abs=0.01)  # the textbook value
    points = np.array([[46.2470, 13.5830, 247.0], [46.3, 12.1, 0.0], [45.9, 17.9, -5.0]])
    metric = exif.to_metric(points[:, 0], points[:, 1], points[:, 2], "EPSG:32633")
    back = exif.to_geographic(metric, "EPSG:32633")
    np.testing.assert_allclose(back[:, 2], points[:, 2])
    lat_m = np.radians(points[:, 0])
    assert np.abs(back[:, 0] - points[:, 0]).max() * 111_000 < 1e-3
    assert (np.abs(back[:, 1] - points[:, 1]) * 111_000 * np.cos(lat_m)).max() < 1e-3


@pytest.mark.parametrize("lat, lon, epsg", [
    (46.247, 13.583, 32633),  # the generator's river, Slovenia
    (-33.92, 18.42, 32734),  # Cape Town: south
    (40.69, -74.04, 32618),  # New York: west
    (0.0, 179.99, 32660), (-0.01, -180.0, 32701),  # the zones' ends
    (60.39, 5.32, 32632),  # Bergen: zone 32V, not 31
    (78.22, 15.65, 32633),  # Longyearbyen, Svalbard: zone 33X
])
def test_utm_zone_choice(lat, lon, epsg):
    assert exif.utm_epsg(lat, lon) == epsg


def photo(name, lat, lon, flag=None):
    return exif.PhotoPosition(name, lat, lon, 100.0, "EXIF GPS", "EXIF GPSAltitude", rtk_flag=flag)


def test_positions_in_the_zone_of_their_mean_or_the_chosen_crs():
    photos = [photo("a", 46.0, 11.99), photo("b", 46.0, 12.03), photo("c", 46.0, 12.02)]  # mean east of 12
    xyz, crs = exif.positions(photos)
    assert exif.crs_label(crs) == "EPSG:32633" and set(xyz) == {"a", "b", "c"}
    assert xyz["a"][0] < xyz["b"][0] and xyz["a"][2] == 100.0
    xyz, crs = exif.positions(photos, "EPSG:32632")
    assert exif.crs_label(crs) == "EPSG:32632" and xyz["a"][0] > 700000  # east of zone 32's meridian
    with pytest.raises(ConfigError, match="not a projected CRS in metres"):
        exif.positions(photos, "EPSG:4326")


def test_the_noise_follows_the_source():
    fixed = exif.PhotoPosition("f", 46.0, 13.0, 1.0, "EXIF GPS", "x", rtk_flag=50, std_horizontal=0.012,
                               std_vertical=0.001)
    s = exif.sigmas([fixed, photo("r", 46.0, 13.0, 50), photo("g", 46.0, 13.0), photo("fl", 46.0, 13.0, 34)],
                    None)
    np.testing.assert_allclose(s, [[0.012, exif.MIN_STD], [0.02, 0.03], [2.0, 3.0], [2.0, 3.0]])
    np.testing.assert_allclose(exif.sigmas([fixed], (0.05, 0.06)), [[0.05, 0.06]])  # --rtk-sigma wins
    baro = replace(photo("b", 46.0, 13.0), relative_altitude=40.0)
    rtk_baro = replace(photo("rb", 46.0, 13.0, 50), relative_altitude=40.0)  # RTK: its own height
    np.testing.assert_allclose(exif.sigmas([baro, rtk_baro], None, barometer=0.1), [[2.0, 0.1], [0.02, 0.03]])


def test_consumer_heights_come_from_the_barometer():
    """A consumer drone's GPS heights scatter by metres; where its photos carry DJI's RelativeAltitude,
    each is put at the take-off point's height (the median of GPS height less relative altitude) plus its
    own; RTK-fixed photos and photos without one keep their height."""
    rng = np.random.default_rng(0)
    truth = 140.0 + np.array([40.0, 40.1, 39.9, 40.0, 40.05])  # take-off 140 m, flown at about 40 m
    photos = [replace(photo(f"{k}", 46.0, 13.0 + 1e-4 * k), altitude=float(z + rng.normal(0, 3)),
                      relative_altitude=float(z - 140.0)) for k, z in enumerate(truth)]
    heights = exif.barometric_heights(photos)
    takeoff = np.median([p.altitude - p.relative_altitude for p in photos])
    np.testing.assert_allclose(heights, takeoff + truth - 140.0)
    np.testing.assert_allclose(np.diff(heights), np.diff(truth))  # the GPS's metres gone from the tilt
    xyz, _ = exif.positions(photos)
    np.testing.assert_allclose([xyz[p.name][2] for p in photos], heights)
    others = [photo("g", 46.0, 13.0), replace(photo("r", 46.0, 13.0, 50), relative_altitude=3.0)]
    # alone, a photo's take-off point is its own: its height as given
    np.testing.assert_allclose(exif.barometric_heights(others + photos[:1]),
                               [100.0, 100.0, photos[0].altitude])
    assert [p.barometric for p in others] == [False, False] and photos[0].barometric


def test_gimbal_angles_are_true_north_headings():
    """West of zone 33's central meridian grid north is (15 - lon) sin(lat) degrees west of true north: a
    north-up nadir's heading is about -1.02 deg, a view tilted 30 deg towards grid east's about 88.98; a
    level view to grid north rolled 0.1 rad has that roll."""
    origin = exif.to_metric(ORIGIN.lat, ORIGIN.lon, ORIGIN.height, "EPSG:32633")[0]
    cams = [Camera.look_at([0, 0, 10], [0, 0, 0], 64, 64, 60.0),
            Camera.look_at([0, 0, 10], [10 * math.tan(math.radians(30)), 0, 0], 64, 64, 60.0, up=(0, 0, 1)),
            Camera.look_at([0, 0, 10], [0, 10, 10], 64, 64, 60.0, up=(math.sin(0.1), 0, math.cos(0.1)))]
    yaw, pitch, roll = gimbal_angles(cams, origin, "EPSG:32633").T
    convergence = (ORIGIN.lon - 15) * math.sin(math.radians(ORIGIN.lat))
    np.testing.assert_allclose(yaw, [convergence, 90 + convergence, convergence], atol=0.02)
    np.testing.assert_allclose(pitch, [-90, -60, 0], atol=1e-9)
    np.testing.assert_allclose(roll, [0, 0, math.degrees(0.1)], atol=1e-9)  # looking north, right side down


ORIGIN = GeoOrigin()
# to the 4 m flight's scale (its 2.4 m against a real flight's 84 m, for the barometer)
CONSUMER = ConsumerGPS(line_bias=(0.4, 0.6), line_bias_z=0.2, jitter=0.2, barometer_drift=0.006,
                       barometer_jitter=0.001)
BAROMETER = ["--barometer-sigma", "0.003"]


def lens_photo(scene: dict, cam: Camera, water: WaterSurface, k1: float, k2: float) -> np.ndarray:
    """[H, W, 3] uint8: `scene` seen by `cam` through a lens with radial distortion k1, k2 (COLMAP's RADIAL),
    resampled (bilinear) from a pinhole render of twice the size and a view wide enough for the corners."""
    r_corner = math.hypot(cam.width / 2, cam.height / 2) / cam.fx  # distorted, normalised
    r = r_corner
    for _ in range(50):
        r = r_corner / (1 + k1 * r * r + k2 * r**4)
    scale = 2 * r_corner / r / 1.05  # the render's focal over cam's: twice the pixels, the corners inside
    wide = replace(cam, width=2 * cam.width, height=2 * cam.height, fx=cam.fx * scale, fy=cam.fy * scale,
                   cx=2 * cam.cx, cy=2 * cam.cy)
    image = render_views(scene, [wide], water)[0]["image"].numpy()
    u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    xd, yd = (u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy
    x, y = xd, yd
    for _ in range(50):
        f = 1 + k1 * (x * x + y * y) + k2 * (x * x + y * y) ** 2
        x, y = xd / f, yd / f
    su, sv = wide.fx * x + wide.cx - 0.5, wide.fy * y + wide.cy - 0.5  # array indices in the render
    u0, v0 = np.floor(su).astype(int), np.floor(sv).astype(int)
    fu, fv = (su - u0)[..., None], (sv - v0)[..., None]
    out = ((1 - fu) * (1 - fv) * image[v0, u0] + fu * (1 - fv) * image[v0, u0 + 1]
           + (1 - fu) * fv * image[v0 + 1, u0] + fu * fv * image[v0 + 1, u0 + 1])
    return (np.clip(out, 0, 1) * 255 + 0.5).astype(np.uint8)


@pytest.fixture(scope="session")
def geotagged(tmp_path_factory):
    """A gravel bed 0.8 m under water seen by 12 nadir (three flight lines) and 6 oblique photos from 4 m,
    made into a survey by the generator: survey/images/ (RTK, 5 / 8 mm) and survey/images-gps/ (consumer GPS
    at this flight's scale: lines 0.4-0.6 m off, 0.2 m scatter)."""
    root = tmp_path_factory.mktemp("geotagged")
    water = WaterSurface(0.0, 1.33)
    scene = bed_scene(30000, half=3.0, depth=0.8, seed=0)
    scene["colors"] = torch.rand(30000, 3, generator=torch.Generator().manual_seed(1))
    cams = survey_cameras(lines_along_x=True)
    views = render_views(scene, cams, water)
    write_dataset(root, views, water)
    poses = [Pose(f"{i:04d}", "nadir" if i < 12 else "oblique30", "train", c) for i, c in enumerate(cams)]
    for p in poses:  # the generator renders these with Blender's polynomial lens (test_blender_markers.py)
        layout.write_png(layout.output_path(root, "lens", p.name), lens_photo(scene, p.camera, water, *LENS))
    assert flight_lines(poses).tolist() == [0] * 4 + [1] * 4 + [2] * 4 + [3] * 6
    assert write_survey(root, poses, WaterSpec(), noise=SurveyNoise(horizontal=0.005, vertical=0.008),
                        origin=ORIGIN, gps=CONSUMER)
    return root, cams


def test_the_generator_geotags_its_photos(geotagged):
    root, cams = geotagged
    record = json.loads((root / layout.SURVEY_RECORD).read_text())["geo"]
    assert record["crs"] == "EPSG:32633" and record["origin"]["lat"] == ORIGIN.lat
    shift = np.array(record["origin_metric"])
    truth = np.array([c.camera_center for c in cams])
    rtk = layout.read_positions(root / layout.SURVEY_POSITIONS)
    for folder, tolerance in ((layout.SURVEY_IMAGES, 1e-3), (layout.SURVEY_IMAGES_GPS, None)):
        tagged = exif.read_photos(sorted((root / folder).iterdir()))
        xyz, crs = exif.positions(tagged)
        assert exif.crs_label(crs) == "EPSG:32633"
        got = np.array([xyz[p.name] for p in tagged]) - shift
        if tolerance:  # the positions.csv centres, to the millimetre
            np.testing.assert_allclose(got, [rtk[p.name] for p in tagged], atol=tolerance)
            assert all(p.rtk_fixed and p.std_vertical == 0.008 for p in tagged)
            # above the take-off point
            assert tagged[0].relative_altitude == pytest.approx(4.0 - 1.0, abs=0.05)
        else:  # each line off by its bias, plus scatter; the heights the barometer's, to millimetres here
            assert all(p.rtk_flag is None for p in tagged)
            off = np.linalg.norm((got - truth)[:, :2], axis=1)
            assert 0.1 < np.median(off) < 1.0
            relative = np.array([p.relative_altitude for p in tagged]) - (truth[:, 2] - 1.0)
            assert np.abs(relative).max() < 0.012 and np.abs(got[:, 2] - truth[:, 2]).max() > 0.1
        nadir = np.array([p.gimbal for p in tagged[:12]])
        assert np.abs(nadir[:, 1] + 90).max() < 2 and np.abs(nadir[:, 0]).max() < 8  # north-up, 2 deg noise
    record_bytes = (root / layout.SURVEY_RECORD).read_bytes()
    jpegs = {p: p.read_bytes() for folder in (layout.SURVEY_IMAGES, layout.SURVEY_IMAGES_GPS)
             for p in (root / folder).iterdir()}
    others = {p: p.read_bytes() for p in (root / "survey").iterdir() if p.is_file() and p.suffix != ".json"}
    poses = [Pose(f"{i:04d}", "nadir" if i < 12 else "oblique30", "train", c) for i, c in enumerate(cams)]
    again = {"noise": SurveyNoise(horizontal=0.005, vertical=0.008), "origin": ORIGIN, "gps": CONSUMER}
    assert not write_survey(root, poses, WaterSpec(), **again)
    assert (root / layout.SURVEY_RECORD).read_bytes() == record_bytes  # nothing written again
    # a survey made before the photos were geotagged gets them, and nothing else changes
    old = json.loads(record_bytes)
    del old["geo"]
    (root / layout.SURVEY_RECORD).write_text(json.dumps(old))
    for path in (root / layout.SURVEY_IMAGES_GPS).iterdir():
        path.unlink()
    photos.write_jpeg(root / layout.SURVEY_IMAGES / "0000.jpg", IMAGE, 40.0)  # no GPS
    assert not write_survey(root, poses, WaterSpec(), **again)
    assert json.loads((root / layout.SURVEY_RECORD).read_text()) == json.loads(record_bytes)
    assert {p: p.read_bytes() for p in jpegs} == jpegs
    assert {p: p.read_bytes() for p in others} == others


def survey_args(root, folder, out, *extra):
    # z = 0 in heights
    level = json.loads((root / layout.SURVEY_RECORD).read_text())["geo"]["origin_metric"][2]
    return ["survey", str(root / folder), "--water-level", str(level), "--out", str(out), "--stop-after",
            "georef", "--no-progress", *extra]


def test_photos_alone_with_rtk_positions(geotagged, tmp_path, capsys):
    root, cams = geotagged
    assert main(survey_args(root, layout.SURVEY_IMAGES, tmp_path / "run")) == 0
    err = capsys.readouterr().err
    assert ("positions from the photos: 18 of 18 have GPS (18 RTK fixed, 0 consumer GPS), in EPSG:32633, WGS "
            "84 / UTM zone 33N; heights as the photos give them (DJI XMP AbsoluteAltitude)") in err
    report = json.loads((tmp_path / "run" / "georef.json").read_text())
    # the pinhole SfM's, through water
    assert report["inliers"] == report["count"] == 18 and report["rms_m"] < 0.05
    assert report["positions"]["crs"] == "EPSG:32633" and "EXIF GPS" in report["positions"]["source"]
    assert report["noise"]["rtk_fixed"]["count"] == 18 and "consumer_gps" not in report["noise"]
    assert "scale_uncertainty" not in report and "scale comes from consumer GPS" not in err
    assert (report["noise"]["rtk_fixed"]["sigma_m_median"] == [0.005, 0.008]
            and report["noise"]["threshold_m"] == 0.2)
    assert set(report["positions"]["photos"]) == {f"{i:04d}.jpg" for i in range(18)}
    # the model's cameras where the truth is, in UTM
    shift = np.array(json.loads((root / layout.SURVEY_RECORD).read_text())["geo"]["origin_metric"])
    truth = np.array([c.camera_center for c in cams]) + shift
    used = np.array([exif.to_metric(p["lat"], p["lon"], p["altitude"], "EPSG:32633")[0]
                     for p in report["positions"]["photos"].values()])
    residual = np.array(list(report["residual_m"].values()))
    assert np.abs(used - truth).max() < 0.05 and np.sqrt((residual ** 2).sum(1).mean()) < 0.05


def test_photos_alone_with_consumer_gps_keep_every_camera(geotagged, tmp_path, capsys):
    root, cams = geotagged
    out = tmp_path / "run"
    assert main(survey_args(root, layout.SURVEY_IMAGES_GPS, out)) == 0
    err = capsys.readouterr().err
    assert "(0 RTK fixed, 18 consumer GPS)" in err
    report = json.loads((out / "georef.json").read_text())
    assert report["inliers"] == report["count"] == 18
    # the scale is the GPS's: the user is told how far depths can be off, and that it covers the frame's
    # scale error (a similarity of the model's camera centres to the true ones)
    stated = report["scale_uncertainty"]
    assert (stated["relative"] == pytest.approx(report["rms_m"] / stated["extent_m"])
            and stated["extent_m"] > 2)
    assert f"may be off by up to about {100 * stated['relative']:.0f} %" in err and "--gcp" in err
    import pycolmap

    from ragsplat.survey import georef

    rec = pycolmap.Reconstruction(str(out / "sfm" / "model"))
    model = {img.name: img.projection_center() for img in rec.images.values()}
    names = sorted(model)
    to_truth = georef.fit_similarity(np.array([model[n] for n in names]),
                                 np.array([cams[int(n[:4])].camera_center for n in names]))
    assert abs(report["scale"] / to_truth.scale - 1) < stated["relative"]
    noise = report["noise"]
    # the heights the barometer's (the generator's photos carry it)
    assert noise["consumer_gps"]["count"] == 18
    assert noise["consumer_gps"]["sigma_m"] == [2.0, exif.BAROMETER_SIGMA]
    assert noise["threshold_m"] == 20.0 and "per-line bias" in noise["consumer_gps"]["bias"]
    assert 0.05 < report["rms_m"] < 1.0 and noise["rms_m_by_source"]["rtk_fixed"] is None
    # held to centimetres as if they were RTK, the same photos lose cameras as "outliers": issue 48's point 3
    assert main(survey_args(root, layout.SURVEY_IMAGES_GPS, out, "--gps-sigma", "0.02", "0.03",
                            "--barometer-sigma", "0.03")) == 0
    assert json.loads((out / "georef.json").read_text())["inliers"] < 18


def test_the_adjustment_holds_each_camera_to_its_own_accuracy():
    """A per-camera prior (RTK and consumer GPS in one flight): the same as the tuple when every row is the
    same; a camera held to metres goes where its photos put it, away from a position 0.5 m off."""
    from ragsplat.survey import bundle

    rng = np.random.default_rng(0)
    cams = [Camera.look_at([x, y, 5.0], [x, y, 0.0], 120, 90, 60.0) for x in (-1.0, 0.0, 1.0)
            for y in (-0.5, 0.5)]
    R = torch.tensor(np.array([c.R for c in cams]))
    C = torch.tensor(np.array([c.camera_center for c in cams]))
    K = torch.tensor([[c.fx, c.fy, c.cx, c.cy] for c in cams])
    P = torch.tensor(np.column_stack([rng.uniform(-2, 2, (60, 2)), rng.uniform(-0.3, 0.3, 60)]))
    point, image = torch.arange(60).repeat(len(cams)), torch.arange(len(cams)).repeat_interleave(60)
    pixels = bundle.project(R[image], C[image], K[image], P[point], None)
    inside = ((pixels >= 0) & (pixels < torch.tensor([120.0, 90.0]))).all(1)
    point, image, pixels = point[inside], image[inside], pixels[inside]
    prior = C.clone()
    prior[0, 0] += 0.5  # one camera's GPS 0.5 m off
    same = bundle.adjust(R, C, K, P, point, image, pixels, None, prior_C=prior,
                         prior_sigma=(0.02, 0.02, 0.03))
    rows = bundle.adjust(R, C, K, P, point, image, pixels, None, prior_C=prior,
                         prior_sigma=torch.tensor([[0.02, 0.02, 0.03]] * len(cams)))
    torch.testing.assert_close(rows.C, same.C)
    each = torch.tensor([[2.0, 2.0, 3.0]] + [[0.02, 0.02, 0.03]] * (len(cams) - 1))
    loose = bundle.adjust(R, C, K, P, point, image, pixels, None, prior_C=prior, prior_sigma=each)
    assert (loose.C - C).norm(dim=1).max() < 0.02 < (same.C - C).norm(dim=1).max()


def frame_tilt_deg(model, cams) -> float:
    """The median tilt between a model's frame and the truth's, from each camera's rotation: W = R_model^T
    R_true takes the truth's world to the model's; its tilt is the angle it turns the vertical by (a turn
    about the vertical, which the water cannot fix, is left out)."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(model))
    tilts = []
    for i in rec.reg_image_ids():
        im = rec.images[i]
        W = im.cam_from_world().rotation.matrix().T @ cams[int(im.name[:4])].R
        tilts.append(np.degrees(np.arccos(np.clip(W[2, 2], -1, 1))))
    return float(np.median(tilts))


@pytest.fixture(scope="session")
def channel_geotagged(tmp_path_factory):
    """`conftest.channel_scene` (a channel between dry banks) seen by the same flight, made into a survey by
    the generator with consumer GPS at this flight's scale."""
    root = tmp_path_factory.mktemp("channel")
    water = WaterSurface(0.0, 1.33)
    cams = survey_cameras(lines_along_x=True)
    write_dataset(root, render_views(channel_scene(6), cams, water), water)
    poses = [Pose(f"{i:04d}", "nadir" if i < 12 else "oblique30", "train", c) for i, c in enumerate(cams)]
    write_survey(root, poses, WaterSpec(), noise=SurveyNoise(horizontal=0.005, vertical=0.008), origin=ORIGIN,
                 gps=CONSUMER)
    return root, cams


def test_consumer_gps_is_levelled_by_the_water_unless_the_barometer_holds_it(channel_geotagged, tmp_path,
                                                                              capsys, monkeypatch):
    """Consumer GPS heights fix no tilt (its lines' biases over a few metres of baseline): without the
    barometer's heights (photos with no RelativeAltitude) and with no level given, the water's plane is
    estimated with its slope in the adjustment through the water and the frame is levelled by it, the
    model's surface then level. On `small`'s 87 photos that took the frame's tilt to 0.12 degrees
    (docs/survey.md); on these 18 photos the plane is fixed to about a degree only (its sigma with the
    cameras held reads 0.14 degrees), about the GPS's own tilt here, so the test asks no worse. With the
    barometer's heights the positions hold the tilt: the level alone is estimated and nothing is levelled."""
    root, cams = channel_geotagged
    tilt, water = {}, {}
    read = exif.read_photo
    for name in ("given", "auto", "barometer", "held"):
        argv = survey_args(root, layout.SURVEY_IMAGES_GPS, tmp_path / name)
        argv[argv.index("--stop-after") + 1] = "water"
        if name == "barometer":
            monkeypatch.setattr(exif, "read_photo", read)
            argv += BAROMETER
        else:
            monkeypatch.setattr(exif, "read_photo", lambda path: replace(read(path), relative_altitude=None))
        if name == "held":  # GPS heights said to be good to 1 cm: they forbid a turn of a degree
            argv += ["--gps-sigma", "2", "0.01"]
        if name != "given":
            del argv[argv.index("--water-level"): argv.index("--water-level") + 2]
            shutil.copytree(tmp_path / "given" / "sfm", tmp_path / name / "sfm")  # the same photos' model
            for kept in (".ragsplat", "stages.json"):
                shutil.copy(tmp_path / "given" / kept, tmp_path / name / kept)
        assert main(argv) == 0, capsys.readouterr().err
        tilt[name] = frame_tilt_deg(tmp_path / name / "model", cams)
        water[name] = json.loads((tmp_path / name / "water.json").read_text())
    estimated = water["auto"]["estimated"]
    assert estimated["free"] == ["level", "slope"] and estimated["levelled_deg"] > 0.5
    assert "slope" not in water["auto"]["surface"] and estimated["frame"] == "consumer GPS (metres)"
    assert 0 < estimated["sigma_given_cameras_m"]["level"] < 0.02 < estimated["sigma_m"]["level"]
    assert tilt["given"] > 0.5 and tilt["auto"] < tilt["given"] + 0.1, tilt
    estimated = water["barometer"]["estimated"]
    assert estimated["free"] == ["level"] and "levelled_deg" not in estimated and "fall" not in estimated
    assert estimated["frame"] == "held by the barometer's heights (decimetres)"
    # the frame's height is still the GPS's (metres): the level's sigma that matters is relative to the bed
    from ragsplat.survey.stages.water import level_sigma

    assert estimated["relative_level"] and level_sigma(estimated) == (estimated["sigma_to_bed_m"], True)
    assert 0 < estimated["sigma_to_bed_m"] < 0.05 < estimated["sigma_m"]["level"]
    assert tilt["barometer"] < 0.3, tilt  # 0.16 degrees measured, against 0.93 from the GPS heights
    estimated = water["held"]["estimated"]
    refused = estimated["slope_refused"]
    assert estimated["free"] == ["level"] and "levelled_deg" not in estimated
    # the frame stays where the GPS heights (0.2 m off by line here) hold it: 1.8 degrees measured
    assert math.hypot(*refused["slope"]) > refused["allowed"] and tilt["held"] > 0.5
    assert "not levelled by the water's plane" in capsys.readouterr().err


def test_the_renderers_lens_polynomial_is_the_radial_model():
    """`ragsplat.datagen.survey.lens_polynomial`: the ray Cycles' polynomial lens sends through each sensor
    point, out to the corners, lands where COLMAP's RADIAL model with the pinhole's focal length puts it,
    within 0.05 px; with k = 0 it is the pinhole. (Rendered markers land there too:
    tests/test_blender_markers.py.)"""
    from ragsplat.datagen.survey import lens_polynomial

    for cam in (Camera(256, 256, 182.8, 182.8, 128.0, 128.0, np.eye(3), np.zeros(3)),
                Camera(240, 180, 150.0, 150.0, 120.0, 90.0, np.eye(3), np.zeros(3))):
        mm = 36.0 / max(cam.width, cam.height)
        r_s = np.linspace(0, math.hypot(cam.width, cam.height) / 2 * mm, 200)  # sensor mm, out to a corner
        for k1, k2 in (LENS, (0.0, 0.0)):
            k = lens_polynomial(cam, k1, k2)
            assert len(k) == 5 and k[0] == 0.0
            theta = -np.polyval(k[::-1], r_s)  # the ray's angle from the axis
            r = np.tan(theta)  # undistorted, normalised
            landed = cam.fx * r * (1 + k1 * r**2 + k2 * r**4)  # pixels from the centre, by the model
            np.testing.assert_allclose(landed, r_s / mm, atol=0.05)


def test_a_lens_distortion_is_estimated_from_the_photos(geotagged, tmp_path, capsys):
    """The generator's survey/images-lens/ (the RTK photos through `LENS`): the adjustment through the water
    estimates the distortion to a fraction of a pixel across the photo (k1 and k2 trade against each other
    over this 60-degree view: -0.065 / 0.002 against -0.08 / 0.02 gives the same curve within 0.3 px), and
    the model's cameras carry it for the import to undistort by."""

    root, cams = geotagged
    out = tmp_path / "run"
    argv = survey_args(root, layout.SURVEY_IMAGES_LENS, out)
    argv[argv.index("--stop-after") + 1] = "water"
    assert main(argv) == 0, capsys.readouterr().err
    lens = json.loads((out / "water.json").read_text())["lens"]
    r = np.linspace(0, math.hypot(120, 90) / cams[0].fx, 50)  # out to the corners, normalised
    shift = lambda k1, k2: cams[0].fx * r * (k1 * r**2 + k2 * r**4)  # pixels from the pinhole
    assert np.abs(shift(lens["k1"], lens["k2"]) - shift(*LENS)).max() < 0.5 < np.abs(shift(*LENS)).max(), lens
    import pycolmap

    cams = pycolmap.Reconstruction(str(out / "model")).cameras.values()
    assert all(c.model == pycolmap.CameraModelId.RADIAL and c.params[3] == lens["k1"] for c in cams)
    assert "nadir_only" not in lens  # six obliques at 30 degrees

    # that lens held on the nadir photos alone (`--lens WATER.json`): as it was, said where from
    nadir = tmp_path / "nadir"
    nadir.mkdir()
    for photo in sorted((root / layout.SURVEY_IMAGES_LENS).iterdir())[:12]:
        shutil.copy(photo, nadir / photo.name)
    held = tmp_path / "held"
    argv = survey_args(root, layout.SURVEY_IMAGES_LENS, held, "--lens", str(out / "water.json"))
    argv[1], argv[argv.index("--stop-after") + 1] = str(nadir), "water"
    assert main(argv) == 0, capsys.readouterr().err
    said = capsys.readouterr().err
    assert f"k1 {lens['k1']:+.4f}, k2 {lens['k2']:+.4f}, held from {out / 'water.json'}" in said
    again = json.loads((held / "water.json").read_text())["lens"]
    assert (again["k1"], again["k2"], again["held"]) == (lens["k1"], lens["k2"], str(out / "water.json"))
    assert "sigma" not in again and "nadir_only" not in again
    cams = pycolmap.Reconstruction(str(held / "model")).cameras.values()
    assert all(c.model == pycolmap.CameraModelId.RADIAL and tuple(c.params[3:]) == (lens["k1"], lens["k2"])
               for c in cams)

    # estimated from those nadir photos instead: said to be open to doming (the structure from motion reused)
    estimated = tmp_path / "estimated"
    shutil.copytree(held / "sfm", estimated / "sfm")
    for name in (".ragsplat", "stages.json"):
        shutil.copy(held / name, estimated / name)
    argv[argv.index("--out") + 1] = str(estimated)
    del argv[argv.index("--lens"): argv.index("--lens") + 2]
    assert main(argv) == 0, capsys.readouterr().err
    assert "degrees of nadir and no ground control" in capsys.readouterr().err
    nadir_only = json.loads((estimated / "water.json").read_text())["lens"]["nadir_only"]
    assert nadir_only["off_nadir_max_deg"] < 3  # rendered looking straight down


def test_a_lens_estimated_from_nadir_photos_alone_is_said_to_be_open_to_doming():
    """Cameras all within `NADIR_ONLY_DEG` of straight down: the line says the lens and a dome trade, and
    what separates them."""
    from scipy.spatial.transform import Rotation

    from ragsplat.survey.stages import water

    down = np.diag([1.0, -1.0, -1.0])  # cam_from_world of a camera looking straight down
    tilted = lambda deg: Rotation.from_euler("x", deg, degrees=True).as_matrix() @ down
    R = torch.as_tensor(np.stack([down, tilted(4.0), tilted(-7.0)]))
    assert water._off_nadir_deg(R) == pytest.approx(7.0)
    assert water._off_nadir_deg(torch.as_tensor(np.stack([down, tilted(20.0)]))) == pytest.approx(20.0)
    said = water._say_lens({"k1": -0.01, "k2": 0.001, "nadir_only": {"off_nadir_max_deg": 7.0}})
    assert "within 7.0 degrees of nadir" in said and "fly obliques" in said and "--lens WATER.json" in said


def test_a_lens_file_is_read_or_refused(tmp_path):
    from ragsplat.survey.stages.inputs import read_lens

    (tmp_path / "water.json").write_text(json.dumps({"surface": {}, "lens": {"k1": -0.08, "k2": 0.02}}))
    (tmp_path / "lens.json").write_text(json.dumps({"k1": 0.01, "k2": 0}))
    assert read_lens(tmp_path / "water.json") == (-0.08, 0.02)
    assert read_lens(tmp_path / "lens.json") == (0.01, 0.0)
    for text in ('{"surface": {}}', "[1, 2]", "not json", '{"k1": "x", "k2": 0}', '{"k1": NaN, "k2": 0}'):
        (tmp_path / "bad.json").write_text(text)
        with pytest.raises(ConfigError, match="bad.json"):
            read_lens(tmp_path / "bad.json")


def test_neighbour_pairs_each_photo_with_its_nearest():
    from ragsplat.survey.sfm import neighbour_pairs

    rng = np.random.default_rng(0)
    centres = np.column_stack([rng.uniform(0, 200, 300), rng.uniform(0, 40, 300), rng.uniform(20, 21, 300)])
    pairs = neighbour_pairs(centres, 10)
    assert (pairs[:, 0] < pairs[:, 1]).all() and len(np.unique(pairs, axis=0)) == len(pairs)
    assert 300 * 10 / 2 <= len(pairs) <= 300 * 10  # linear in the photos, not 44 850
    d = np.linalg.norm(centres[:, None, :2] - centres[None, :, :2], axis=-1)
    np.fill_diagonal(d, np.inf)
    nearest = np.argsort(d, axis=1)[:, :10]
    listed = {tuple(p) for p in pairs.tolist()}
    assert all((min(i, j), max(i, j)) in listed for i in range(300) for j in nearest[i])
    far = d[pairs[:, 0], pairs[:, 1]]
    assert far.max() < 30  # none reaches across the reach
    assert len(neighbour_pairs(centres[:8], 10)) == 28  # a few photos: every pair


def test_a_large_survey_matches_neighbours_not_every_pair(geotagged, tmp_path, capsys, monkeypatch):
    """Above `EXHAUSTIVE_MAX` photos, each is matched with its nearest by the photos' positions (here the
    limits lowered to this 18-photo survey): fewer pairs, every photo still registered; the pairs and each
    stage's time reported."""
    from ragsplat.survey import sfm

    root, _ = geotagged
    monkeypatch.setattr(sfm, "EXHAUSTIVE_MAX", 10)
    monkeypatch.setattr(sfm, "NEIGHBOURS", 8)
    out = tmp_path / "run"
    argv = survey_args(root, layout.SURVEY_IMAGES, out)
    argv[argv.index("--stop-after") + 1] = "sfm"
    assert main(argv) == 0
    err = capsys.readouterr().err
    timings = json.loads((out / "sfm" / "timings.json").read_text())
    assert "each photo matched with its 8 nearest" in err and f"{timings['pairs']} pairs matched" in err
    assert 18 * 8 / 2 <= timings["pairs"] < 18 * 17 / 2
    assert "18 of 18 photos registered" in err
    assert (out / "sfm" / "pairs.txt").read_text().count("\n") == timings["pairs"]


def test_coarse_photos_train_with_the_surfels_centre_z_unless_told():
    """A consumer drone's mapping flight (5.8 cm a pixel at 40 m with the benchmark's FC300S photos) trains
    as the long preset does; `small`'s 2.3 cm keep the preset's ray z; --surfel-depth and a preset's own
    choice stand; a variant without surfels is left alone."""
    from ragsplat.survey.stages.training import COARSE_GSD, surfel_depth_for

    assert surfel_depth_for("small", "2dgs+full", None, 0.058) == "centre"
    assert surfel_depth_for("small", "2dgs+full", None, 0.023) is None
    assert surfel_depth_for("small", "2dgs+full", None, COARSE_GSD) is None  # coarser than, not at
    assert surfel_depth_for("small", "2dgs+full", "ray", 0.058) == "ray"
    assert surfel_depth_for("long", "2dgs+full", None, 0.058) is None  # its own centre's z
    assert surfel_depth_for("small", "3dgs", None, 0.058) is None
