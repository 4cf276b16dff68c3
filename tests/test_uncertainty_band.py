"""The TVU95 band's plumbing (issue 52): `ragsplat export --uncertainty` writes the DEM's band 3 and the LAS's
extra dimension as the model gives them from the run's features, and nothing changes without it; a tiled
survey merges the band with the heights; `ragsplat score` reports the band's coverage as computed by hand;
`python -m tools.fit_uncertainty` refuses the held-out reaches and records what it fitted on.

Every model here is a hand-made test fixture (`FIXTURE`), not a fitted one: no fitted model exists yet."""

import json
import shutil

import laspy
import numpy as np
import pytest
import rasterio
import torch
from conftest import WATER, tiny_bed_run

from ragsplat.cli.main import main
from ragsplat.dataset import layout, rasters
from ragsplat.dataset.load import load_dataset
from ragsplat.errors import ConfigError
from ragsplat.eval.calibration import iho_shares
from ragsplat.eval.evaluate import height_error
from ragsplat.export import TVU_BAND, extract_bed, write_dem, write_las
from ragsplat.ply import save_ply
from ragsplat.runs import load_run, run_water
from ragsplat.survey import tiles
from ragsplat.survey.stages import base, products, tiled
from ragsplat.uncertainty import FEATURES, UncertaintyModel, cell_features, tvu95

REGION = {"xmin": -0.8, "xmax": 0.8, "ymin": -0.8, "ymax": 0.8}
# A hand-made model, clearly not fitted: weights of the right order (m, and pixels for the geometry)
FIXTURE = UncertaintyModel(FEATURES, (0.004, 0.5, 0.01, 1.0, 0.02), scale=1.3,
                           fit_seeds=("hand-made test fixture",),
                           calibration_seeds=("hand-made test fixture",),
                           stats={"note": "a test fixture, not fitted on anything"})


def bed_height(x, y):  # the evaluable dataset's bed (conftest)
    return -1.0 + 0.1 * np.sin(2.0 * x) * np.cos(1.5 * y)


def save_discs(run, z, half=1.0, step=0.05, noise=0.0, seed=0) -> None:
    """Replaces a run's Gaussians by flat discs (3 x 3 cm, 3 mm thick, opacity 0.8) on a `step` lattice at
    heights z(x, y) + N(0, noise): a bed that passes the evaluation's culls after a 2-step training."""
    x, y = (a.ravel() for a in np.meshgrid(np.arange(-half, half + step / 2, step),
                                           np.arange(-half, half + step / 2, step)))
    heights = z(x, y) + np.random.default_rng(seed).normal(0.0, noise, len(x))
    n = len(x)
    save_ply(run / "point_cloud.ply", {
        "means": torch.tensor(np.column_stack([x, y, heights]), dtype=torch.float32),
        "sh0": torch.zeros(n, 1, 3), "opacities": torch.logit(torch.full((n,), 0.8)),
        "scales": torch.tensor([[0.03, 0.03, 0.003]] * n).log(), "quats": torch.tensor([[1.0, 0, 0, 0]] * n)})


@pytest.fixture(scope="module")
def bed_run(tmp_path_factory):
    """A finished 2-iteration run on a bed 1 m under water, its Gaussians replaced by discs on a wavy bed."""
    run = tiny_bed_run(tmp_path_factory.mktemp("band"))
    save_discs(run, bed_height)
    return run


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("model") / "fixture_model.json"
    path.write_text(FIXTURE.to_json())
    return path


def expected_tvu(run, level_sigma=0.0, n_sigma=0.0):
    """(the bed export extracts at 10 cm, each cell's TVU95 by the library directly: the features from the
    dataset's training views as loaded with their images)."""
    gaussians, ds, seed = load_run(run)
    water = run_water(json.loads((run / "config.json").read_text()), ds)
    bed = extract_bed(gaussians, 0.1, water, ds.eval_region, ds.georef, seed, ds.gsd, cells=True)
    cams = [v.camera for v in load_dataset(ds.root, splits=("train",), load_dry=False).train]
    features = cell_features(bed.grid, cams, water, bed.cells, level_sigma, n_sigma)
    return bed, tvu95(FIXTURE, features)


