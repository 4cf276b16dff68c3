"""Orthophotos (`ragsplat.ortho`, `ragsplat export --ortho`): the far pinhole draws each cell at its centre
and a point off the reference height within its parallax bound; a plane of two colours comes out with its
edge where it lies, north up; the mosaic reads a photo of a known plane back at each cell and puts a wet bed
at its apparent height; the tiles' orthophotos merge; a finished run's orthophotos share the DEM's grid."""

import math

import numpy as np
import pytest
import rasterio
import torch
from conftest import tiny_bed_run

from ragsplat.camera import Camera
from ragsplat.cli.main import main
from ragsplat.dataset import layout, rasters
from ragsplat.export import merge_orthophotos
from ragsplat.gaussians import init_grid, rgb_to_sh
from ragsplat.ortho import (
    NADIR,
    ORTHO_PARALLAX,
    TILE_PX,
    OrthoGrid,
    _project,
    apparent_mosaic,
    bed_orthophoto,
    far_height,
    mosaic_height,
    ortho_tiles,
)
from ragsplat.rendering import render_splats
from ragsplat.water_surface import WaterSurface

GRID = OrthoGrid(west=-3.0, north=2.0, step=0.05, width=1100, height=700)  # several tiles each way


def whole_image_pixel(rows, cols, cam, points):
    uv, seen = _project(cam, points)
    return uv + np.array([cols.start, rows.start]), seen


def test_the_far_pinhole_draws_each_cell_at_its_centre_and_relief_within_its_bound():
    reference, relief = -1.0, 1.5
    tiles = ortho_tiles(GRID, reference, relief)
    assert len(tiles) == math.ceil(700 / TILE_PX) * math.ceil(1100 / TILE_PX)
    x, y = GRID.centres()
    for rows, cols, cam in tiles:
        # every cell centre of the tile at the reference height: exactly at its pixel's centre
        jj, ii = np.meshgrid(np.arange(cols.start, cols.stop), np.arange(rows.start, rows.stop))
        pts = np.column_stack([x[jj.ravel()], y[ii.ravel()], np.full(jj.size, reference)])
        uv, _ = whole_image_pixel(rows, cols, cam, pts)
        np.testing.assert_allclose(uv, np.column_stack([jj.ravel() + 0.5, ii.ravel() + 0.5]), atol=1e-6)
    # the farthest corner, `relief` above and below: off by at most ORTHO_PARALLAX cells
    for dz in (relief, -relief):
        rows, cols, cam = tiles[-1]
        corner = np.array([[x[-1], y[-1], reference + dz]])
        uv, _ = whole_image_pixel(rows, cols, cam, corner)
        off = np.abs(uv[0] - [GRID.width - 0.5, GRID.height - 0.5]).max()
        assert 0.5 * ORTHO_PARALLAX < off <= ORTHO_PARALLAX * 1.01
    assert far_height(GRID, 0.0) == 100.0  # a flat grid: the least height


def two_colour_plane(edge_x, z=-1.0):
    """Gaussians 2 cm apart on a plane at `z`, red west of x = edge_x and blue east of it (raw parameters)."""
    splats = init_grid(-3.2, 2.8, -1.6, 2.2, z, 0.02, degree=0, opacity=0.99)
    with torch.no_grad():
        splats["scales"].fill_(math.log(0.012))
        splats["scales"][:, 2] = math.log(1e-3)
        east = splats["means"][:, 0] > edge_x
        rgb = torch.where(east[:, None], torch.tensor([0.1, 0.2, 0.9]), torch.tensor([0.9, 0.2, 0.1]))
        splats["sh0"].copy_(rgb_to_sh(rgb)[:, None, :])
    return splats


def test_a_plane_of_two_colours_comes_out_north_up_with_its_edge_where_it_lies():
    edge = 0.34  # between the Gaussians at 0.33 and 0.35; 1.5 cm east of the centre of the cell at 0.325
    splats = two_colour_plane(edge)
    background = torch.zeros(3)

    def render(cam):
        centre = torch.tensor(cam.camera_center, dtype=torch.float32)
        img, alpha, _, _ = render_splats(splats, cam, centre, 0, None, None, False, background, "torch")
        return img, alpha

    grid = OrthoGrid(west=-2.0, north=1.0, step=0.05, width=60, height=30)
    rgba = bed_orthophoto(render, grid, -1.0, 0.0, samples=3)  # Gaussians of 2 cm in cells of 5
    assert rgba.shape == (30, 60, 4) and rgba[..., 3].min() > 0.95
    x, _ = grid.centres()
    red = rgba[..., 0] > rgba[..., 2]  # [H, W]
    assert (red == (x < edge)[None, :]).all()


