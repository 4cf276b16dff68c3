"""`ragsplat score`: a bed from any software (DEM GeoTIFF, LAS/LAZ, PLY, CSV) on the ground truth's nodes,
scored as `ragsplat.eval.evaluate.score_grid` scores a grid: an exported DEM as its grid; points on the true
bed + 2 cm with a +2 cm bias in every file kind; a depth band as the elevation band; files in the dataset's
UTM frame or in another CRS on the same cells; a file elsewhere refused in one line."""

import json
import shutil

import laspy
import numpy as np
import pytest
from rasterio.warp import transform

from ragsplat.cli.main import main
from ragsplat.dataset import layout, rasters
from ragsplat.dataset.load import load_dataset
from ragsplat.eval.evaluate import score_grid
from ragsplat.export import Bed, Georef, write_dem
from ragsplat.water_surface import WaterSurface

OFFSET = (500_000.012, 5_000_000.037, 100.0)  # not on multiples of the 5 cm cells
WATER = WaterSurface(0.0, 1.33)  # the evaluable dataset's (conftest)
UP = 0.02  # m: the points above the true bed, between 1 % and 3 % of the 1.08 m maximum depth


@pytest.fixture(scope="module")
def utm_dataset(evaluable_dataset, tmp_path_factory):
    """The evaluable dataset georeferenced in UTM zone 33N with `OFFSET`."""
    root = tmp_path_factory.mktemp("utm") / "data"
    shutil.copytree(evaluable_dataset, root)
    meta = json.loads((root / layout.TRANSFORMS).read_text())
    meta["georef"] = {"offset": list(OFFSET), "crs": "EPSG:32633"}
    (root / layout.TRANSFORMS).write_text(json.dumps(meta))
    return root


def truth_of(data):
    return load_dataset(data, splits=(), ground_truth=True).ground_truth


def score(file, data, *options) -> dict:
    out = file.with_name(file.name + ".json")
    assert main(["score", str(file), "--truth", str(data), "--out", str(out), *options]) == 0
    return json.loads(out.read_text())


def assert_same(got, expected, atol: float, where: str = "") -> None:
    """Every figure of two scores (nested dicts) equal, floats to `atol`."""
    if isinstance(expected, dict):
        assert sorted(got) == sorted(expected), where
        for key in expected:
            assert_same(got[key], expected[key], atol, f"{where}/{key}")
    elif isinstance(expected, (list, tuple)):
        assert len(got) == len(expected), where
        for k, (a, b) in enumerate(zip(got, expected)):
            assert_same(a, b, atol, f"{where}/{k}")
    elif isinstance(expected, float) and got is not None:
        np.testing.assert_allclose(got, expected, rtol=0, atol=atol, err_msg=where)
    else:
        assert got == expected, where


def bed(x, y):  # the evaluable dataset's bed (conftest)
    return -1.0 + 0.1 * np.sin(2.0 * x) * np.cos(1.5 * y)


def raised() -> np.ndarray:
    """[625, 3] the bed + `UP` on the truth's 5 cm lattice, 10 cm beyond its edges (so that the TIN covers
    its edge nodes), one point (the centre) a 1 m spike: what the outlier filter removes."""
    x, y = (a.ravel() for a in np.meshgrid(np.arange(-12, 13) * 0.05, np.arange(-12, 13) * 0.05))
    pts = np.column_stack([x, y, bed(x, y) + UP])
    pts[len(pts) // 2, 2] += 1.0
    return pts


def write_laz(path, pts: np.ndarray, crs: str | None = None) -> None:
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = np.full(3, 1e-6), np.floor(pts.min(0))
    if crs is not None:
        header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(Georef(crs=crs).wkt()))
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts.T
    las.write(path)


def write_csv(path, pts: np.ndarray) -> None:  # the columns in another order, and one more
    rows = [f"{k},{z!r},{x!r},{y!r}" for k, (x, y, z) in enumerate(pts)]
    path.write_text("\n".join(["id, Z, x, y", *rows]) + "\n")


