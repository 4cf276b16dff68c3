import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from eval import ablation, metrics
from eval.ablation import run_ablation
from eval.evaluate import evaluate_geometry, evaluate_views
from eval.report import load_published, table1, table2, write_outputs
from ragsplat_core.errors import ConfigError, OutputError
from ragsplat_core.train.config import VARIANTS


def fake_row(i: int) -> dict:
    """Per-variant numbers made up for the layout tests (distinct per variant so rows can be told apart)."""
    app = {"psnr": 20.0 + i, "ssim": 0.5 + 0.01 * i, "lpips": None}
    geo = {"chamfer": 0.1 * (i + 1), "precision@0.1": 0.5, "recall@0.1": 0.25, "f1@0.1": 1 / 3,
           "precision@0.3": 1.0, "recall@0.3": 1.0, "f1@0.3": 1.0}
    curve = [{"iteration": k * 10, "time_s": 30.0 * k, "psnr_refr": 15 + k + i, "psnr_dry": 12 + k,
              "f1@0.1": 0.1 * k} for k in range(1, 4)]
    return {"appearance": {"refr": app, "dry": dict(app, psnr=float("nan")), "per_view": []},
            "num_gaussians": 12345, "train_time_s": 90.0, "geometry": geo, "curve": curve}


def test_tables_put_paper_values_beside_ours():
    published = load_published()
    rows = {v: fake_row(i) for i, v in enumerate(VARIANTS)}
    t1 = table1(rows, published)
    t2 = table2(rows, published)
    full = next(line for line in t2.splitlines() if line.startswith("| full |"))
    # CD 0.5 m vs the paper's 0.011; P 50 % vs 91.56; F1 as a percentage
    assert full.startswith("| full | 0.500 | 0.011 | 50.00 | 91.56 | 25.00 | 96.58 | 33.33 | 94.00 |")
    base = next(line for line in t1.splitlines() if line.startswith("| 3dgs |"))
    # the paper leaves 3dgs refr empty; LPIPS missing on our side; 12345 Gaussians -> 12.3 K; 90 s -> 1.5 min
    assert base.startswith("| 3dgs | 0.500 |  | 20.00 |  | n/a |  | 0.500 | 0.682 | n/a | 14.12 |")
    assert base.endswith("| 12.3 | 40.0 | 1.5 | 6.8 |")
    aniso = next(line for line in t1.splitlines() if line.startswith("| full+anisotropic |"))
    assert "| 0.550 | - |" in aniso  # not in the paper


def test_write_outputs_files(tmp_path):
    rows = {v: fake_row(i) for i, v in enumerate(list(VARIANTS)[:3])}
    text = write_outputs(tmp_path, rows, {"preset": "smoke", "seed": 3}, "weights missing")
    assert "LPIPS n/a: weights missing" in (tmp_path / "table1.md").read_text()
    assert (tmp_path / "table2.md").read_text() in text
    res = json.loads((tmp_path / "results.json").read_text(), parse_constant=lambda c: pytest.fail(c))
    assert res["seed"] == 3 and list(res["variants"]) == list(list(VARIANTS)[:3])
    assert res["variants"]["3dgs"]["appearance"]["dry"]["psnr"] is None  # NaN stored as null
    assert res["lpips"] == {"available": False, "reason": "weights missing"}
    png = (tmp_path / "error_vs_time.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


def make_data(root):
    root.mkdir()
    (root / "transforms.json").write_text('{"frames": []}')
    return root


def test_rows_are_reused_and_keyed(tmp_path, monkeypatch):
    monkeypatch.setattr(metrics, "default_vgg16_path", lambda: tmp_path / "absent.pth")
    data, out = make_data(tmp_path / "data"), tmp_path / "out"
    calls = []

    def train(variant, data, out, preset, seed, lpips_metric):
        calls.append(variant)
        return fake_row(list(VARIANTS).index(variant))

    quiet = {"log": lambda s: None}
    run_ablation(data, out, "smoke", ["3dgs", "full"], 0, train, **quiet)
    assert calls == ["3dgs", "full"]
    rows = run_ablation(data, out, "smoke", ["3dgs", "position", "full"], 0, train, **quiet)
    assert calls == ["3dgs", "full", "position"]  # only the missing row was trained
    assert list(rows) == ["3dgs", "position", "full"]
    res = json.loads((out / "results.json").read_text())
    assert res["variants"]["full"]["key"]["seed"] == 0 and "row_total_s" in res["variants"]["full"]["timings"]
    # a subset run still tabulates the other finished rows
    run_ablation(data, out, "smoke", ["full"], 0, train, **quiet)
    assert "| position |" in (out / "table1.md").read_text() and len(calls) == 3
    with pytest.raises(OutputError, match="seed"):
        run_ablation(data, out, "smoke", ["full"], 1, train, **quiet)
    with pytest.raises(ConfigError, match="unknown variant"):
        run_ablation(data, out, "smoke", ["nope"], 0, train, **quiet)


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


def test_evaluate_geometry_flat_bed():
    x, y = np.meshgrid(np.arange(30) * 0.05, np.arange(30) * 0.05, indexing="ij")
    bed = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, -2.0)])
    g = {"means": torch.tensor(bed), "scales": torch.tensor([[0.03, 0.03, 0.003]]).expand(len(bed), 3),
         "quats": torch.tensor([[1.0, 0, 0, 0]]).expand(len(bed), 4), "opacities": torch.full((len(bed),), 0.9)}
    region = {"xmin": 0.3, "xmax": 1.2, "ymin": 0.3, "ymax": 1.2}
    gt = bed[(np.abs(bed[:, :2] - 0.75) < 0.451).all(1)]  # nodes 6 .. 24 on both axes
    res = evaluate_geometry(g, gt, region, ablation.extract_config("smoke", 19 * 19, seed=0))
    assert res["n_gt"] == 19 * 19 and res["f1@0.1"] == 1.0 and res["chamfer"] < 0.005
    assert res["extraction"]["config"]["n_samples"] == 16 * 19 * 19


def test_eval_steps_avoid_opacity_resets():
    assert ablation.eval_steps(1500, 5) == [300, 600, 900, 1200]
    # resets every 150 steps until 750: 300 and 600 would see freshly reset opacities
    assert ablation.eval_steps(1500, 5, reset_every=150, reset_stop=750) == [299, 599, 900, 1200]
    assert ablation.eval_steps(10, 1) == []


def test_published_rows_are_the_papers_variants():
    published = load_published()
    assert set(published["table1_appearance"]["rows"]) == set(list(VARIANTS)[:5])
    assert set(published["table2_geometry"]["rows"]) == set(list(VARIANTS)[:5])
