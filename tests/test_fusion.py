"""TSDF fusion of depth maps (`ragsplat.fusion`): exact depth maps of analytic height fields, cast from
a few cameras, come back as heights within a fraction of a voxel; pixels without depth change nothing."""

import numpy as np
import pytest

from ragsplat.camera import Camera
from ragsplat.errors import ConfigError
from ragsplat.fusion import (
    FuseConfig,
    Tsdf,
    fuse,
    grid_nodes,
    ground_sample,
    height_grid,
    height_mesh,
    integrate,
    z_range,
)

REGION = {"xmin": -1.0, "xmax": 1.0, "ymin": -0.8, "ymax": 0.8}
CELL = 0.05
ORIGIN = (0.0, 0.0)


def tilted(xy):
    return -1.0 + 0.15 * xy[..., 0] - 0.1 * xy[..., 1]


def wavy(xy):
    return -1.0 + 0.12 * np.sin(np.pi * xy[..., 0]) * np.cos(0.8 * np.pi * xy[..., 1])


def cameras(size=96):
    """A nadir view and four 30 degree obliques from 2.5 m, all on the region."""
    cams = [Camera.look_at([0.0, 0.0, 2.5], [0.0, 0.0, -1.0], size, size, 70.0)]
    for az in (0, 90, 180, 270):
        a = np.radians(az)
        eye = [1.6 * np.cos(a), 1.6 * np.sin(a), 2.2]
        cams.append(Camera.look_at(eye, [0.0, 0.0, -1.0], size, size, 70.0, up=(0.0, 0.0, 1.0)))
    return cams


def depth_map(cam: Camera, height) -> np.ndarray:
    """[H, W] exact z-depth of the height field z = height(x, y) at every pixel centre (bisection along the
    ray between the camera and 6 m of z-depth), 0 where the ray leaves the region first (no depth)."""
    j, i = np.mgrid[0: cam.height, 0: cam.width]
    pix = np.stack([i + 0.5, j + 0.5], -1).reshape(-1, 2).astype(float)
    c = cam.camera_center
    ray = cam.unproject(pix, np.ones(len(pix))) - c  # the point at z-depth s is c + s * ray
    lo, hi = np.full(len(pix), 1e-3), np.full(len(pix), 6.0)
    for _ in range(60):
        mid = (lo + hi) / 2
        p = c + mid[:, None] * ray
        above = p[:, 2] > height(p[:, :2])
        lo, hi = np.where(above, mid, lo), np.where(above, hi, mid)
    p = c + hi[:, None] * ray
    # depth only over a patch a bit wider than REGION
    inside = (np.abs(p[:, 0]) < 1.3) & (np.abs(p[:, 1]) < 1.1)
    return np.where(inside, hi, 0.0).reshape(cam.height, cam.width)


def step(xy):
    return np.where(xy[..., 0] < 0.1, -1.0, -0.6)


# (max, mean) |error| in voxels. Measured: tilted 0.003 / 0.002 (a plane's projective distance is not
# linear in the voxel's position), wavy 0.045 / 0.010 (linear interpolation between voxels of a curved bed).
@pytest.mark.parametrize(("height", "tol"), [(tilted, (0.01, 0.005)), (wavy, (0.08, 0.02))],
                         ids=["tilted", "wavy"])
def test_exact_depth_maps_give_the_heights(height, tol):
    cams = cameras()
    depths = [depth_map(c, height) for c in cams]
    gsd = ground_sample(depths, cams)
    assert 0.03 < gsd < 0.06  # 3.5 m away, 68 px per radian
    grid, stats = fuse(depths, cams, REGION, CELL, ORIGIN)
    voxel = stats["voxel_m"]
    assert voxel == pytest.approx(3 * gsd) and stats["trunc_m"] == pytest.approx(3 * voxel)
    nodes = grid_nodes(REGION, CELL, ORIGIN)
    assert len(nodes) == 41 * 33 and len(grid) == len(nodes)  # every node has a surface
    err = grid[:, 2] - height(grid[:, :2])
    assert (np.abs(err).max() < tol[0] * voxel
            and np.abs(err).mean() < tol[1] * voxel), (np.abs(err).max(), voxel)
    np.testing.assert_allclose(grid[:, :2], nodes)
    # the z range came from the depth maps alone, padded
    zs = height(nodes)
    assert stats["z_range_m"][0] < zs.min() and stats["z_range_m"][1] > zs.max()


def test_a_finer_voxel_is_closer():
    cams = cameras()
    depths = [depth_map(c, wavy) for c in cams]
    errs = [np.abs(g[:, 2] - wavy(g[:, :2])).mean() for g, _ in
            (fuse(depths, cams, REGION, CELL, ORIGIN, FuseConfig(voxel=v)) for v in (0.2, 0.05))]
    assert errs[1] < errs[0] / 5, errs  # measured: 2.5 mm and 0.2 mm


