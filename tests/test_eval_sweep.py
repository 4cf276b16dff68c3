"""The turbidity sweep's report from its levels' results.json (made up here; `ragsplat sweep` makes them by
rendering and ablating each level): the best reference is the best by F1@3% that does not read the ground
truth, clear water has no Secchi-like depth, and the table, JSON and figure say so."""

import json

import pytest

from ragsplat.datagen.conditions import secchi_depth
from ragsplat.errors import OutputError
from ragsplat.eval import sweep


def _results(extinction, method_f1_3, refs):
    def fig(f1_1, f1_3):
        return {"F1@1% (%)": {"mean": f1_1, "std": 0.5, "n": 3},
                "F1@3% (%)": {"mean": f1_3, "std": 0.2, "n": 3},
                "p95 (cm)": {"mean": 8.0, "std": None, "n": 1},
                "wet cover (%)": {"mean": 99.0, "std": None, "n": 1}}

    summary = {"2dgs+full+reflection": fig(70.0, method_f1_3), "2dgs+full": fig(68.0, method_f1_3 - 1)}
    summary.update({name: fig(f - 20, f) for name, f in refs.items()})
    return {"conditions": {"extinction_per_m": extinction, "sun_elevation_deg": 55.0},
            "summary": summary, "seeds": [0, 1, 2], "dataset_fingerprint": "x"}


def test_the_report_takes_the_best_reference_that_does_not_read_the_answer(tmp_path):
    levels = {0.0: [0.0, 0.0, 0.0], 2.0: [0.88, 0.34, 0.42]}
    refs = {0.0: {"oracle plane": 99.0, "triangulation (refracted)": 90.0, "3dgs x n": 80.0},
            2.0: {"oracle plane": 99.0, "triangulation (refracted)": 70.0, "dietrich (tracks)": 75.0}}
    for t, ext in levels.items():
        (tmp_path / sweep.level_name(t)).mkdir()
        (tmp_path / sweep.level_name(t) / "results.json").write_text(
            json.dumps(_results(ext, 95.0 - t, refs[t])))
    text = sweep.report(tmp_path, [0.0, 2.0], ["2dgs+full+reflection", "2dgs+full"])
    rows = json.loads((tmp_path / "sweep.json").read_text())["levels"]
    assert [r["best_reference"] for r in rows] == ["triangulation (refracted)", "dietrich (tracks)"]
    assert rows[0]["secchi_like_depth_m"] == [None, None, None]
    assert rows[1]["secchi_like_depth_m"] == pytest.approx(list(secchi_depth([0.88, 0.34, 0.42], 55.0)))
    assert "| 0 | clear |" in text and "+5.0 |" in text and "+18.0 |" in text  # the lead at 3 %
    assert (tmp_path / "sweep.png").stat().st_size > 0 and (tmp_path / "sweep.md").read_text() == text
    with pytest.raises(OutputError, match="turbidity 4"):
        sweep.report(tmp_path, [0.0, 4.0], ["2dgs+full+reflection"])
    with pytest.raises(OutputError, match="no row of 3dgs"):
        sweep.report(tmp_path, [0.0], ["3dgs"])


def test_the_command_renders_and_ablates_each_level_then_reports(tmp_path, monkeypatch, capsys):
    """`ragsplat sweep` as a user runs it, with the renderer and the ablation command stood in for (they
    render and train: tested on their own, the sharing in tests/test_blender_sweep.py): each level's dataset
    at its turbidity without lens photos, the dry passes shared from the first level, its ablation with the
    sweep's variants and seeds, then the report from their results."""
    from types import SimpleNamespace

    from ragsplat.cli import main as cli
    from ragsplat.datagen import build
    from ragsplat.train.defaults import survey_variant

    calls = []

    def render(spec, out, progress=None, share=None):
        calls.append(("dataset", str(out), spec, share))
        return {"rendered": 1, "skipped": 0, "wall_s": 0.0}

    def fake(name, argv):
        calls.append((name, argv[argv.index("--out") + 1], argv, None))

        def run(args):
            out = tmp_path / "runs" / argv[argv.index("--out") + 1].rsplit("/", 1)[1]
            t = float(out.name.split("-", 1)[1])
            out.mkdir(parents=True, exist_ok=True)
            (out / "results.json").write_text(json.dumps(
                _results([0.44 * t, 0.17 * t, 0.21 * t], 95.0 - t, {"triangulation (refracted)": 90.0})))
            return 0

        return SimpleNamespace(run=run), None

    sweep_cmd, args = cli.command("sweep", ["--data", str(tmp_path / "data"), "--out", str(tmp_path / "runs"),
                                            "--turbidity", "0", "2", "--seeds", "0", "1", "--jobs", "2"])
    monkeypatch.setattr(cli, "command", fake)
    monkeypatch.setattr(build, "generate", render)
    assert sweep_cmd.run(args) == 0
    want = [(name, str(tmp_path / root / f"turbidity-{t}")) for t in (0, 2)
            for name, root in (("dataset", "data"), ("ablation", "runs"))]
    assert [c[:2] for c in calls] == want
    (_, _, clear, first), (_, _, murky, shared), ablation = calls[0], calls[2], calls[3][2]
    assert (clear.conditions.turbidity, murky.conditions.turbidity) == (0.0, 2.0)
    assert murky.preset == "small-field" and murky.seed == 0 and not murky.render.lens
    assert first is None and shared == tmp_path / "data" / "turbidity-0"

    def after(argv, option, until=None):
        i = argv.index(option) + 1
        return argv[i:argv.index(until)] if until else argv[i]

    assert after(ablation, "--variants", "--seeds") == [survey_variant("small-field"), "2dgs+full"]
    assert after(ablation, "--seeds", "--jobs") == ["0", "1"] and after(ablation, "--preset") == "small-field"
    assert "| 2 | 3.97 |" in capsys.readouterr().out and (tmp_path / "runs" / "sweep.png").is_file()
