"""The tuning records (ragsplat_core/tuning/*.json) are data the configs agree with: each record's chosen value
is the value the config holds, and each record names its command, commit and dataset seed."""

from dataclasses import asdict

from ragsplat_core.surface import EXTRACT_TUNING, ExtractConfig
from ragsplat_core.tuning import record


def test_the_extraction_holds_the_recorded_choices():
    cfg = asdict(ExtractConfig())
    for chosen in (EXTRACT_TUNING["chosen"], EXTRACT_TUNING["despike"]["chosen"], EXTRACT_TUNING["fill"]["chosen"]):
        assert {k: cfg[k] for k in chosen} == chosen
    assert EXTRACT_TUNING["dataset_seed"] == 1
    for step in ("min_opacity", "both", "despike", "fill"):
        assert EXTRACT_TUNING[step]["commit"] and EXTRACT_TUNING[step]["command"].startswith("ragsplat eval")


def test_a_record_is_a_new_dict_each_time():
    a = record("extract")
    a["chosen"]["min_opacity"] = 0.0
    assert record("extract")["chosen"]["min_opacity"] == 0.7
