import json
import re
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from ragsplat.dataset.load import GroundTruth
from ragsplat.errors import ConfigError
from ragsplat.eval import ablation, references
from ragsplat.eval.ablation import run_ablation
from ragsplat.eval.evaluate import evaluate_fused, evaluate_geometry, evaluate_views, score_grid
from ragsplat.eval.report import load_published, table1, table2, table3, table4, write_outputs
from ragsplat.eval.rows import start_row
from ragsplat.fusion import FuseConfig
from ragsplat.train.config import VARIANTS, preset_config
from ragsplat.water_surface import WaterSurface

WATER = WaterSurface(0.0, 1.33)


def fake_row(i: int, seed: int = 0) -> dict:
    """Per-variant numbers made up for the layout tests (distinct per variant and seed)."""
    app = {"psnr": 20.0 + i + seed, "ssim": 0.5 + 0.01 * i, "lpips": None}
    named = {"10cm": 0.5, "30cm": 1.0, "1%": 0.25 + 0.1 * seed, "3%": 0.75}
    geo = {"chamfer": 0.1 * (i + 1), "precision": named, "recall": named, "f1": named,
           "survey": {"coverage": 0.9, "wet": {"bias": -0.02, "rmse": 0.05, "p95": 0.1}}}
    fused = {**geo, "chamfer": 0.05 * (i + 1), "f1": {**named, "3%": 0.875},
             "survey": {"coverage": 0.8, "wet": {"bias": 0.01, "rmse": 0.04, "p95": 0.08}}}
    curve = [{"iteration": k * 10, "time_s": 30.0 * k, "psnr_refr": 15 + k + i, "psnr_dry": 12 + k,
              "f1": {"1%": 0.1 * k, "3%": 0.2 * k}}
             for k in range(4)]
    return {"name": list(VARIANTS)[i], "seed": seed,
            "appearance": {"refr": app, "dry": dict(app, psnr=float("nan")), "per_view": []},
            "num_gaussians": 12345, "time": {"wall_s": 90.0, "cpu_s": 150.0, "median_step_s": 0.06},
            "geometry": geo, "geometry_fused": fused, "curve": curve}


def test_tables_compare_with_the_paper_only_on_depth_scaled_columns():
    published = load_published()
    rows = {v: [fake_row(i, 0), fake_row(i, 1)] for i, v in enumerate(VARIANTS)}
    rows["oracle plane"] = [{"name": "oracle plane", "seed": None, "uses_ground_truth": True,
                             "geometry": fake_row(0)["geometry"]}]
    rows["oracle plane"][0]["extraction"] = "-"
    t2 = table2(rows, published)
    head = t2.splitlines()[2]
    assert head.startswith("| Row | seeds | bed | CD (m) | F1@10cm (%) | F1@30cm (%) | P@1% (%) | paper |")
    assert head.count("paper") == 6  # P/R/F1 at 1 % and 3 % only
    lines = [line for line in t2.splitlines() if line.startswith("| ")]
    assert lines[1].startswith("| oracle plane (uses GT) | - | - |")  # reference rows first, marked, one bed
    assert not any(line.startswith("| oracle plane (uses GT) | - | fused |") for line in lines)
    full = next(line for line in lines if line.startswith("| full | 2 | volume |"))
    # F1@1%: seeds 25 % and 35 % -> 30.0 ± 7.1, beside the paper's F1@10cm at 10 m (94.00)
    assert "| 2 | volume | 0.500 ± 0.000 | 50.0 ± 0.0 | 100.0 ± 0.0 | 30.0 ± 7.1 | 91.6 |" in full
    assert "| 30.0 ± 7.1 | 94.0 |" in full
    # the fused bed of the same row follows it, with the same paper values beside it
    fused = lines[lines.index(full) + 1]
    assert (fused.startswith("| full | 2 | fused | 0.250 ± 0.000 |")
            and fused.endswith("| 87.5 ± 0.0 | 99.1 |"))
    t1 = table1(rows, published)
    base = next(line for line in t1.splitlines() if line.startswith("| 3dgs |"))
    # the paper leaves 3dgs refr empty; 12345 Gaussians -> 12.3 K; 90 s -> 1.5 min wall, 2.5 min CPU
    assert base.startswith("| 3dgs | 2 | 0.500 ± 0.000 |  | 20.50 ± 0.71 |  | n/a |")
    assert base.endswith("| 12.3 ± 0.0 | 40.0 | 1.5 ± 0.0 | 6.8 | 2.5 ± 0.0 | 0.060 ± 0.000 |")
    assert "oracle plane" not in t1  # no appearance
    t3 = table3(rows)
    assert "| full | 2 | volume | 90.0 ± 0.0 | -2.0 ± 0.0 | 5.0 ± 0.0 | 10.0 ± 0.0 |" in t3
    assert "| full | 2 | fused | 80.0 ± 0.0 | +1.0 ± 0.0 | 4.0 ± 0.0 | 8.0 ± 0.0 |" in t3


