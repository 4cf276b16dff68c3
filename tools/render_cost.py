"""What each field condition costs the renderer: `python -m tools.render_cost [--preset small]
[--views 4]`.

Renders the same few views (every k-th of the flight plan, all three passes) of the ideal preset, of each
effect alone and of all of them (the preset's `-field` conditions), one after the other in one run, and
prints seconds per image by pass and the ratio of each run's total to the ideal one. The whole dataset's
time scales with the views (a wet, a dry and a depth image each).
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

from ragsplat.datagen import flight
from ragsplat.datagen.build import generate
from ragsplat.datagen.spec import preset, with_conditions


def variants(name: str) -> dict:
    """{label: spec}: the ideal preset, each effect alone, and all (the `-field` preset's conditions)."""
    ideal = preset(name)
    field = preset(f"{name}-field").conditions
    alone = replace(field, turbidity=0.0, reflection=False, ripple_amplitude=0.0, targets=0)
    return {"ideal": ideal,
            "turbid": with_conditions(replace(ideal, conditions=alone), turbidity=field.turbidity),
            "reflection": with_conditions(replace(ideal, conditions=alone), reflection=True),
            "ripples": with_conditions(replace(ideal, conditions=alone),
                                       ripple_amplitude=field.ripple_amplitude),
            "targets": replace(ideal, conditions=replace(alone, targets=field.targets)),
            "all": replace(ideal, conditions=field)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.render_cost", description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="small",
                        help="an ideal preset that has a -field twin (default small)")
    parser.add_argument("--views", type=int, default=4, help="views rendered per variant (default 4)")
    args = parser.parse_args(argv)
    specs = variants(args.preset)
    count = len(flight.plan(specs["ideal"]))
    shard = (0, max(1, count // args.views))
    print(f"{args.preset}: views 0, {shard[1]}, {2 * shard[1]}, ... of {count}, "
          f"wet + dry + depth each; seconds per image inside Cycles' render calls (sync included)")
    totals = {}
    with tempfile.TemporaryDirectory() as tmp:
        for label, spec in specs.items():
            events = []
            generate(spec, Path(tmp) / label, shard=shard, progress=lambda e, out=events: out.append(e))
            done = [e for e in events if e["event"] == "done"]
            per = {kind: [e["render_s"] for e in done if e["kind"] == kind]
                   for kind in ("wet", "dry", "depth")}
            totals[label] = sum(sum(v) for v in per.values())
            print(f"  {label:10s} " + "  ".join(f"{k} {sum(v) / len(v):6.2f} s" for k, v in per.items() if v)
                  + f"  total {totals[label]:7.1f} s  x{totals[label] / totals['ideal']:.2f} of ideal")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