def plane_photo(cam: Camera, z: float) -> np.ndarray:
    """The photo [h, w, 3] uint8 of a plane at height `z` whose red channel is 20 x (its x + 5) and green 20 x
    (its y + 5), each pixel centre's ray traced to it (no water)."""
    jj, ii = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    rays = np.stack([(jj - cam.cx) / cam.fx, (ii - cam.cy) / cam.fy, np.ones_like(jj)], -1) @ cam.R  # world
    centre = cam.camera_center
    s = (z - centre[2]) / rays[..., 2]
    hit = centre + s[..., None] * rays
    return np.stack([20 * (hit[..., 0] + 5), 20 * (hit[..., 1] + 5), np.zeros_like(jj)], -1).round() \
        .clip(0, 255).astype(np.uint8)


def test_the_mosaic_reads_a_plane_back_at_each_cell_from_the_nearest_photo_that_sees_it():
    z = -1.0
    cams = [Camera(200, 150, 180.0, 180.0, 100.0, 75.0, NADIR, -NADIR @ np.array([cx, 0.3, 4.0]))
            for cx in (-1.5, 1.5)]
    photos = [(c, plane_photo(c, z)) for c in cams]
    grid = OrthoGrid(west=-3.0, north=1.5, step=0.1, width=60, height=30)
    bed = np.full((grid.height, grid.width), z)
    bed[0, 0] = np.nan  # no height: not drawn
    rgba = apparent_mosaic(photos, grid, bed, None)
    x, y = grid.centres()
    xx, yy = np.meshgrid(x, y)
    drawn = rgba[..., 3] > 0
    assert not drawn[0, 0] and drawn.mean() > 0.9
    np.testing.assert_allclose(rgba[..., 0][drawn] * 255, (20 * (xx + 5))[drawn], atol=0.6)
    np.testing.assert_allclose(rgba[..., 1][drawn] * 255, (20 * (yy + 5))[drawn], atol=0.6)
    # the cells beyond both photos' footprints are left empty
    outside = np.abs(xx) > 1.5 + 4.0 * 100 / 180 + 0.1
    assert not drawn[outside].any()


def test_the_mosaic_puts_a_wet_bed_at_its_apparent_height_at_nadir():
    water = WaterSurface(0.0, 1.33)
    xy = np.zeros((3, 2))
    bed = np.array([-1.33, 0.5, 0.0])  # 1.33 m deep, a bank above the water, the water's edge
    np.testing.assert_allclose(mosaic_height(bed, water, xy), [-1.0, 0.5, 0.0], atol=1e-12)
    np.testing.assert_array_equal(mosaic_height(bed, None, xy), bed)


def test_the_tiles_orthophotos_merge_on_their_lattice(tmp_path):
    a = np.zeros((4, 10, 20), np.uint8)
    a[:, :, :12] = 200  # drawn west of column 12
    b = np.full((4, 10, 20), 100, np.uint8)
    rasters.write_rgba(tmp_path / "a.tif", a, (0.5, 0, 100.0, 0, -0.5, 50.0), layout.LOCAL_CRS, "tile")
    rasters.write_rgba(tmp_path / "b.tif", b, (0.5, 0, 105.0, 0, -0.5, 48.0), layout.LOCAL_CRS, "tile")
    merge_orthophotos([tmp_path / "a.tif", tmp_path / "b.tif"], tmp_path / "m.tif")
    with rasterio.open(tmp_path / "m.tif") as r:
        m = r.read()
        assert tuple(r.transform)[:6] == (0.5, 0, 100.0, 0, -0.5, 50.0) and m.shape == (4, 14, 30)
    np.testing.assert_array_equal(m[:, :10, :12], 200)  # the first tile's drawn pixels
    np.testing.assert_array_equal(m[:, 4:14, 12:30], 100)  # the second's where the first drew nothing
    np.testing.assert_array_equal(m[:, :4, 20:], 0)  # neither


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return tiny_bed_run(tmp_path_factory.mktemp("ortho"))