def test_write_outputs_files(tmp_path):
    rows = {v: [fake_row(i)] for i, v in enumerate(list(VARIANTS)[:3])}
    text = write_outputs(tmp_path, rows, {"preset": "smoke", "seeds": [3], "max_depth_m": 3.0},
                         "weights missing")
    assert "LPIPS n/a: weights missing" in (tmp_path / "table1.md").read_text()
    assert (tmp_path / "table2.md").read_text() in text and (tmp_path / "table3.md").read_text() in text
    assert "1 % / 3 % of the maximum depth (3 m: 30 / 90 mm)" in text
    res = json.loads((tmp_path / "results.json").read_text(), parse_constant=lambda c: pytest.fail(c))
    assert res["seeds"] == [3] and list(res["rows"]) == list(list(VARIANTS)[:3])
    assert res["rows"]["3dgs"][0]["appearance"]["dry"]["psnr"] is None  # NaN stored as null
    assert res["summary"]["3dgs"]["F1@1% (%)"] == {"mean": 25.0, "std": None, "n": 1}
    assert res["summary_fused"]["3dgs"]["F1@3% (%)"] == {"mean": 87.5, "std": None, "n": 1}
    assert res["summary_fused"]["3dgs"]["RMSE (cm)"]["mean"] == pytest.approx(4.0)
    assert res["lpips"] == {"available": False, "reason": "weights missing"}
    png = (tmp_path / "error_vs_time.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    # the same on one page: every table's rows as HTML tables, the plot inlined
    page = (tmp_path / "report.html").read_text()
    separators = [line for line in text.splitlines() if re.fullmatch(r"\|[\s:|-]+\|", line)]
    assert page.count("<table>") == len(separators) >= 3
    assert "<td>3dgs</td>" in page and 'src="data:image/png;base64,' in page and "src=\"http" not in page


class FakeRunner:
    """`run_ablation`'s runner without training: made-up rows, a flat ground truth at -1 m."""

    def __init__(self):
        x, y = np.meshgrid(np.arange(5) * 0.05, np.arange(5) * 0.05, indexing="ij")
        grid = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, -1.0)])
        self.truth = GroundTruth(grid, {"xmin": 0, "xmax": 0.2, "ymin": 0, "ymax": 0.2}, 2.0, WATER)
        self.fingerprint, self.dataset_seed, self.gsd = "aaaa", 0, 0.01
        self.calls = []

    def config(self, variant, preset, seed):
        return preset_config(preset, variant=variant, seed=seed)

    def initial(self, cfg):
        g = self.truth.grid
        return {"means": torch.tensor(g), "scales": torch.full((len(g), 3), 0.03),
                "quats": torch.tensor([[1.0, 0, 0, 0]]).expand(len(g), 4),
                "opacities": torch.full((len(g),), 0.9)}

    def train(self, cfg, out, ecfg, fcfg, checkpoints, lpips_metric=None):
        self.calls.append((cfg.variant, cfg.seed))
        apparent = self.truth.grid + [0, 0, 1.0 - 1.0 / 1.33]  # an uncorrected bed at depth / n
        return fake_row(list(VARIANTS).index(cfg.variant), cfg.seed), apparent, self.truth.grid + [0, 0, 0.01]


