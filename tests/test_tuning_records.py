"""The tuning records (ragsplat_core/tuning/*.json) are data the configs agree with: each record's chosen
value is the value the config holds, and each record names its command, commit and dataset seed."""

from dataclasses import asdict

from ragsplat.surface import EXTRACT_TUNING, ExtractConfig
from ragsplat.tuning import record


def test_the_extraction_holds_the_recorded_choices():
    cfg = asdict(ExtractConfig())
    for chosen in (EXTRACT_TUNING["chosen"], EXTRACT_TUNING["despike"]["chosen"],
                   EXTRACT_TUNING["fill"]["chosen"]):
        assert {k: cfg[k] for k in chosen} == chosen
    assert EXTRACT_TUNING["dataset_seed"] == 1
    for step in ("min_opacity", "both", "despike", "fill"):
        assert EXTRACT_TUNING[step]["commit"] and EXTRACT_TUNING[step]["command"].startswith("ragsplat score")


def test_a_record_is_a_new_dict_each_time():
    a = record("extract")
    a["chosen"]["min_opacity"] = 0.0
    assert record("extract")["chosen"]["min_opacity"] == 0.7


def test_the_presets_hold_the_recorded_choices():
    from ragsplat.train.config import FIELD_TUNING, PRESETS, TUNING

    def value(cfg, name):
        return (getattr(cfg.densify, name.split(".", 1)[1]) if name.startswith("densify.")
                else getattr(cfg, name))

    small, field = PRESETS["small"], PRESETS["small-field"]
    steps = ("surfel_terms", "ssim_lambda", "refine_stop", "length", "surfel_depth")
    for rec in (TUNING, *(TUNING[k] for k in steps)):
        assert all(value(small, k) == v for k, v in rec["chosen"].items()), rec["chosen"]
        assert rec["commit"] and "python -m tools.tune" in rec["command"]
    assert all(value(field, k) == v for k, v in FIELD_TUNING["chosen"].items())
    assert field.lambda_normal == FIELD_TUNING["lambda_normal"]["kept"]
    assert field.ssim_lambda == FIELD_TUNING["ssim_lambda"]["kept"]
    assert (value(field, "densify.refine_stop_iter")
            == FIELD_TUNING["refine_stop"]["kept"]["densify.refine_stop_iter"])
    assert TUNING["dataset_seed"] == FIELD_TUNING["dataset_seed"] == 1


def test_the_field_cap_is_the_recorded_rules_choice():
    from statistics import mean

    from ragsplat.train.config import FIELD_TUNING, PRESETS

    rec = FIELD_TUNING["max_gaussians"]
    f1_3 = rec["columns"].index("F1@3% (%)")
    by_cap = {int(k.split()[0]): mean(s[f1_3] for s in v.values()) for k, v in rec["tried"].items()}
    assert PRESETS["small-field"].densify.max_gaussians == rec["chosen"]["densify.max_gaussians"]
    assert max(by_cap, key=by_cap.get) == rec["chosen"]["densify.max_gaussians"]
    assert PRESETS["small"].densify.max_gaussians in by_cap and rec["commit"] and rec["variant"]
    assert "python -m tools.tune" in rec["command"]


def test_the_field_survey_trains_the_recorded_water_terms():
    from ragsplat.train.config import FIELD_TUNING, PRESETS, VARIANTS
    from ragsplat.train.defaults import survey_variant

    rec = FIELD_TUNING["water_terms"]
    f1_3 = rec["columns"].index("F1@3% (%)")
    best = max(rec["tried"], key=lambda k: rec["tried"][k][f1_3])
    assert survey_variant("small-field") == rec["chosen"] == best
    assert rec["chosen"] in VARIANTS and survey_variant("small") == "2dgs+full"
    assert PRESETS["small-field"].wet_sh_degree == rec["kept"]["wet_sh_degree"]
    assert rec["commit"] and "python -m tools.tune" in rec["command"]


def test_the_long_preset_is_small_with_its_recorded_depth_and_cap():
    """`long` is `small` but for what long.json chose by its rule on the long reach's development stretch;
    the extraction's size cap follows the surfels' depth as extract.json's two records chose it."""
    import math
    from dataclasses import replace

    from ragsplat.surface import SIZE_CAP_M, size_cap_m
    from ragsplat.train.config import LONG_TUNING, PRESETS

    rec = LONG_TUNING
    assert rec["dataset_preset"] == "long" and rec["dataset_seed"] == 1 and rec["commit"]
    assert "python -m tools.retrain" in rec["command"]
    f1_1, f1_3 = rec["columns"].index("F1@1% (%)"), rec["columns"].index("F1@3% (%)")
    best3 = max(v[f1_3] for v in rec["tried"].values())
    near = {k: v for k, v in rec["tried"].items() if v[f1_3] >= best3 - 0.5}
    assert max(near, key=lambda k: near[k][f1_1]) == f"surfel_depth {rec['chosen']['surfel_depth']}"
    assert PRESETS["long"] == replace(PRESETS["small"], preset="long", **rec["chosen"])
    assert SIZE_CAP_M == {"ray": ExtractConfig().max_scale_m, "centre": math.inf}
    assert EXTRACT_TUNING["long"]["centre"]["picks"] == {"max_scale_gsd": ExtractConfig().max_scale_gsd,
                                                         "max_scale_m": "inf"}
    surfels = replace(PRESETS["long"], variant="2dgs+full")
    assert size_cap_m(surfels) == math.inf and size_cap_m(replace(surfels, surfel_depth="ray")) == 0.14
    assert size_cap_m(replace(surfels, variant="full")) == 0.14  # 3D Gaussians: the depth does not touch them


def test_a_record_s_choices_set_a_config_and_its_densification():
    from ragsplat.train.config import TrainConfig, chosen, with_chosen

    rec = {"chosen": {"lr_means": 0.002}, "stop": {"chosen": {"densify.refine_stop_iter": 7000}},
           "other": {"chosen": {"ssim_lambda": 0.5}}}
    assert chosen(rec, ("stop",)) == {"lr_means": 0.002, "densify.refine_stop_iter": 7000}
    cfg = with_chosen(TrainConfig(), chosen(rec, ("stop", "other")))
    assert (cfg.lr_means, cfg.ssim_lambda, cfg.densify.refine_stop_iter) == (0.002, 0.5, 7000)
    assert cfg.densify.max_gaussians == TrainConfig().densify.max_gaussians
