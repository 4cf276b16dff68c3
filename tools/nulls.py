"""The null-model table of the README: `python -m tools.nulls [PRESET:SEEDS ...]` (e.g. small:0,1,2).

The same scores `ragsplat generate` writes into scene.json (`build.null_models`), computed from the
heightfield alone, without rendering: a flat plane at the median height of the submerged ground truth
(and at its mean depth), F1 in % at 1 % / 3 % of the maximum depth and at 10 / 30 cm.
"""

from __future__ import annotations

import sys

from ragsplat.datagen import flight
from ragsplat.datagen.bed import ground_truth, make_bed, shear
from ragsplat.datagen.build import max_depth, null_models
from ragsplat.datagen.spec import preset
from ragsplat.dataset import layout


def table(runs: list[tuple[str, int]]) -> str:
    lines = [("| preset, seed | max depth | F1 @ 1 % | F1 @ 3 % | F1 @ 10 cm | F1 @ 30 cm | mean-depth "
              "plane F1 @ 3 % |"),
             "|---|---|---|---|---|---|---|"]
    for name, seed in runs:
        spec = preset(name, seed=seed)
        grid, _ = ground_truth(spec, make_bed(spec), flight.eval_region(spec), layout.GT_GRID_STEP)
        scores = null_models(spec, shear(spec, grid))
        m, mean = scores["median_plane"], scores["mean_depth_plane"]
        lines.append(f"| {name}, {seed} | {max_depth(spec):g} m | {100 * m['f1_1%']:.1f} | "
                     f"{100 * m['f1_3%']:.1f} | {100 * m['f1_10cm']:.1f} | {100 * m['f1_30cm']:.1f} | "
                     f"{100 * mean['f1_3%']:.1f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    args = sys.argv[1:] or ["smoke:0,1,2,3,4", "small:0,1,2", "paper-reach:0,1", "small-bed:0"]
    print(table([(name, int(s)) for arg in args for name, seeds in [arg.split(":")]
                 for s in seeds.split(",")]))