def at_cells(tif, points: np.ndarray) -> np.ndarray:  # [N, bands] at the pixels holding points [N, 2]
    rows, cols = rasterio.transform.rowcol(tif.transform, points[:, 0], points[:, 1])
    return tif.read()[:, rows, cols].T


def test_export_writes_the_band_and_the_las_dimension(bed_run, model_file, tmp_path, capsys):
    dem, laz = tmp_path / "dem.tif", tmp_path / "bed.laz"
    assert main(["export", str(bed_run), "--dem", str(dem), "--las", str(laz), "--resolution", "0.1",
                 "--uncertainty", str(model_file), "--level-sigma", "0.01", "--n-sigma", "0.005"]) == 0
    assert "TVU95 (band 3): median" in capsys.readouterr().out
    bed, expected = expected_tvu(bed_run, 0.01, 0.005)
    assert len(bed.grid) == 17 * 17 and np.isfinite(expected).all() and (expected > 0).all()
    with rasterio.open(dem) as tif:
        assert tif.count == 3 and tif.descriptions[2] == TVU_BAND == "tvu95"
        values = at_cells(tif, bed.grid[:, :2])
    np.testing.assert_allclose(values[:, 0], bed.grid[:, 2], rtol=0, atol=1e-6)  # the same bed
    np.testing.assert_allclose(values[:, 2], expected, rtol=1e-6, atol=1e-9)  # float32 of the same TVU95
    las = laspy.read(laz)
    assert TVU_BAND in las.point_format.extra_dimension_names
    order = np.lexsort((np.round(las.y / 0.1), np.round(las.x / 0.1)))
    mine = np.lexsort((np.round(bed.grid[:, 1] / 0.1), np.round(bed.grid[:, 0] / 0.1)))
    np.testing.assert_allclose(np.asarray(las[TVU_BAND])[order], expected[mine], rtol=1e-6, atol=1e-9)
    # the systematic terms add in quadrature: without them the band is narrower, never wider
    _, statistical = expected_tvu(bed_run)
    assert (statistical <= expected + 1e-12).all() and (statistical < expected).any()


def test_without_the_option_the_products_are_unchanged(bed_run, model_file, tmp_path):
    plain, banded = tmp_path / "plain", tmp_path / "banded"
    for out, extra in ((plain, []), (banded, ["--uncertainty", str(model_file)])):
        out.mkdir()
        assert main(["export", str(bed_run), "--dem", str(out / "dem.tif"), "--las", str(out / "bed.las"),
                     "--resolution", "0.1", *extra]) == 0
    # byte for byte what a bed without a TVU95 writes (the products before the band existed)
    gaussians, ds, seed = load_run(bed_run)
    water = run_water(json.loads((bed_run / "config.json").read_text()), ds)
    bare = extract_bed(gaussians, 0.1, water, ds.eval_region, ds.georef, seed, ds.gsd)
    assert bare.tvu95 is None and bare.cells is None
    write_dem(tmp_path / "bare.tif", bare)
    write_las(tmp_path / "bare.las", bare)
    assert (plain / "dem.tif").read_bytes() == (tmp_path / "bare.tif").read_bytes()
    a, b = laspy.read(plain / "bed.las"), laspy.read(tmp_path / "bare.las")
    assert not list(a.point_format.extra_dimension_names) and a.point_format.id == 6
    assert a.points.array.tobytes() == b.points.array.tobytes()  # (the header's date is the day's)
    with rasterio.open(plain / "dem.tif") as p, rasterio.open(banded / "dem.tif") as q:
        assert p.count == 2 and q.count == 3 and p.descriptions == q.descriptions[:2]
        np.testing.assert_array_equal(p.read(), q.read()[:2])  # the band adds, changes nothing
    c = laspy.read(banded / "bed.las")
    for dim in ("X", "Y", "Z", "classification"):
        np.testing.assert_array_equal(np.asarray(a[dim]), np.asarray(c[dim]))