def test_table4_puts_the_trained_optics_beside_the_scenes():
    """Table 4 (issue 50): the attenuation per channel over the seeds and its ratio to the scene's extinction;
    no table when no row trained a water term (the clear-water ablation writes no table4.md)."""
    veil = {"veil": [0.1, 0.2, 0.3], "coefficients": [1, 2, 3]}
    rows = {"2dgs+full": [{"seed": 0, "train_stats": {"attenuation": None, "backscatter": None}}],
            "2dgs+full+water": [
                {"seed": 0, "train_stats": {"attenuation": [0.4, 0.2, 0.3], "backscatter": veil}},
                {"seed": 1, "train_stats": {"attenuation": [0.6, 0.2, 0.3], "backscatter": veil}}]}
    text = table4(rows, {"extinction_per_m": [0.5, 0.25, 0.3]})
    line = next(x for x in text.splitlines() if x.startswith("| 2dgs+full+water"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[:8] == ["2dgs+full+water", "2", "0.500 ± 0.141", "0.200 ± 0.000", "0.300 ± 0.000",
                         "1.00 ± 0.28", "0.80 ± 0.00", "1.00 ± 0.00"]
    assert "| 2dgs+full |" not in text and "0.500 / 0.250 / 0.300" in text
    assert "n/a" in table4(rows, None) and table4({"2dgs+full": rows["2dgs+full"]}, None) == ""


def test_rows_only_trains_each_row_and_the_tables_reuse_them(tmp_path):
    # what a Dask task of `ragsplat ablation --jobs 2` does (`train_row`): its rows, trained, and nothing
    # else; the surfel rows are handed out first; the last run reuses every row and writes the tables
    data, out, runner = tmp_path / "data", tmp_path / "out", FakeRunner()
    data.mkdir()
    quiet = {"log": lambda s: None, "download": False}
    order = ablation.row_order(["3dgs", "2dgs+full"], [0, 1])
    assert order == [("2dgs+full", 0), ("2dgs+full", 1), ("3dgs", 0), ("3dgs", 1)]
    for variant, seed in order:
        got = run_ablation(data, out, "smoke", [variant], [seed], runner, rows_only=True, **quiet)
        assert list(got) == [variant]
    assert runner.calls == order
    assert not (out / "results.json").exists() and not (out / "init").exists()
    run_ablation(data, out, "smoke", ["3dgs", "2dgs+full"], [0, 1], runner, rows_only=True, **quiet)
    assert len(runner.calls) == 4  # every row is there already
    rows = run_ablation(data, out, "smoke", ["3dgs", "2dgs+full"], [0, 1], runner, **quiet)
    assert len(runner.calls) == 4 and [r["seed"] for r in rows["2dgs+full"]] == [0, 1]
    assert list(rows) == ["3dgs", "2dgs+full", "init", "3dgs x n", "oracle plane", "oracle median plane"]
    assert (out / "results.json").is_file()
    # the sources edited while the processes ran: refused, not keyed to two versions of the code
    with pytest.raises(ConfigError, match="changed since this command started"):
        run_ablation(data, out, "smoke", ["3dgs"], [0], runner, code="0123456789abcdef", **quiet)


def test_rows_are_reused_only_under_their_key(tmp_path):
    data, out, runner = tmp_path / "data", tmp_path / "out", FakeRunner()
    data.mkdir()
    quiet = {"log": lambda s: None, "download": False}
    rows = run_ablation(data, out, "smoke", ["3dgs", "full"], [0, 1], runner, **quiet)
    assert runner.calls == [("3dgs", 0), ("full", 0), ("3dgs", 1), ("full", 1)]
    assert list(rows) == ["3dgs", "full", "init", "3dgs x n", "oracle plane", "oracle median plane"]
    assert [r["seed"] for r in rows["full"]] == [0, 1] and len(rows["oracle plane"]) == 1
    # the classical correction of an apparent flat bed (depth / n) is exact: every reference has a known
    # answer
    assert rows["3dgs x n"][0]["geometry"]["f1"]["1%"] == 1.0
    assert (rows["oracle plane"][0]["geometry"]["f1"]["1%"] == 1.0
            and rows["oracle plane"][0]["uses_ground_truth"])
    assert rows["init"][0]["geometry"]["survey"]["wet"]["bias"] == pytest.approx(0.0, abs=0.01)
    for name in ("bed.npy", "bed.tif", "depth_error.png"):
        assert (out / "3dgs-x-n" / "seed0" / name).stat().st_size > 0
    assert not (out / "3dgs-x-n" / "seed0" / "bed_fused.npy").exists()
    assert [r["extraction"] for n in ("init", "3dgs x n", "oracle plane") for r in rows[n]] == \
        ["volume", "volume", "volume", "volume", "-"]
    # a trained row keeps both beds; the fused one also as a mesh: 4 x 4 squares of the 5 x 5 grid, 2 each
    assert np.load(out / "full" / "seed0" / "bed_fused.npy")[:, 2] == pytest.approx(-0.99)
    ply = (out / "full" / "seed0" / "bed_fused.ply").read_bytes()
    assert b"element vertex 25\n" in ply and b"element face 32\n" in ply
    assert rows["full"][0]["outputs"]["depth_error_fused"].endswith("depth_error_fused.png")
    # same key: reused; only the requested variants and seeds are tabulated
    rows = run_ablation(data, out, "smoke", ["full"], [1], runner, **quiet)
    assert len(runner.calls) == 4 and list(rows) == ["full", "init", "oracle plane", "oracle median plane"]
    res = json.loads((out / "results.json").read_text())
    assert (list(res["rows"]) == ["oracle plane", "oracle median plane", "init", "full"]
            and res["seeds"] == [1])
    assert "| 3dgs |" not in (out / "table2.md").read_text()
    # another dataset content (one image changed): recomputed, never reused
    runner.fingerprint = "bbbb"
    logged = []
    run_ablation(data, out, "smoke", ["full"], [1], runner, log=logged.append, download=False)
    assert runner.calls[-1] == ("full", 1) and any("another dataset" in line for line in logged)
    with pytest.raises(ConfigError, match="unknown variant"):
        run_ablation(data, out, "smoke", ["nope"], [0], runner, **quiet)
    with pytest.raises(ConfigError, match="seeds"):
        run_ablation(data, out, "smoke", ["full"], [1, 1], runner, **quiet)


def test_a_stale_checkpoint_is_not_resumed(tmp_path):
    folder = tmp_path / "full" / "seed0"
    folder.mkdir(parents=True)
    start_row(folder, {"dataset": "aaaa"})
    (folder / "ckpt.pt").write_bytes(b"trained on aaaa")
    start_row(folder, {"dataset": "aaaa"})
    assert (folder / "ckpt.pt").exists()  # same key: the killed run resumes
    start_row(folder, {"dataset": "bbbb"})
    assert not (folder / "ckpt.pt").exists()


def slope_truth():
    """A 2 x 0.5 m slope from 0 to 1.95 m deep on 5 cm nodes: its first row of 10 nodes is the bank."""
    x, y = np.meshgrid(np.arange(40) * 0.05, np.arange(10) * 0.05, indexing="ij")
    nodes = np.column_stack([x.ravel(), y.ravel(), -0.05 * x.ravel()])
    return GroundTruth(nodes[10:], {}, 1.95, WATER, banks=nodes[:10]), nodes


def test_survey_figures_count_holes_as_misses():
    truth, nodes = slope_truth()
    pred = nodes + [0, 0, 0.02]
    whole = score_grid(pred, truth)["survey"]
    assert whole["wet"]["bias"] == pytest.approx(0.02) and whole["wet"]["rmse"] == pytest.approx(0.02)
    assert (whole["wet"]["p95"] == pytest.approx(0.02) and whole["coverage"] == 1.0
            and whole["wet"]["holes"] == 0)
    assert (whole["wet"]["within"] == {"3cm": 1.0, "5cm": 1.0}
            and all(v == 1.0 for v in whole["wet"]["iho"].values()))
    half = score_grid(pred[::2], truth)["survey"]  # every other cell: half the wet cells are holes
    wet = half["wet"]
    assert half["coverage"] == pytest.approx(195 / 390) and wet["n"] + wet["holes"] == 390
    assert wet["bias"] == pytest.approx(0.02) and wet["rmse"] == pytest.approx(0.02)  # over the covered cells
    assert wet["p95"] is None  # half the cells have no error to rank
    assert (wet["within"]["3cm"] == pytest.approx(195 / 390)
            and wet["within"]["5cm"] == pytest.approx(195 / 390))
    assert all(v == pytest.approx(195 / 390) for v in wet["iho"].values())
    for band in ("shallow", "middle", "deep"):
        assert half[band]["n"] + half[band]["holes"] == whole[band]["n"]
    assert half["banks"]["n"] == 5 and sum(half[b]["n"] for b in ("shallow", "middle", "deep")) == wet["n"]
    assert references.depth_times_n(np.array([[0, 0, -1.0], [0, 0, 0.5]]), WATER).tolist() == \
        [[0, 0, -1.33], [0, 0, 0.5]]


def test_a_bank_cell_never_counts_as_wet():
    truth, nodes = slope_truth()
    pred = nodes.copy()
    pred[:10, 2] += 5.0  # the banks 5 m too high, the bed exact
    s = score_grid(pred, truth)["survey"]
    assert s["wet"]["bias"] == 0.0 and s["wet"]["p95"] == 0.0 and s["wet"]["within"]["3cm"] == 1.0
    assert s["banks"]["bias"] == pytest.approx(5.0) and s["banks"]["n"] == 10 and s["coverage"] == 1.0


def test_iho_shares_at_the_order_s_bound():
    from ragsplat.scoring import tvu

    truth, nodes = slope_truth()
    depth = -nodes[:, 2]
    pred = nodes.copy()
    pred[:, 2] += np.where(np.arange(len(nodes)) % 2 == 0, 0.99, 1.01) * tvu(depth, "special")  # half inside
    iho = score_grid(pred, truth)["survey"]["wet"]["iho"]
    assert iho["special"] == pytest.approx(0.5) and iho["exclusive"] == 0.0 and iho["order 1"] == 1.0
    assert tvu(np.array([0.0, 10.0]), "order 2") == pytest.approx([1.0, np.hypot(1.0, 0.23)])


def test_quantile_with_holes_is_numpy_s_with_holes_as_the_largest():
    from ragsplat.scoring import quantile_with_holes

    e = np.random.default_rng(0).uniform(0, 1, 200)
    assert quantile_with_holes(e, 0, 0.95) == pytest.approx(np.percentile(e, 95), abs=0, rel=1e-12)
    for holes in (1, 5, 9):  # the quantile still falls among the errors
        assert (quantile_with_holes(e, holes, 0.95)
                == pytest.approx(np.percentile(np.r_[e, np.full(holes, 9.0)], 95)))
    assert quantile_with_holes(e, 11, 0.95) is None and quantile_with_holes(np.zeros(0), 0, 0.95) is None


def test_oracle_planes_on_a_tilted_bed_with_relief():
    x, y = np.meshgrid(np.arange(30) * 0.1, np.arange(20) * 0.1, indexing="ij")
    x, y = x.ravel(), y.ravel()
    z = -1.0 - 0.2 * x + 0.1 * y + 0.05 * np.sin(7 * x) * np.cos(5 * y)  # tilted, with stones
    truth = GroundTruth(np.column_stack([x, y, z]), {}, float(-z.min()), WATER)
    grids = references.oracle_grids(truth)
    plane, flat = grids["oracle plane"], grids["oracle median plane"]
    A = np.column_stack([np.ones_like(x), x, y])
    assert plane[:, 2] == pytest.approx(A @ np.linalg.lstsq(A, z, rcond=None)[0])
    assert np.abs(plane[:, 2] - z).max() < 0.06  # the tilt is found: only the stones are left
    assert flat[:, 2] == pytest.approx(np.median(z)) and np.abs(flat[:, 2] - z).max() > 0.3
    assert score_grid(plane, truth)["f1"]["10cm"] == 1.0 > score_grid(flat, truth)["f1"]["10cm"]


def test_evaluate_views_conditions():
    gen = torch.Generator().manual_seed(0)
    wet, dry = torch.rand(16, 16, 3, generator=gen) * 0.8, torch.rand(16, 16, 3, generator=gen) * 0.8
    views = [SimpleNamespace(name="0000", kind="nadir", image=wet, dry=dry),
             SimpleNamespace(name="0001", kind="oblique20", image=wet, dry=None)]

    def render(view, interface):  # through the interface: wet + 0.1 (20 dB); without: exactly the dry image
        return view.image + 0.1 if interface else dry

    res = evaluate_views(render, views)
    assert res["refr"]["psnr"] == pytest.approx(20.0, abs=1e-4)
    assert res["dry"]["ssim"] == pytest.approx(1.0) and res["dry"]["lpips"] is None
    assert res["per_view"][1]["dry"] is None and res["per_view"][1]["kind"] == "oblique20"
    quick = evaluate_views(render, views, psnr_only=True)  # the training curve's points: PSNR alone
    assert quick["refr"]["psnr"] == res["refr"]["psnr"] and quick["dry"]["psnr"] == res["dry"]["psnr"]
    assert quick["refr"]["ssim"] is None and quick["per_view"][0]["dry"]["ssim_3dgs"] is None


def test_evaluate_geometry_flat_bed():
    x, y = np.meshgrid(np.arange(30) * 0.05, np.arange(30) * 0.05, indexing="ij")
    bed = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, -2.0)])
    g = {"means": torch.tensor(bed), "scales": torch.tensor([[0.03, 0.03, 0.003]]).expand(len(bed), 3),
         "quats": torch.tensor([[1.0, 0, 0, 0]]).expand(len(bed), 4),
         "opacities": torch.full((len(bed),), 0.9)}
    region = {"xmin": 0.3, "xmax": 1.2, "ymin": 0.3, "ymax": 1.2}
    gt = bed[(np.abs(bed[:, :2] - 0.75) < 0.451).all(1)]  # nodes 6 .. 24 on both axes
    res, grid = evaluate_geometry(g, GroundTruth(gt, region, 2.0, WATER),
                                  ablation.extract_config(preset_config("small"), 19 * 19, 0.01))
    assert res["n_gt"] == 19 * 19 and res["f1"]["10cm"] == 1.0 and res["chamfer"] < 0.005 and len(grid) > 350
    assert res["extraction"]["config"]["n_samples"] == 16 * 19 * 19