def test_an_exported_dem_scores_as_its_grid(evaluable_dataset, tmp_path, capsys):
    truth = truth_of(evaluable_dataset)
    g = truth.grid
    grid = np.column_stack([g[:, :2], g[:, 2] + 0.03 * np.sin(7 * g[:, 0])])[np.arange(len(g)) % 7 != 3]
    write_dem(tmp_path / "bed.tif", Bed(grid, 0.05, WATER, Georef()))  # as `ragsplat export --dem` writes it
    result = score(tmp_path / "bed.tif", evaluable_dataset)
    assert_same(result["geometry"], score_grid(grid, truth), atol=1e-6)  # float32 heights near 1 m
    assert (result["kind"], result["band"], result["cells"]) == ("DEM", 1, len(grid))
    assert result["wet_nodes_covered"] == len(grid) and result["frame"] == "the dataset's local frame"
    assert result["dataset_fingerprint"] and "oracle plane" in result["references"]
    assert (tmp_path / "bed.tif_error.png").is_file()
    out = capsys.readouterr().out
    assert "| bed.tif | DEM |" in out and "| oracle plane (uses GT) |" in out and "add --references" in out


def test_a_depth_band_scores_as_the_elevation_band(evaluable_dataset, tmp_path):
    truth = truth_of(evaluable_dataset)
    # band 2: the depth below the water
    write_dem(tmp_path / "bed.tif", Bed(truth.grid + [0, 0, UP], 0.05, WATER, Georef()))
    elevation = score(tmp_path / "bed.tif", evaluable_dataset)
    depth = score(tmp_path / "bed.tif", evaluable_dataset, "--band", "2", "--kind", "depth")
    assert_same(depth["geometry"], elevation["geometry"], atol=1e-6)
    assert depth["values"] == "depth" and depth["band"] == 2
    assert elevation["geometry"]["survey"]["wet"]["bias"] == pytest.approx(UP, abs=1e-6)
    wrong = score(tmp_path / "bed.tif", evaluable_dataset, "--band", "2")  # depths read as heights
    assert wrong["geometry"]["survey"]["wet"]["bias"] > 1.5


def test_points_on_the_bed_plus_2_cm_score_a_2_cm_bias_in_every_file_kind(evaluable_dataset, tmp_path):
    truth = truth_of(evaluable_dataset)
    np.testing.assert_allclose(truth.grid[:, 2], bed(*truth.grid[:, :2].T), rtol=0, atol=1e-12)
    pts = raised()
    write_laz(tmp_path / "bed.laz", pts)
    write_csv(tmp_path / "bed.csv", pts)
    layout.write_ply(tmp_path / "bed.ply", pts)  # binary doubles
    (tmp_path / "ascii.ply").write_text(
        f"ply\nformat ascii 1.0\nelement vertex {len(pts)}\nproperty float intensity\nproperty double x\n"
        "property double y\nproperty double z\nelement face 0\nproperty list uchar int vertex_indices\n"
        "end_header\n" + "".join(f"7 {x!r} {y!r} {z!r}\n" for x, y, z in pts))
    laz = score(tmp_path / "bed.laz", evaluable_dataset)
    assert laz["kind"] == "LAS" and laz["points"] == laz["points_near"] == len(pts)
    assert laz["wet_nodes_covered"] == len(truth.grid)
    geometry = laz["geometry"]
    assert geometry["survey"]["wet"]["bias"] == pytest.approx(UP, abs=0.001)
    assert geometry["f1"]["3%"] == 1.0 and geometry["f1"]["1%"] == 0.0 and geometry["f1"]["10cm"] == 1.0
    assert_same(geometry, score_grid(truth.grid + [0, 0, UP], truth), atol=0.001)  # the spike filtered out
    for other in ("bed.csv", "bed.ply", "ascii.ply"):  # LAS keeps 1e-6 m
        assert_same(score(tmp_path / other, evaluable_dataset)["geometry"], geometry, atol=1e-5)
    spiked = score(tmp_path / "bed.laz", evaluable_dataset, "--no-filter")
    assert spiked["filter"] is None and spiked["geometry"]["survey"]["wet"]["bias"] > UP + 0.002
    assert spiked["geometry"]["f1"]["3%"] < 1.0


