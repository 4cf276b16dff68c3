"""`ragsplat export`: a trained run's bed as a DEM GeoTIFF, LAS/LAZ, PLY and PNG, read back with rasterio,
laspy and numpy; a flat bed of known depth; UTM-sized coordinates; one-line errors."""

import json
import math
import shutil

import laspy
import numpy as np
import pytest
import rasterio
import torch
from conftest import tiny_bed_run
from rasterio.crs import CRS

from ragsplat import export
from ragsplat.cli.main import main
from ragsplat.dataset import load_dataset
from ragsplat.dataset.layout import LOCAL_CRS, NODATA
from ragsplat.errors import ConfigError
from ragsplat.eval.ablation import extract_config
from ragsplat.eval.evaluate import evaluate_geometry
from ragsplat.export import (
    BATHYMETRIC,
    GROUND,
    Georef,
    extract_bed,
    hillshade,
    sample_count,
    write_dem,
    write_las,
    write_ply,
)
from ragsplat.ply import save_ply
from ragsplat.runs import load_run
from ragsplat.train import preset_config
from ragsplat.water_surface import WaterSurface

REGION = {"xmin": -0.8, "xmax": 0.8, "ymin": -0.8, "ymax": 0.8}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A finished 2-iteration run on a bed 1 m under water."""
    return tiny_bed_run(tmp_path_factory.mktemp("export"))


def plane_gaussians(z, half=1.0, step=0.05) -> dict:
    """Flat discs (sigma 3 cm x 3 cm x 3 mm, opacity 0.8) on a `step` lattice over [-half, half]^2 at
    heights z(x, y): activated parameters as `load_run` returns them."""
    x, y = np.meshgrid(np.arange(-half, half + step / 2, step), np.arange(-half, half + step / 2, step))
    means = np.column_stack([x.ravel(), y.ravel(), z(x.ravel(), y.ravel())])
    n = len(means)
    return {"means": torch.tensor(means, dtype=torch.float32),
            "scales": torch.tensor([[0.03, 0.03, 0.003]] * n),
            "quats": torch.tensor([[1.0, 0, 0, 0]] * n), "opacities": torch.full((n,), 0.8)}


def read_ply(path) -> np.ndarray:
    data = path.read_bytes()
    head, body = data.split(b"end_header\n", 1)
    assert b"property double x\nproperty double y\nproperty double z\n" in head
    return np.frombuffer(body, "<f8").reshape(-1, 3)


def at_cells(tif, points: np.ndarray) -> np.ndarray:
    """[N, 2] band values (both bands) at the pixels holding absolute points [N, 2]; checks each point is
    its pixel's centre."""
    rows, cols = rasterio.transform.rowcol(tif.transform, points[:, 0], points[:, 1])
    centres = np.column_stack(rasterio.transform.xy(tif.transform, rows, cols))
    np.testing.assert_allclose(centres, points, rtol=0, atol=1e-6)
    return tif.read()[:, rows, cols].T