def test_a_sigma_without_a_model_or_a_file_that_is_no_model_is_refused(bed_run, tmp_path, capsys):
    dem = tmp_path / "dem.tif"
    assert main(["export", str(bed_run), "--dem", str(dem), "--level-sigma", "0.01"]) == 2
    assert "without --uncertainty" in capsys.readouterr().err and not dem.exists()
    (tmp_path / "bad.json").write_text('{"features": ["one"], "weights": [-1.0]}')
    assert main(["export", str(bed_run), "--dem", str(dem), "--uncertainty", str(tmp_path / "bad.json")]) == 2
    assert "bad.json" in capsys.readouterr().err and not dem.exists()


def test_a_tiled_survey_merges_the_band_with_the_heights(evaluable_dataset, tmp_path):
    # the merge of `ragsplat survey`'s tiles (tiled.merge_tiles), two tiles with x = 1 between their cores
    cfg = base.SurveyConfig(images=tmp_path, out=tmp_path / "run", resolution=0.05)
    shutil.copytree(evaluable_dataset, cfg.out / "tiles" / "0" / "data")  # the first tile's frame
    boxes = np.array([[0.0, 0.0, 1.0, 1.0], [1.0, 0.0, 2.0, 1.0]])  # a photo over each half
    plan = tiles.plan([0, 0], [2, 1], boxes, ["a", "b"], 1.0, 0.25, min_photos=1)
    xs = np.arange(-10, 50) * 0.05
    cells = [(x, y) for x in xs for y in (0.45, 0.5, 0.55)]  # three rows (the PNG's hillshade needs two)
    left = np.array([(x, y, -0.5, 0.02) for x, y in cells if x < 1.25 + 1e-9])
    right = np.array([(x, y, -0.49, 0.03) for x, y in cells if x > 0.75 - 1e-9])
    products = [cfg.out / name for name in base.PRODUCTS]
    tiled.merge_tiles(cfg, WATER, plan, [left, right], products)
    with rasterio.open(products[0]) as tif:
        assert tif.count == 3 and tif.descriptions[2] == TVU_BAND
        pts = np.array(cells)
        values = at_cells(tif, pts)
    core = pts[:, 0] >= 1.0 - 1e-9  # each cell from the tile whose core holds it, its TVU95 with it
    np.testing.assert_allclose(values[:, 0], np.where(core, -0.49, -0.5), atol=1e-6)
    np.testing.assert_allclose(values[:, 2], np.where(core, 0.03, 0.02), atol=1e-7)
    las = laspy.read(products[1])
    np.testing.assert_allclose(np.asarray(las[TVU_BAND]), np.where(las.x >= 1.0 - 1e-9, 0.03, 0.02),
                               atol=1e-7)


def test_the_survey_takes_the_adjustment_s_level_sigma(tmp_path, model_file):
    out = tmp_path / "run"
    out.mkdir()
    (out / "water.json").write_text(json.dumps({"estimated": {"free": ["level"], "sigma_m": {"level": 0.004},
                                                              "sigma_given_cameras_m": {"level": 0.5}}}))
    cfg = base.SurveyConfig(images=tmp_path, out=out, uncertainty=model_file, n_sigma=0.002)
    band = products.uncertainty_settings(cfg)
    assert band["level_sigma"] == 0.004 and band["n_sigma"] == 0.002
    assert UncertaintyModel.from_json(band["model"]) == FIXTURE
    given = products.uncertainty_settings(base.SurveyConfig(images=tmp_path, out=out,
                                                                uncertainty=model_file, level_sigma=0.01))
    assert given["level_sigma"] == 0.01
    (out / "water.json").write_text(json.dumps({"surface": {}}))  # a level given, not estimated: exact
    assert products.uncertainty_settings(base.SurveyConfig(images=tmp_path, out=out,
                                                               uncertainty=model_file))["level_sigma"] == 0.0
    assert products.uncertainty_settings(base.SurveyConfig(images=tmp_path, out=out)) is None


# ---------------------------------------------------------------- ragsplat score


def banded_dem(path, truth, description=TVU_BAND, seed=0):
    """A DEM on the truth's nodes with errors of N(0, 2 cm) and a TVU95 band of 1-8 cm none of whose cells
    lies within 0.1 mm of |dz| (so that float32 rounding decides no cell); returns (dz, TVU95)."""
    rng = np.random.default_rng(seed)
    g = truth.grid
    dz = rng.normal(0.0, 0.02, len(g))
    tvu = rng.uniform(0.01, 0.08, len(g))
    near = (np.abs(np.abs(dz) - tvu) < 1e-4) | (np.abs(tvu - 0.05) < 1e-4)
    tvu[near] += 3e-4
    grid = np.column_stack([g[:, :2], g[:, 2] + dz])
    depth = WATER.depth(grid)
    bands = [(grid[:, 2], "bed elevation"), (np.where(depth > 0, depth, np.nan), "water depth"),
             (tvu, description)]
    rasters.write_raster(path, grid[:, :2], bands, 0.05)
    return dz, tvu