def test_evaluate_fused_flat_bed():
    # exact depth maps of the plane z = -1 from five cameras: every node of the region at -1, to 1 mm
    from test_fusion import cameras, depth_map

    cams = cameras(64)
    maps = {id(c): torch.tensor(depth_map(c, lambda xy: np.full(len(xy), -1.0))) for c in cams}
    x, y = np.meshgrid(np.arange(-10, 11) * 0.05, np.arange(-8, 9) * 0.05, indexing="ij")
    gt = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, -1.0)])
    truth = GroundTruth(gt, {"xmin": -0.5, "xmax": 0.5, "ymin": -0.4, "ymax": 0.4}, 1.0, WATER)
    views = [SimpleNamespace(camera=c) for c in cams]
    res, grid = evaluate_fused(lambda cam: maps[id(cam)], views, truth, FuseConfig(), 0.05)
    assert len(grid) == len(gt) and np.abs(grid[:, 2] + 1.0).max() < 1e-3
    assert res["f1"]["1%"] == 1.0 and res["n_gt"] == len(gt) and res["survey"]["wet"]["rmse"] < 1e-3
    assert (res["fusion"]["views"] == 5
            and res["fusion"]["voxel_m"] == pytest.approx(3 * res["fusion"]["gsd_m"]))


def test_eval_steps_avoid_opacity_resets():
    assert ablation.eval_steps(1500, 8) == [188, 375, 562, 750, 938, 1125, 1312]
    # resets every 150 steps before 750: 188 is 38 steps after the reset at 150 (opacities still recovering)
    assert (ablation.eval_steps(1500, 8, reset_every=150, reset_stop=750)
            == [149, 375, 562, 750, 938, 1125, 1312])
    assert ablation.eval_steps(10, 1) == []