def test_a_runs_orthophotos_share_the_dems_grid(run, tmp_path, capsys):
    dem, ortho, apparent = tmp_path / "dem.tif", tmp_path / "bed.tif", tmp_path / "apparent.tif"
    assert main(["export", str(run), "--dem", str(dem), "--ortho", str(ortho), "--ortho-apparent",
                 str(apparent), "--min-opacity", "0.05", "--max-scale-gsd", "inf"]) == 0
    assert f"wrote {ortho}" in capsys.readouterr().out
    with rasterio.open(dem) as d:
        covered = d.read(1) != layout.NODATA
        transform, crs, shape = d.transform, d.crs, (d.height, d.width)
    for path in (ortho, apparent):
        with rasterio.open(path) as r:
            assert r.transform == transform and r.crs == crs and (r.height, r.width) == shape
            assert r.count == 4 and r.dtypes[0] == "uint8"
            assert [c.name for c in r.colorinterp] == list(rasters.RGBA)
            image = r.read()
        assert (image[3][covered] > 0).mean() > 0.9  # drawn over the bed
    assert (image[3][~covered] == 0).all()  # the mosaic draws only where the DEM has a height


def test_an_orthophoto_is_scored_against_the_truth_where_it_lies(evaluable_dataset, tmp_path, capsys):
    """A truth of textured blobs over the dataset's region, and orthophotos of it: the truth itself on another
    lattice scores high and unshifted; moved 2 cells east, the score finds it there (`tools.ortho_score`)."""
    import shutil

    from ragsplat.eval.ortho import score_orthophoto
    from tools.ortho_score import main as ortho_score

    data = tmp_path / "data"
    shutil.copytree(evaluable_dataset, data)
    step, west, north, size = 0.05, -0.5, 0.5, 20

    def blobs(x, y):  # [.., 3] in [0, 1], features of 5-10 cells
        grey = 0.5 + 0.2 * np.sin(13 * x + 1) * np.cos(17 * y) + 0.2 * np.sin(19 * x - 11 * y)
        return np.stack([grey, 0.8 * grey + 0.1, 0.5 + 0.3 * np.sin(9 * y - 14 * x)], -1)

    x = west + (np.arange(size) + 0.5) * step
    y = north - (np.arange(size) + 0.5) * step
    xx, yy = np.meshgrid(x, y)
    layout.write_png(data / layout.GT_ORTHO, np.round(255 * blobs(xx, yy)).astype(np.uint8))
    rasters.write_world_file(data / layout.GT_ORTHO_WORLD, step, west, north)
    layout.Surface(-2.0, 0.5, np.full((9, 9), -1.0)).save(data / layout.GT_SURFACE)  # 1 m under the water
    fine = 0.02  # the orthophoto on a finer lattice, 1 cm off the truth's
    fx = -0.61 + (np.arange(70) + 0.5) * fine
    fy = 0.61 - (np.arange(70) + 0.5) * fine
    for name, moved in (("here", 0.0), ("east", 2 * step)):
        fxx, fyy = np.meshgrid(fx, fy)
        rgba = np.concatenate([blobs(fxx - moved, fyy), np.ones(fxx.shape + (1,))], -1)
        rasters.write_rgba(tmp_path / f"{name}.tif", np.round(255 * rgba).astype(np.uint8).transpose(2, 0, 1),
                          (fine, 0, -0.61, 0, -fine, 0.61), layout.LOCAL_CRS, name)
    here, east = (score_orthophoto(tmp_path / f"{n}.tif", data) for n in ("here", "east"))
    assert here["drawn"] == 1.0 and here["psnr"] > 35 and np.abs(here["shift_cells"]).max() < 0.1
    assert abs(east["shift_cells"][0] - 2) < 0.2 and abs(east["shift_cells"][1]) < 0.2
    assert east["psnr"] < here["psnr"] - 10
    assert ortho_score([str(data), str(tmp_path / "here.tif")]) == 0
    assert "| 100.0 % |" in capsys.readouterr().out