def test_score_reports_the_band_s_coverage(evaluable_dataset, tmp_path, capsys):
    truth = load_dataset(evaluable_dataset, splits=(), ground_truth=True).ground_truth
    dz, tvu = banded_dem(tmp_path / "bed.tif", truth)
    out = tmp_path / "score.json"
    assert main(["score", str(tmp_path / "bed.tif"), "--truth", str(evaluable_dataset), "--out",
                 str(out)]) == 0
    u = json.loads(out.read_text())["uncertainty"]
    _, depth = height_error(truth.grid, truth)
    assert u["band"] == 3 and u["cells"] == len(truth.grid) and (depth > 0).all()
    tvu32 = tvu.astype(np.float32).astype(float)
    assert u["coverage"]["0.95"] == np.mean(np.abs(dz) <= tvu)  # |dz| <= TVU95, by hand
    assert 0.3 < u["coverage"]["0.95"] < 0.99  # the fixture covers some cells, not all
    assert u["median_tvu95"] == pytest.approx(np.median(tvu32), abs=1e-9)
    assert u["z_variance"] == pytest.approx(np.var(dz / (tvu / 1.959963984540054)), rel=1e-4)
    expected = iho_shares(tvu, depth)
    assert u["iho"] == {k: pytest.approx(v, abs=1e-12) for k, v in expected.items()}
    assert 0 < u["iho"]["5cm"] < 1
    printed = capsys.readouterr().out
    assert f"|dz| <= TVU95 in {100 * u['coverage']['0.95']:.1f} %" in printed and "within 5 cm" in printed
    # another band's description: named by --tvu-band, the same figures; without either no band is scored
    banded_dem(tmp_path / "other.tif", truth, description="sigma")
    out2 = tmp_path / "other.json"
    assert main(["score", str(tmp_path / "other.tif"), "--truth", str(evaluable_dataset), "--out",
                 str(out2)]) == 0
    assert "uncertainty" not in json.loads(out2.read_text())
    assert main(["score", str(tmp_path / "other.tif"), "--truth", str(evaluable_dataset), "--out", str(out2),
                 "--tvu-band", "3"]) == 0
    assert json.loads(out2.read_text())["uncertainty"] == u


def test_a_tvu_band_of_points_or_of_the_heights_is_refused(evaluable_dataset, tmp_path, capsys):
    truth = load_dataset(evaluable_dataset, splits=(), ground_truth=True).ground_truth
    banded_dem(tmp_path / "bed.tif", truth)
    assert main(["score", str(tmp_path / "bed.tif"), "--truth", str(evaluable_dataset), "--tvu-band",
                 "1"]) == 2
    assert "heights' band" in capsys.readouterr().err
    (tmp_path / "bed.csv").write_text("x,y,z\n0,0,-1\n")
    assert main(["score", str(tmp_path / "bed.csv"), "--truth", str(evaluable_dataset), "--tvu-band",
                 "3"]) == 2
    assert "no DEM" in capsys.readouterr().err


# ---------------------------------------------------------------- python -m tools.fit_uncertainty


def seeded(data, root, seed):
    """A copy of the dataset `data` whose scene.json says it was rendered with dataset seed `seed`."""
    shutil.copytree(data, root)
    scene = json.loads((root / layout.SCENE).read_text())
    (root / layout.SCENE).write_text(json.dumps({**scene, "seed": seed}))
    return root


def fake_run(folder, data, preset="smoke"):
    """A run folder whose config.json names `data` (what the protocol's checks read, before any work)."""
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({"dataset": str(data), "config": {"seed": 0,
                                                                                      "preset": preset}}))
    return folder