def test_utm_files_and_another_crs_land_on_the_same_cells(utm_dataset, evaluable_dataset, tmp_path, capsys):
    truth = truth_of(utm_dataset)
    grid = truth.grid + [0, 0, UP]
    # a DEM in the dataset's CRS, the offset not taken off (`ragsplat export` of a survey)
    write_dem(tmp_path / "utm.tif", Bed(grid, 0.05, WATER, Georef(OFFSET, "EPSG:32633")))
    result = score(tmp_path / "utm.tif", utm_dataset)
    assert result["crs"] == "EPSG:32633" and result["frame"] == "the dataset's CRS, its offset taken off"
    assert_same(result["geometry"], score_grid(grid, truth), atol=1e-5)  # float32 heights at 100 m
    higher = Georef((*OFFSET[:2], OFFSET[2] + 0.05), "EPSG:32633")
    write_dem(tmp_path / "high.tif", Bed(grid, 0.05, WATER, higher))
    high = score(tmp_path / "high.tif", utm_dataset)["geometry"]["survey"]["wet"]["bias"]
    assert high == pytest.approx(UP + 0.05, abs=1e-5)  # the dataset's z0 is what is taken off
    assert main(["score", str(tmp_path / "utm.tif"), "--truth", str(evaluable_dataset)]) == 2  # local frame
    capsys.readouterr()

    # points without a CRS in absolute coordinates: the offset taken off, as local points in the local frame
    pts = raised()
    write_csv(tmp_path / "local.csv", pts)
    write_csv(tmp_path / "absolute.csv", pts + OFFSET)
    absolute = score(tmp_path / "absolute.csv", utm_dataset)
    assert absolute["frame"] == "the dataset's frame with its offset, taken off"
    local = score(tmp_path / "local.csv", utm_dataset)
    assert local["frame"] == "the dataset's local frame"
    assert_same(absolute["geometry"], local["geometry"], atol=1e-6)

    # the same points in Web Mercator: reprojected onto the same nodes
    x, y = transform("EPSG:32633", "EPSG:3857", pts[:, 0] + OFFSET[0], pts[:, 1] + OFFSET[1])
    write_laz(tmp_path / "mercator.laz", np.column_stack([x, y, pts[:, 2] + OFFSET[2]]), "EPSG:3857")
    mercator = score(tmp_path / "mercator.laz", utm_dataset)
    assert mercator["frame"].startswith("reprojected from EPSG:3857")
    assert_same(mercator["geometry"], local["geometry"], atol=1e-5)

    # a DEM in Web Mercator at 4 cm (not the truth's lattice) of a plane: bilinear at the nodes = the plane
    def plane(xy):
        return -1.0 + 0.05 * xy[:, 0] - 0.03 * xy[:, 1]

    nodes = truth.nodes[:, :2]
    corners = np.column_stack(transform("EPSG:32633", "EPSG:3857", nodes[[0, -1], 0] + OFFSET[0],
                                        nodes[[0, -1], 1] + OFFSET[1]))
    lo, hi = corners.min(0) - 0.2, corners.max(0) + 0.2
    cx, cy = np.meshgrid(np.arange(lo[0], hi[0], 0.04), np.arange(lo[1], hi[1], 0.04))
    cells = np.column_stack([cx.ravel(), cy.ravel()])
    local_xy = np.column_stack(transform("EPSG:3857", "EPSG:32633", cells[:, 0], cells[:, 1])) - OFFSET[:2]
    rasters.write_raster(tmp_path / "plane.tif", cells, [(plane(local_xy) + OFFSET[2], "z")], 0.04,
                        crs="EPSG:3857")
    result = score(tmp_path / "plane.tif", utm_dataset)
    assert result["nodes_covered"] == len(nodes)
    assert_same(result["geometry"], score_grid(np.column_stack([nodes, plane(nodes)]), truth), atol=1e-5)
    wrong_crs = ["--crs", "EPSG:32633"]  # Web Mercator's numbers taken as UTM's: elsewhere
    assert main(["score", str(tmp_path / "plane.tif"), "--truth", str(utm_dataset), *wrong_crs]) == 2