def test_a_step_is_exact_away_from_its_edge():
    # 40 cm up at x = 0.1: depth maps read across the edge mix both sides (within the truncation) or take the
    # pixel's own depth; nodes two voxels away from the edge are exact, those near it lie between the two.
    cams = cameras()
    grid, stats = fuse([depth_map(c, step) for c in cams], cams, REGION, CELL, ORIGIN)
    far = np.abs(grid[:, 0] - 0.1) > 2 * stats["voxel_m"]
    assert far.sum() > 0.5 * len(grid) and np.abs(grid[far, 2] - step(grid[far, :2])).max() < 1e-3
    assert (grid[:, 2] > -1.01).all() and (grid[:, 2] < -0.59).all()


def test_pixels_without_depth_are_ignored():
    cams = cameras()
    depths = [depth_map(c, tilted) for c in cams]
    zlim, voxel = (-1.5, -0.5), 0.1
    ref = integrate(depths, cams, REGION, zlim, voxel, 0.3)
    # a view held 0.25 m over the surface whose depth map is empty: with 0 read as a depth, every voxel
    # within the truncation below it (0 - z >= -0.3) would be pulled towards -1
    low = Camera.look_at([0.0, 0.0, -0.75], [0.0, 0.0, -2.0], 32, 32, 90.0)
    got = integrate(depths + [np.zeros((32, 32))], cams + [low], REGION, zlim, voxel, 0.3)
    # bit-identical: the empty view updates no voxel (torch.where keeps the value), the others run as before
    np.testing.assert_array_equal(got.values, ref.values)
    np.testing.assert_array_equal(got.weights, ref.weights)
    # holes (40 % of the pixels of every view, and NaN / inf) leave the heights where they were
    rng = np.random.default_rng(0)
    holed = []
    for d in depths:
        d = d.copy()
        d[rng.random(d.shape) < 0.4] = 0.0
        d[rng.random(d.shape) < 0.02] = np.nan
        d[rng.random(d.shape) < 0.02] = np.inf
        holed.append(d)
    nodes = grid_nodes(REGION, CELL, ORIGIN)
    full = height_grid(ref, nodes)
    part = height_grid(integrate(holed, cams, REGION, zlim, voxel, 0.3), nodes)
    # a voxel reads one pixel per view: 0.4^5 of them are seen by none, and a crossing needs 8 voxels
    assert len(full) == len(nodes) and len(part) > 0.8 * len(full)
    assert np.abs(part[:, 2] - tilted(part[:, :2])).max() < 0.2 * voxel


def test_topmost_crossing_and_unobserved_columns():
    # A hand-made column: + above, - below at two places (a floater over the bed); the topmost one is taken.
    col = np.array([-0.5, 0.5, 1.0, 1.0, -0.2, 0.6, 1.0], np.float32)  # z = 0, 0.1, ..., 0.6
    values = np.tile(col, (3, 3, 1))
    weights = np.ones_like(values)
    tsdf = Tsdf(values, weights, np.zeros(3), 0.1, 0.3)
    nodes = np.array([[0.05, 0.1], [0.15, 0.15]])
    got = height_grid(tsdf, nodes)
    np.testing.assert_allclose(got[:, 2], 0.4 + 0.1 * 0.2 / 0.8, atol=1e-6)  # between z 0.4 and 0.5
    weights[1, 1, 5] = 0  # one unobserved corner: the nodes next to it lose that crossing, not the lower one
    got = height_grid(Tsdf(values, weights, np.zeros(3), 0.1, 0.3), nodes)
    np.testing.assert_allclose(got[:, 2], 0.05, atol=1e-6)
    # outside the volume's columns: no point
    assert len(height_grid(tsdf, np.array([[0.25, 0.1], [-0.01, 0.1]]))) == 0


def test_height_mesh_triangulates_present_cells():
    nodes = grid_nodes({"xmin": 0, "xmax": 0.2, "ymin": 0, "ymax": 0.1}, CELL, ORIGIN)  # 5 x 3
    grid = np.column_stack([nodes, nodes[:, 0]])
    verts, tris = height_mesh(grid, CELL)
    assert len(tris) == 2 * 4 * 2
    normals = np.cross(verts[tris[:, 1]] - verts[tris[:, 0]], verts[tris[:, 2]] - verts[tris[:, 0]])
    assert (normals[:, 2] > 0).all()  # counter-clockwise from above
    assert len(height_mesh(grid[1:], CELL)[1]) == 2 * 4 * 2 - 2  # a missing corner drops its square


def test_bad_inputs():
    cams = cameras(16)
    with pytest.raises(ValueError, match="one depth map per camera"):
        fuse([np.ones((16, 16))], cams, REGION, CELL, ORIGIN)
    with pytest.raises(ValueError, match="shape"):
        ground_sample([np.ones((8, 16))], cams[:1])
    with pytest.raises(ConfigError, match="trunc_voxels"):
        FuseConfig(trunc_voxels=0)
    grid, stats = fuse([np.zeros((16, 16))], cams[:1], REGION, CELL, ORIGIN)
    assert len(grid) == 0 and stats["z_range_m"] is None
    assert z_range([np.zeros((16, 16))], cams[:1], REGION) is None
    # a zero z span: two layers
    flat = integrate([np.ones((16, 16))], cams[:1], REGION, (-1.0, -1.0), 0.1, 0.3)
    assert flat.values.shape[2] == 2 and len(height_grid(flat, grid_nodes(REGION, CELL, ORIGIN))) == 0