@pytest.mark.parametrize("held_out, role", [(0, "evaluation"), (7, "untouched")])
def test_the_fit_tool_refuses_the_held_out_reaches(evaluable_dataset, tmp_path, capsys, held_out, role):
    from tools.fit_uncertainty import main as fit_main

    dev = fake_run(tmp_path / "dev", seeded(evaluable_dataset, tmp_path / "d1", 1))
    other = fake_run(tmp_path / "other", seeded(evaluable_dataset, tmp_path / "d2", 2))
    bad = fake_run(tmp_path / "bad", seeded(evaluable_dataset, tmp_path / "held", held_out), preset="small")
    out = tmp_path / "model.json"
    for argv in (["--fit", str(bad), "--calibrate", str(other)], ["--fit", str(dev), "--calibrate", str(bad)],
                 # a development run scored against the held-out reach's truth
                 ["--fit", str(dev), "--calibrate", str(other), "--truth", f"{other}={tmp_path / 'held'}"]):
        assert fit_main([*argv, "--out", str(out)]) == 1
        err = capsys.readouterr().err
        assert f"dataset seed {held_out}, the {role} reach" in err and "development seeds only" in err
        assert not out.exists()


def test_the_fit_tool_refuses_one_seed_in_both_steps(evaluable_dataset, tmp_path, capsys):
    from tools.fit_uncertainty import main as fit_main

    data = seeded(evaluable_dataset, tmp_path / "d1", 1)
    a, b = fake_run(tmp_path / "a", data), fake_run(tmp_path / "b", data)
    assert fit_main(["--fit", str(a), "--calibrate", str(b), "--out", str(tmp_path / "m.json")]) == 1
    assert "both fitted and calibrated on" in capsys.readouterr().err
    assert fit_main(["--fit", str(a), "--calibrate", str(a), "--out", str(tmp_path / "m.json")]) == 1
    assert "in both --fit and --calibrate" in capsys.readouterr().err


def test_the_fit_tool_fits_calibrates_and_records(evaluable_dataset, tmp_path, capsys):
    from ragsplat.eval.calibration import coverage
    from ragsplat.eval.tvu_cells import run_cells, run_source
    from ragsplat.uncertainty import sigma
    from tools.fit_uncertainty import main as fit_main

    data = tmp_path / "data"
    shutil.copytree(evaluable_dataset, data)  # training caches its tracks in the dataset
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "trained"), "--preset", "smoke",
                 "--iterations", "2", "--init-depth", "1.0", "--no-progress"]) == 0
    runs = []
    for k, seed in enumerate((1, 2)):  # two development reaches, beds with 1 cm and 2 cm of noise
        run = tmp_path / f"run{seed}"
        shutil.copytree(tmp_path / "trained", run)
        save_discs(run, bed_height, half=0.7, noise=0.01 * (k + 1), seed=k)
        runs.append((run, seeded(evaluable_dataset, tmp_path / f"s{seed}", seed)))
    out = tmp_path / "model.json"
    assert fit_main(["--fit", str(runs[0][0]), "--calibrate", str(runs[1][0]), "--out", str(out),
                     *[f"--truth={r}={d}" for r, d in runs]]) == 0, capsys.readouterr().err
    model = UncertaintyModel.from_json(out.read_text())
    assert model.fit_seeds == (1,) and model.calibration_seeds == (2,) and model.features == FEATURES
    assert model.commit is not None and model.stats["code_digest"]
    assert [r["run"] for r in model.stats["fit_runs"]] == [str(runs[0][0])]
    assert model.stats["calibration_runs"][0]["truth"] == str(runs[1][1])
    # the conformal step: the 95 % interval covers at least 95 % of the calibration run's wet cells
    cells = run_cells(run_source(runs[1][0], runs[1][1]))
    assert len(cells.errors) > 100
    covered = coverage(sigma(model, cells.features), cells.errors)
    assert covered >= 0.95 and model.stats["calibration_coverage_per_run"][str(runs[1][0])] == covered
    assert "wrote" in capsys.readouterr().out

    # the check on a held-out reach (dataset seed 3, noise between the two), its report and figure
    from tools.check_uncertainty import main as check_main

    held = tmp_path / "run3"
    shutil.copytree(tmp_path / "trained", held)
    save_discs(held, bed_height, half=0.7, noise=0.015, seed=3)
    held_data = seeded(evaluable_dataset, tmp_path / "s3", 3)
    report, figure = tmp_path / "check.json", tmp_path / "check.png"
    assert check_main([str(out), str(held), f"--truth={held}={held_data}", "--out", str(report),
                       "--figure", str(figure)]) == 0, capsys.readouterr().err
    r = json.loads(report.read_text())
    mine = run_cells(run_source(held, held_data))
    assert r["cells"] == len(mine.errors) and r["runs"][str(held)]["dataset_seed"] == 3
    assert r["coverage"]["0.95"] == pytest.approx(coverage(sigma(model, mine.features), mine.errors))
    assert 0 < r["oracle_median_tvu95"] and r["sharpness_vs_oracle"] > 0 and figure.stat().st_size > 0
    assert "coverage 50/80/95 %" in capsys.readouterr().out
    # a reach the model was calibrated on is not a test of it
    assert check_main([str(out), str(runs[1][0]), f"--truth={runs[1][0]}={runs[1][1]}"]) == 1
    assert "is not held out from the uncertainty model" in capsys.readouterr().err