def test_export_writes_every_product(run, tmp_path, capsys):
    out = {k: tmp_path / f"bed.{k}" for k in ("tif", "laz", "ply", "png")}
    # 2 steps from opacity 0.1 and the start's wide Gaussians: limits they pass (the defaults are for trained
    # runs)
    assert main(["export", str(run), "--dem", str(out["tif"]), "--las", str(out["laz"]),
                 "--ply", str(out["ply"]), "--png", str(out["png"]), "--min-opacity", "0.05",
                 "--max-scale-gsd", "inf", "--despike-radius", "0.5", "--despike-tol", "0.02"]) == 0
    gaussians, ds, seed = load_run(run)
    bed = extract_bed(gaussians, 0.05, ds.water.level, ds.eval_region, seed=seed, min_opacity=0.05,
                      max_scale_gsd=math.inf, despike_radius=0.5, despike_tol=0.02)  # the same
    grid = bed.grid
    assert len(grid) > 100 and (grid[:, 2] < 0).all()  # 2 steps from the grid at -1 m: all under water
    stdout = capsys.readouterr().out
    assert (f"{len(grid)} cells of 0.05 m, {len(grid)} under water" in stdout
            and f"wrote {out['png']}" in stdout)
    with rasterio.open(out["tif"]) as tif:
        assert tif.count == 2 and tif.dtypes == ("float32", "float32") and tif.nodata == NODATA
        # GeoTIFF keeps the local frame's name
        assert tif.crs.to_wkt().startswith(LOCAL_CRS[:LOCAL_CRS.index(",")])
        assert (tif.transform.a == 0.05 and tif.transform.e == -0.05
                and tif.transform.b == tif.transform.d == 0)
        values = at_cells(tif, grid[:, :2])
        assert (tif.read(1) != NODATA).sum() == len(grid)  # nothing else is covered
    # the same extraction in one process; the DEM's float32 of z (+ a zero offset) read back losslessly
    np.testing.assert_array_equal(values[:, 0], grid[:, 2].astype(np.float32))
    np.testing.assert_allclose(values[:, 1], -grid[:, 2], rtol=0, atol=1e-6)  # level 0
    las = laspy.read(out["laz"])
    assert las.header.version == "1.4" and las.header.point_format.id == 6 and len(las.points) == len(grid)
    assert las.header.are_points_compressed
    np.testing.assert_allclose(np.column_stack([las.x, las.y, las.z]), grid, rtol=0, atol=0.0005)
    assert (las.classification == BATHYMETRIC).all()
    np.testing.assert_array_equal(read_ply(out["ply"]), grid)  # doubles: lossless
    assert out["png"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the depth band's QGIS style beside the DEM: band 2, a ramp from 0 to the deepest cell
    import xml.etree.ElementTree as ET

    style = ET.parse(out["tif"].with_suffix(".qml")).getroot()
    renderer = style.find("pipe/rasterrenderer")
    assert renderer.get("type") == "singlebandpseudocolor" and renderer.get("band") == "2"
    values = [float(i.get("value")) for i in renderer.iter("item")]
    assert values[0] == 0 and values[-1] == pytest.approx(float(-grid[:, 2].min()), abs=1e-4)  # level 0
    assert values == sorted(values)


def test_flat_bed_at_known_depth(run, tmp_path):
    flat = tmp_path / "run"
    shutil.copytree(run, flat)
    g = plane_gaussians(lambda x, y: np.full_like(x, -1.5))
    save_ply(flat / "point_cloud.ply", {"means": g["means"], "sh0": torch.zeros(len(g["means"]), 1, 3),
                                         "opacities": torch.logit(g["opacities"]),
                                        "scales": g["scales"].log(),
                                         "quats": g["quats"]})
    assert main(["export", str(flat), "--dem", str(tmp_path / "dem.tif"), "--resolution", "0.1"]) == 0
    with rasterio.open(tmp_path / "dem.tif") as tif:
        elevation, depth = tif.read()
        # the region [-0.8, 0.8]^2 at 10 cm, nodes on multiples of 10 cm: 17 x 17 cells, all covered
        assert elevation.shape == (17, 17) and tif.transform.c == pytest.approx(-0.85)
    assert np.abs(depth - 1.5).max() < 0.005 and np.abs(elevation + 1.5).max() < 0.005


def test_the_size_cap_follows_the_runs_surfel_depth(run, tmp_path, capsys):
    """A run whose surfels took the centre's z is exported without the 14 cm cap (6 pixels alone,
    `surface.SIZE_CAP_M`), one that took the ray's with it, unless the command gives the cap. Discs of
    sigma 45 cm at 11 cm a pixel: within 6 pixels (66 cm), beyond the ray's cap (its floor, 3 pixels, 33
    cm)."""
    g = plane_gaussians(lambda x, y: np.full_like(x, -1.5), step=0.1)
    g["scales"] = torch.tensor([[0.45, 0.45, 0.005]] * len(g["means"]))
    gsd = load_run(run)[1].gsd
    assert 3 * gsd < 0.45 <= 6 * gsd
    exported = {}
    for depth in ("ray", "centre"):
        folder = tmp_path / depth
        shutil.copytree(run, folder)
        save_ply(folder / "point_cloud.ply", {"means": g["means"], "sh0": torch.zeros(len(g["means"]), 1, 3),
                                               "opacities": torch.logit(g["opacities"]),
                                               "scales": g["scales"].log(), "quats": g["quats"]})
        meta = json.loads((folder / "config.json").read_text())
        meta["config"].update(variant="2dgs+full", surfel_depth=depth)
        (folder / "config.json").write_text(json.dumps(meta))
        exported[depth] = main(["export", str(folder), "--dem", str(tmp_path / f"{depth}.tif"),
                                "--resolution", "0.1"])
    assert exported == {"ray": 2, "centre": 0}  # 2: an output error (nothing to export)
    assert "no bed surface" in capsys.readouterr().err
    with rasterio.open(tmp_path / "centre.tif") as tif:
        assert np.abs(tif.read(1)[tif.read(1) != NODATA] + 1.5).max() < 0.01
    assert main(["export", str(tmp_path / "centre"), "--dem", str(tmp_path / "capped.tif"),
                 "--max-scale-m", "0.14"]) == 2  # the cap as given


def test_export_extracts_the_bed_that_eval_scores(evaluable_dataset):
    """At the evaluation's 5 cm the export samples as `ragsplat score` does (`extract_config`: 16 per node of
    the ground-truth grid, 21 x 21 here, all under water): the same bed, cell for cell (the count by area of
    before, 6 400 per m^2, drew 6 400 samples instead of 7 056: other samples, other medians)."""
    ds = load_dataset(evaluable_dataset, splits=(), ground_truth=True)
    truth = ds.ground_truth
    g = plane_gaussians(lambda x, y: -1.0 + 0.1 * np.sin(2.0 * x) * np.cos(1.5 * y))
    _, scored = evaluate_geometry(g, truth, extract_config(preset_config("small", seed=3), len(truth.grid),
                                                           ds.gsd))
    bed = extract_bed(g, 0.05, ds.water.level, ds.eval_region, seed=3, gsd=ds.gsd)
    assert len(truth.grid) == 441 and len(scored) > 400

    def by_node(grid):
        return grid[np.lexsort(np.round(grid[:, :2] / 0.05).T.astype(int))]

    np.testing.assert_allclose(by_node(bed.grid), by_node(scored), rtol=0, atol=1e-9)


def test_a_coarser_resolution_draws_fewer_samples(monkeypatch):
    """16 samples per cell of the DEM grid in the region: a quarter as many at twice the cell (with the
    noise filter's radius at 2 cells, so that 50 cm cells still make a bed), never fewer than 4 per Gaussian
    (a sample for only some of them goes to the first ones in the file), and the size check before any
    sampling, naming a resolution that passes it. The count by area of before drew 16 384 at every cell."""
    drawn = []
    real = export.extract_surface

    def spy(*args, **kwargs):
        drawn.append((args[4].n_samples, args[4].filter_radius))
        return real(*args, **kwargs)

    monkeypatch.setattr(export, "extract_surface", spy)
    g = plane_gaussians(lambda x, y: np.full_like(x, -1.5), step=0.1)  # 21 x 21 Gaussians
    for resolution, nodes, n in ((0.05, 33, 16 * 33**2), (0.1, 17, 16 * 17**2), (0.5, 3, 4 * 21**2)):
        # nodes: multiples of it in [-0.8, 0.8]
        bed = extract_bed(g, resolution, WaterSurface(0.0), REGION, gsd=0.01)
        assert drawn[-1] == (n, max(0.1, 2 * resolution)), resolution
        assert len(bed.grid) == nodes**2 and np.abs(bed.grid[:, 2] + 1.5).max() < 0.01, resolution
    # a coarse model for a coarse DEM: 9 x 9 Gaussians 10 cm wide, 324 samples, about 2 within 10 cm of each
    coarse = plane_gaussians(lambda x, y: np.full_like(x, -1.5), step=0.25)
    coarse["scales"] = torch.tensor([[0.1, 0.1, 0.003]] * len(coarse["means"]))
    # found: the noise filter looks 1 m around
    bed = extract_bed(coarse, 0.5, WaterSurface(0.0), REGION, gsd=0.05)
    assert drawn[-1] == (4 * 9**2, 1.0) and len(bed.grid) == 9 and np.abs(bed.grid[:, 2] + 1.5).max() < 0.01
    big = {"xmin": -200.0, "xmax": 200.0, "ymin": -200.0, "ymax": 200.0}  # 16 ha: 6.4e7 cells of 5 cm
    with pytest.raises(ConfigError, match=r"6.4e\+07 cells .*resolution, (\S+) m or more") as refused:
        extract_bed(g, 0.05, WaterSurface(0.0), big, gsd=0.01)
    assert len(drawn) == 4  # refused before sampling
    coarser = float(str(refused.value).split("resolution, ")[1].split(" m")[0])
    lo, hi = (-200.0, -200.0), (200.0, 200.0)
    assert sample_count(lo, hi, coarser) > 0  # passes, and not far above the finest that passes:
    with pytest.raises(ConfigError):
        sample_count(lo, hi, 0.9 * coarser)


def test_a_large_bed_is_extracted_in_blocks(monkeypatch):
    """Above `BLOCK_SAMPLES` the bed is extracted block by block (memory bounded by a block, not the area):
    the same nodes as in one pass, heights as close to the truth (other random draws, so not the same), and
    each block's own margin so that no seam shows where blocks meet."""
    g = plane_gaussians(lambda x, y: -1.0 + 0.3 * np.sin(2 * x) * np.cos(3 * y))  # 41 x 41 Gaussians
    once = extract_bed(g, 0.05, WaterSurface(0.0), REGION, gsd=0.01)
    monkeypatch.setattr(export, "BLOCK_SAMPLES", 4000)  # 15 x 15 cells a block: 3 x 3 blocks over 33 x 33
    seen = []
    blocks = extract_bed(g, 0.05, WaterSurface(0.0), REGION, gsd=0.01,
                         on_block=lambda k, n: seen.append((k, n)))
    assert seen == [(k, 9) for k in range(1, 10)]

    def by_node(grid):
        return grid[np.lexsort(np.round(grid[:, :2] / 0.05).T.astype(int))]

    a, b = by_node(once.grid), by_node(blocks.grid)
    np.testing.assert_allclose(b[:, :2], a[:, :2], rtol=0, atol=1e-9)  # every node once, none twice
    truth = -1.0 + 0.3 * np.sin(2 * b[:, 0]) * np.cos(3 * b[:, 1])
    err_once, err = np.abs(a[:, 2] - truth), np.abs(b[:, 2] - truth)
    assert np.median(err) < 1.3 * np.median(err_once) and err.max() < 0.05
    # the nodes on either side of the blocks' edges (15 cells = 0.75 m from the region's corner at -0.8)
    ij = np.rint((b[:, :2] + 0.8) / 0.05).astype(int)
    seam = ((ij % 15 == 0) | (ij % 15 == 14)).any(1) & (ij > 0).all(1) & (ij < 32).all(1)
    assert seam.sum() > 100 and np.median(err[seam]) < 1.3 * np.median(err_once)


def test_utm_offset_round_trip(tmp_path):
    # A bed sloping up through the water plane (waterline at x = 0.5) in UTM zone 33N
    x0, y0, z0 = 500_000.012, 5_000_000.037, 100.0
    georef = Georef((x0, y0, z0), "EPSG:32633")
    g = plane_gaussians(lambda x, y: 0.2 * x - 0.1)
    bed = extract_bed(g, 0.05, WaterSurface(0.0), {"xmin": -0.7, "xmax": 0.7, "ymin": -0.7, "ymax": 0.7},
                      georef, gsd=0.01)
    absolute = bed.grid + [x0, y0, z0]
    wet = bed.grid[:, 2] < 0
    assert 0.3 < wet.mean() < 0.9 and np.abs(bed.grid[:, 2] - (0.2 * bed.grid[:, 0] - 0.1)).max() < 0.01
    write_dem(tmp_path / "dem.tif", bed)
    write_las(tmp_path / "bed.las", bed)
    write_ply(tmp_path / "bed.ply", bed)
    with rasterio.open(tmp_path / "dem.tif") as tif:
        assert tif.crs == CRS.from_epsg(32633)
        nodes = (tif.transform.c + 0.025) / 0.05, (tif.transform.f - 0.025) / 0.05
        np.testing.assert_allclose(nodes, np.round(nodes), rtol=0, atol=1e-6)  # on multiples of 5 cm
        values = at_cells(tif, absolute[:, :2])  # the pixel centres are the absolute points to 1e-6 m
    np.testing.assert_allclose(values[:, 0], absolute[:, 2], rtol=0, atol=1e-4)  # float32 at 100 m
    np.testing.assert_allclose(values[wet, 1], -bed.grid[wet, 2], rtol=0, atol=1e-6)
    assert (values[~wet, 1] == NODATA).all()
    las = laspy.read(tmp_path / "bed.las")
    assert not las.header.are_points_compressed
    np.testing.assert_allclose(np.column_stack([las.x, las.y, las.z]), absolute, rtol=0, atol=0.0005)
    np.testing.assert_array_equal(las.classification, np.where(wet, BATHYMETRIC, GROUND))
    assert las.header.global_encoding.wkt
    assert CRS.from_wkt(las.header.vlrs[0].string) == CRS.from_epsg(32633)
    # the same one add; doubles: lossless
    np.testing.assert_array_equal(read_ply(tmp_path / "bed.ply"), absolute)
    with pytest.raises(ConfigError, match="CRS 'EPSG:0' is not usable"):
        Georef(crs="EPSG:0")


def test_hillshade_orientation():
    y = np.arange(5.0)[::-1, None] * np.ones(5)  # row 0 is north: z = y rises northwards (faces south)
    np.testing.assert_allclose(hillshade(y, 1.0, azimuth=180, altitude=45), 1.0)  # sun in the south, normal
    np.testing.assert_allclose(hillshade(y, 1.0, azimuth=0, altitude=45), 0.0, atol=1e-12)
    np.testing.assert_allclose(hillshade(np.zeros((3, 3)), 1.0), np.sin(np.radians(45)))
    x = np.ones(5)[:, None] * np.arange(5.0)  # z = x rises eastwards: lit from the west
    np.testing.assert_allclose(hillshade(x, 1.0, azimuth=270, altitude=45), 1.0)


def test_not_a_run_or_no_dataset_is_one_line(run, tmp_path, capsys):
    moved = tmp_path / "moved"
    shutil.copytree(run, moved)
    meta = json.loads((moved / "config.json").read_text())
    meta["dataset"] = str(tmp_path / "gone")
    (moved / "config.json").write_text(json.dumps(meta))
    changed = tmp_path / "data"
    shutil.copytree(json.loads((run / "config.json").read_text())["dataset"], changed)
    with open(changed / "transforms.json", "a") as f:
        f.write(" ")  # same cameras, other bytes
    empty = tmp_path / "empty"
    empty.mkdir()
    dem = tmp_path / "dem.tif"
    cases = [([str(empty)], "not a finished training run (no config.json"),
             ([str(tmp_path / "nowhere")], "not a finished training run"),
             ([str(moved)], f"{tmp_path / 'gone'}: the run's dataset directory does not exist"),
             ([str(run), "--data", str(changed)], f"{changed} is not the dataset {run} was trained on")]
    for argv, phrase in cases:
        assert main(["export", *argv, "--dem", str(dem)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("ragsplat export: error: ") and phrase in err[0], err
    for argv, option in ((["--las", str(tmp_path / "bed.txt")], "--las"),
                         (["--resolution", "0"], "--resolution")):
        with pytest.raises(SystemExit) as done:
            main(["export", str(run), "--dem", str(dem), *argv])
        assert done.value.code == 2 and option in capsys.readouterr().err.splitlines()[-1]
    assert not dem.exists()