def test_the_references_option_adds_the_tracks_rows(evaluable_dataset, tmp_path, monkeypatch, capsys):
    from ragsplat.eval.ablation import TrainEval

    truth = truth_of(evaluable_dataset)
    monkeypatch.setattr(TrainEval, "track_grids", lambda self, log: {"triangulation (refracted)": truth.grid})
    write_csv(tmp_path / "bed.csv", raised())
    result = score(tmp_path / "bed.csv", evaluable_dataset, "--references")
    assert result["references"]["triangulation (refracted)"]["f1"]["1%"] == 1.0
    out = capsys.readouterr().out
    assert "| triangulation (refracted) | TIN |" in out and "add --references" not in out
    # a dataset without held-out views (a stretch of the long reach): the tracks read the training views only
    shutil.copytree(evaluable_dataset, tmp_path / "no-test")
    meta = json.loads((tmp_path / "no-test" / layout.TRANSFORMS).read_text())
    meta["frames"] = [f for f in meta["frames"] if f.get("split") != "test"]
    (tmp_path / "no-test" / layout.TRANSFORMS).write_text(json.dumps(meta))
    result = score(tmp_path / "bed.csv", tmp_path / "no-test", "--references")
    assert result["references"]["triangulation (refracted)"]["f1"]["1%"] == 1.0


@pytest.mark.parametrize("name, text, message", [
    ("far.csv", None, "covers 0 of the ground truth's 441 wet cells (fewer than 1%): another place or"),
    ("bed.xyz", "1 2 3\n", "unknown bed file kind '.xyz'"),
    ("noz.csv", "x,y,height\n0,0,-1\n", "a CSV of points needs a header naming x, y and z columns"),
])
def test_a_file_elsewhere_or_unknown_is_refused_in_one_line(evaluable_dataset, tmp_path, capsys, name, text,
                                                             message):
    path = tmp_path / name
    if text is None:
        write_csv(path, raised() + [1000.0, 0, 0])  # a kilometre east
    else:
        path.write_text(text)
    assert main(["score", str(path), "--truth", str(evaluable_dataset)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"ragsplat score: error: {path}: ") and message in err and err.count("\n") == 1
    assert not list(tmp_path.glob("*.json")) and not list(tmp_path.glob("*.png"))


def test_a_dem_off_the_truth_s_lattice_keeps_its_cells_at_a_hole_s_edge():
    from rasterio.transform import from_origin

    from ragsplat.eval.score_file import dem_at

    values = np.arange(16, dtype=float).reshape(4, 4)  # cell (row r, col c) holds 4 r + c
    values[1, 1] = np.nan  # one empty cell
    tf = from_origin(0.0, 4.0, 1.0, 1.0)  # 1 m cells, north up: cell (r, c) spans x c..c+1, y 3-r..4-r
    xy = np.array([[2.8, 1.8],  # between four covered centres: bilinear
                   [1.3, 2.3],  # in the empty cell: a hole
                   [2.2, 2.2],  # in cell (1, 2), beside the hole: that cell's value, not a new hole
                   [0.5, 3.5]])  # on a centre: that cell
    z, read = dem_at(values, tf, xy)
    assert read.tolist() == [True, False, True, True]
    # the plane 4 r + c at centres r = 3.5 - y, c = x - 0.5
    assert z[0] == pytest.approx(4 * (3.5 - 1.8) + (2.8 - 0.5))
    assert z[2] == values[1, 2] and z[3] == values[0, 0]