def test_the_protocol_check_is_a_config_error(evaluable_dataset, tmp_path):
    from ragsplat.eval.tvu_cells import check_development, run_source

    run = fake_run(tmp_path / "run", seeded(evaluable_dataset, tmp_path / "d0", 0))
    with pytest.raises(ConfigError, match="evaluation reach"):
        check_development(run_source(run))
    check_development(run_source(fake_run(tmp_path / "dev", evaluable_dataset)))  # no seed recorded: not held


def test_the_ablation_writes_each_trained_row_s_band_and_table3_reports_it(evaluable_dataset, tmp_path):
    from dataclasses import replace

    from ragsplat.eval.calibration import coverage
    from ragsplat.eval.report import table3
    from ragsplat.eval.rows import row_dir
    from ragsplat.eval.tvu_cells import band_rows, check_held_out, run_cells, run_source
    from ragsplat.uncertainty import Z95

    data = seeded(evaluable_dataset, tmp_path / "data", 3)  # a reach the fixture was not fitted on
    out = tmp_path / "ablation"
    run = row_dir(out, "2dgs+full", 0)
    assert main(["train", "--data", str(data), "--out", str(run), "--preset", "smoke", "--iterations", "2",
                 "--init-depth", "1.0", "--no-progress"]) == 0
    save_discs(run, bed_height, half=0.7, noise=0.01)
    plain = {"seed": 0, "geometry": {"survey": {"coverage": 1.0}}}
    rows = {"2dgs+full": [dict(plain)], "init": [dict(plain)]}  # a reference row: no band
    lines = []
    band_rows(out, data, rows, FIXTURE, lines.append)
    tvu = rows["2dgs+full"][0]["geometry"]["survey"]["tvu"]
    cells = run_cells(run_source(run, data))
    expected = tvu95(FIXTURE, cells.features)
    assert tvu["cells"] == len(cells.errors) > 100 and "tvu" not in rows["init"][0]["geometry"]["survey"]
    assert tvu["coverage"]["0.95"] == coverage(expected / Z95, cells.errors)
    assert tvu["median_tvu95"] == pytest.approx(np.median(expected)) and tvu["sharpness_vs_oracle"] > 0
    with rasterio.open(run / "tvu95.tif") as tif:  # the band, on the bed's cells
        assert tif.descriptions[0] == TVU_BAND
        np.testing.assert_allclose(at_cells(tif, cells.xy)[:, 0], expected, rtol=1e-6, atol=1e-9)
    assert "TVU95 band" in lines[0]
    text = table3(rows)
    assert "TVU95 covers (%)" in text and f"{100 * tvu['coverage']['0.95']:.1f}" in text
    assert "TVU95" not in table3({"2dgs+full": [plain]})  # no band, no columns
    check_held_out(FIXTURE, 3)
    with pytest.raises(ConfigError, match="not held out"):
        check_held_out(replace(FIXTURE, calibration_seeds=(3,)), 3)
    seen = tmp_path / "seen.json"
    seen.write_text(replace(FIXTURE, fit_seeds=(3,)).to_json())
    assert main(["ablation", "--data", str(data), "--out", str(tmp_path / "refused"), "--preset", "smoke",
                 "--variants", "2dgs+full", "--seeds", "0", "--jobs", "1", "--uncertainty", str(seen)]) == 2
    assert not (tmp_path / "refused" / "results.json").exists()

    # the product's bed: the cells of the DEM `ragsplat export` writes, band 3 the same model's TVU95
    dem = tmp_path / "dem.tif"
    fixture = tmp_path / "fixture.json"
    fixture.write_text(FIXTURE.to_json())
    assert main(["export", str(run), "--dem", str(dem), "--uncertainty", str(fixture)]) == 0
    product = run_cells(run_source(run, data), bed="export")
    assert len(product.errors) > 100 and product.cell == 0.05
    with rasterio.open(dem) as tif:
        np.testing.assert_allclose(at_cells(tif, product.xy)[:, 2], tvu95(FIXTURE, product.features),
                                   rtol=1e-6, atol=1e-9)
    with pytest.raises(ConfigError, match="unknown bed"):
        run_cells(run_source(run, data), bed="survey")