def test_published_rows_are_the_papers_variants():
    published = load_published()
    assert set(published["table1_appearance"]["rows"]) == set(list(VARIANTS)[:5])
    assert set(published["table2_geometry"]["rows"]) == set(list(VARIANTS)[:5])


def test_tune_sets_nested_and_top_level_parameters():
    from ragsplat.train import preset_config
    from ragsplat.train.settings import PARAMS, with_value

    cfg = preset_config("small")
    capped = with_value(cfg, "densify.max_gaussians", 20000.0)
    assert capped.densify.max_gaussians == 20000 and isinstance(capped.densify.max_gaussians, int)
    assert capped.densify.prune_opa == cfg.densify.prune_opa and capped.iterations == cfg.iterations
    assert with_value(cfg, "lr_means", 1e-3).lr_means == 1e-3
    longer = with_value(cfg, "iterations", 4500.0)
    assert longer.iterations == 4500 and isinstance(longer.iterations, int)
    assert {"lr_means", "iterations", "densify.max_gaussians", "densify.grow_grad2d"} <= set(PARAMS)
    # a choice is tuned by its word, and the config still refuses a word it does not know
    assert with_value(cfg, "surfel_depth", "centre").surfel_depth == "centre" and "surfel_depth" in PARAMS
    assert "variant" not in PARAMS and "preset" not in PARAMS  # the tool's own options
    with pytest.raises(ConfigError):
        with_value(cfg, "surfel_depth", "middle")
    # a switch by true or false
    assert with_value(cfg, "detrend_albedo", "true").detrend_albedo is True and "detrend_albedo" in PARAMS
    assert with_value(cfg, "detrend_albedo", "false").detrend_albedo is False
    with pytest.raises(ValueError, match="true or false"):
        with_value(cfg, "detrend_albedo", "yes")


