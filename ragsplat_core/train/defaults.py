"""What the commands that train many runs start from when not told, shared by `ragsplat ablation` (its rows)
and `ragsplat survey` (its tiles), one home each; their `--help` prints them. The training's own defaults (the
variants, the start `INIT`, the presets) are `train.config`'s; the ablation's alone (seeds, jobs per GPU) are
`ragsplat.eval.ablation`'s."""

from __future__ import annotations

from ragsplat.train.config import FIELD_TUNING, VARIANTS, WATER_TERMS

# The ablation's rows by default: the clear-water variants (the paper's and 2DGS's). The water's optics
# (`WATER_TERMS`) are for the scenes that need them (e.g. `small-field`), asked for by name.
CLEAR_VARIANTS = tuple(v for v in VARIANTS if v not in WATER_TERMS)
# Trainings at once on the CPU (the ablation's rows, the survey's tiles), each with cores / JOBS threads: on
# the 2-core CPU two single-threaded trainings together did 1.7x the steps of one with both threads (measured
# on `small`), because much of a step is small operations that two threads do not share well.
JOBS = 2


def tile_workers(tiles: int) -> int:
    """Local workers for a survey's `tiles` when not told: one per tile while they are fewer than two per
    `JOBS` worker, the cores shared among them, else `JOBS`. The tiles train for the same number of steps, so
    3 tiles on 2 workers take two rounds with a core idle in the second; 3 one-thread trainings at once on
    the 2-core CPU did 0.70-0.75 s a step each against 0.43 s alone (two at once: 0.44-0.45): 1.7 tiles' time
    instead of 2 (docs/lab/performance.md, "The whole reach from nothing")."""
    return tiles if tiles < 2 * JOBS else JOBS


# The variant `ragsplat survey` trains under each preset unless told (`--variant`): the best on the preset's
# development seed. small-field: with the surface's reflection, ahead of `2dgs+full` at 1 % and 3 % of depth
# with a lower RMSE and the same cover there, where all three water terms lose cover (small_field.json,
# "water_terms").
SURVEY_VARIANTS = {"small-field": FIELD_TUNING["water_terms"]["chosen"]}


def survey_variant(preset: str) -> str:
    """The variant a survey under `preset` trains by default (`SURVEY_VARIANTS`, else `2dgs+full`)."""
    return SURVEY_VARIANTS.get(preset, "2dgs+full")