def test_the_band_is_checked_at_the_dem_s_own_cells_not_read_between_them(evaluable_dataset, tmp_path):
    """A DEM whose lattice is off the truth's nodes (as `ragsplat export`'s is; 2 of 5 cm, so that no centre
    is equally near two nodes): each covered cell in the region is checked against the bed at its own centre
    (here the nearest node's: this truth has no exact surface), its TVU95 as written (no interpolation)."""
    from ragsplat.eval.score_file import score_file

    truth = load_dataset(evaluable_dataset, splits=(), ground_truth=True).ground_truth
    rng = np.random.default_rng(1)
    xy = truth.grid[:, :2] + 0.02
    z = truth.grid[:, 2] + rng.normal(0.0, 0.02, len(xy))
    tvu = rng.uniform(0.01, 0.08, len(xy))
    bands = [(z, "bed elevation"), (WATER.depth(np.column_stack([xy, z])), "water depth"), (tvu, TVU_BAND)]
    rasters.write_raster(tmp_path / "off.tif", xy, bands, 0.05)
    u = score_file(tmp_path / "off.tif", evaluable_dataset)[0]["uncertainty"]
    r = truth.region
    mine = ((xy[:, 0] <= r["xmax"] + 1e-6) & (xy[:, 1] <= r["ymax"] + 1e-6))  # the offset moves one edge out
    z32 = z.astype(np.float32).astype(float)  # as the GeoTIFF holds them
    dz, depth = height_error(np.column_stack([xy, z32])[mine], truth)
    wet = depth > 0
    t32 = tvu.astype(np.float32).astype(float)[mine][wet]
    assert u["checked_at"] == "the DEM's own cells" and u["cells"] == wet.sum() < len(xy)
    assert u["coverage"]["0.95"] == pytest.approx(np.mean(np.abs(dz[wet]) <= t32), abs=1e-12)
    assert u["median_tvu95"] == pytest.approx(np.median(t32), abs=1e-9)


def test_the_shipped_model_is_fitted_on_development_seeds_and_named_small(tmp_path):
    from ragsplat.eval.tvu_cells import check_held_out
    from ragsplat.export import SHIPPED_MODELS, read_uncertainty

    model = read_uncertainty("small")
    assert SHIPPED_MODELS == ("small", "small-field") and model.features == FEATURES and model.scale > 0
    assert model.fit_seeds == (1,) and model.calibration_seeds == (2,) and model.stats["bed"] == "evaluation"
    assert "tools.fit_uncertainty" in model.stats["command"] and model.commit
    for seed in (0, 3, 7):  # the held-out reaches it may be checked on
        check_held_out(model, seed)
    with pytest.raises(ConfigError, match="not held out"):
        check_held_out(model, 1)
    with pytest.raises(ConfigError, match="no shipped model of that name"):
        read_uncertainty(tmp_path / "nothing.json")
    field = read_uncertainty("small-field")  # clear water's weights, the field development seed's scale
    assert field.features == FEATURES and field.fit_seeds == (2,) and field.calibration_seeds == (1,)
    assert field.scale > model.scale and "small-field-s1" in field.stats["command"]
    check_held_out(field, 7)