def test_true_ripples_are_each_photos_surface_from_the_scene(tmp_path):
    from ragsplat.datagen import conditions
    from ragsplat.datagen.spec import preset
    from tools.tune import true_ripples

    spec = preset("small-field")
    (tmp_path / "scene.json").write_text(json.dumps({"spec": spec.to_dict()}))
    gradient = true_ripples(tmp_path)
    xy = torch.tensor([[0.3, -1.2], [2.0, 0.5]])
    k, amplitude = conditions.ripple_waves(spec.conditions, spec.seed)
    for view in (0, 3):  # the photo's own phases, by its frame name
        want = conditions.ripple_gradient(xy.double().numpy(), k, amplitude,
                                          conditions.ripple_phases(spec.conditions, spec.seed, view))
        got = gradient(f"{view:04d}", xy)
        assert got.dtype == xy.dtype and np.allclose(got.numpy(), want, atol=1e-7)
    assert not torch.allclose(gradient("0000", xy), gradient("0003", xy))
    (tmp_path / "scene.json").write_text(json.dumps({"spec": preset("small").to_dict()}))
    with pytest.raises(ValueError, match="without ripples"):
        true_ripples(tmp_path)
    with pytest.raises(ValueError, match="no such file"):
        true_ripples(tmp_path / "elsewhere")


