"""The paper's gravel bed: heightfield, albedo and exact ground truth: seeded, bathymetric,
mesh == height_at == PLY."""

import numpy as np
import pytest
import trimesh

from ragsplat.datagen import flight
from ragsplat.datagen.bed import ground_truth_grid, height_at, make_bed, mesh
from ragsplat.datagen.spec import preset
from ragsplat.dataset import layout


@pytest.fixture(scope="module")
def smoke_bed():
    return make_bed(preset("smoke-bed"))


def test_same_seed_same_bed_other_seed_other_bed(smoke_bed):
    again = make_bed(preset("smoke-bed"))
    assert np.array_equal(again.heights, smoke_bed.heights) and np.array_equal(again.albedo, smoke_bed.albedo)
    other = make_bed(preset("smoke-bed", seed=1))
    assert not np.allclose(other.heights, smoke_bed.heights)


def test_bed_is_bathymetric_with_stones_and_a_flat_border(smoke_bed):
    spec = preset("smoke-bed")
    h = smoke_bed.mesh_heights
    assert h.mean() == pytest.approx(spec.level - spec.bed.depth, abs=0.02)
    assert h.max() < spec.level - 1.0  # everything well under water
    core = h[20:-20, 20:-20]
    assert core.max() - core.min() > 0.2  # stones stand out of the relief
    assert np.all(h[0] == smoke_bed.z0) and np.all(h[:, -1] == smoke_bed.z0)  # meets the flat floor
    assert smoke_bed.albedo.std() > 10  # textured, not flat colour


def test_height_at_is_the_triangulated_mesh(smoke_bed, tmp_path):
    verts, tris = mesh(smoke_bed)
    # At vertices: the heights themselves.
    np.testing.assert_allclose(height_at(smoke_bed, verts[:, :2]), verts[:, 2], atol=1e-12)
    # Inside triangles: barycentric interpolation of the triangle that holds the point.
    rng = np.random.default_rng(0)
    pick = rng.integers(0, len(tris), 200)
    w = rng.dirichlet([1, 1, 1], 200)
    pts = np.einsum("nk,nkd->nd", w, verts[tris[pick]])
    np.testing.assert_allclose(height_at(smoke_bed, pts[:, :2]), pts[:, 2], atol=1e-12)
    # The PLY round-trips exactly through an independent reader.
    layout.write_ply(tmp_path / "bed.ply", verts, tris)
    m = trimesh.load(tmp_path / "bed.ply", process=False)
    assert np.array_equal(m.vertices, verts) and np.array_equal(m.faces, tris)
    assert np.all(m.face_normals[:, 2] > 0)  # counter-clockwise from above: normals up


def test_ground_truth_grid_covers_eval_region_at_5cm(smoke_bed):
    spec = preset("smoke-bed")
    region = flight.eval_region(spec)
    g = ground_truth_grid(smoke_bed, region, 0.05)
    assert g.dtype == np.float64 and g.shape[1] == 3
    xs = np.unique(g[:, 0].round(9))
    np.testing.assert_allclose(np.diff(xs), 0.05, atol=1e-9)
    assert xs[0] == pytest.approx(region["xmin"]) and xs[-1] <= region["xmax"] + 1e-9
    # the grid's own call: same function
    np.testing.assert_array_equal(g[:, 2], height_at(smoke_bed, g[:, :2]))
