"""The tuning records: how the presets' and the extraction's values were chosen, kept as data. One JSON file
per record (`small`, `small_field`, `long`, `extract`): every value tried with its figures, the rule, the
chosen value, the command, the commit and the dataset seed it was chosen on. The configs hold the chosen
values (`train/config.py`, `surface.ExtractConfig`); `ragsplat ablation` repeats the records in results.json;
the sweeps' tables and readings are in docs/lab/history.md."""

from __future__ import annotations

import json
from importlib import resources


def record(name: str) -> dict:
    """The tuning record `name` (a new dict each call)."""
    return json.loads(resources.files(__name__).joinpath(f"{name}.json").read_text(encoding="utf-8"))