def test_default_jobs_and_the_gpus_they_share(monkeypatch):
    # `--jobs` left out: 2 processes on the CPU, JOBS_PER_GPU per GPU on CUDA, shared out round the GPUs.
    import torch

    from ragsplat.eval import ablation

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert ablation.default_jobs(None) == ablation.default_jobs("cpu") == ablation.JOBS == 2
    assert ablation.visible_gpus(None) == []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    assert ablation.default_jobs(None) == ablation.default_jobs("cuda") == 2 * ablation.JOBS_PER_GPU
    assert ablation.default_jobs("cuda:1") == ablation.JOBS_PER_GPU  # all on the one named
    assert ablation.default_jobs("cpu") == ablation.JOBS
    assert ablation.visible_gpus("cuda") == ablation.visible_gpus(None) == ["0", "1"]
    assert ablation.visible_gpus("cuda:1") == ablation.visible_gpus("cpu") == []
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2,3")
    assert ablation.visible_gpus(None) == ["2", "3"]
    # each local Dask worker takes one of them, round the list
    assert [ablation.worker_gpu(("2", "3"), k) for k in range(5)] == ["2", "3", "2", "3", "2"]


def test_gsplat_is_built_once_before_the_processes_on_cuda(monkeypatch, tmp_path):
    # gsplat's JIT start deletes a build folder without a library, so six processes building it at once
    # deleted each other's build (an H100, 2026-11-26): the parent builds it first when the rows train on CUDA
    import sys
    from argparse import Namespace

    from ragsplat import rasterize
    from ragsplat.cli import ablation as cli

    # build_gsplat imports gsplat's backend module (here a stand-in that counts its imports)
    pkg = tmp_path / "gsplat" / "cuda"
    pkg.mkdir(parents=True)
    (tmp_path / "gsplat" / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "_backend.py").write_text("import builtins\nbuiltins._gsplat_builds = getattr(builtins, "
                                     "'_gsplat_builds', 0) + 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in [m for m in sys.modules if m == "gsplat" or m.startswith("gsplat.")]:
        monkeypatch.delitem(sys.modules, name)
    import builtins

    monkeypatch.setattr(builtins, "_gsplat_builds", 0, raising=False)
    assert rasterize.gsplat_available()
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    for device, builds in (("cpu", 0), ("cuda", 1), ("cuda:1", 1), (None, 1)):
        for name in [m for m in sys.modules if m == "gsplat" or m.startswith("gsplat.")]:
            monkeypatch.delitem(sys.modules, name)
        builtins._gsplat_builds = 0
        cli.prepare(Namespace(vgg16=None, no_download=True, init="grid", device=device), "fingerprint")
        assert builtins._gsplat_builds == builds, device
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    builtins._gsplat_builds = 0
    cli.prepare(Namespace(vgg16=None, no_download=True, init="grid", device=None), "fingerprint")
    assert builtins._gsplat_builds == 0  # "auto" without CUDA trains on the CPU
