"""The same dataset with less render noise in what training sees: `python -m tools.resample DATA OUT SAMPLES`.

OUT is a copy of the synthetic dataset DATA whose training views' wet photos are rendered again at SAMPLES
samples a pixel (Cycles' noise falls as one over its square root; every other setting, the sampling seed and
the ripples included, as DATA has them). The held-out views' photos, the dry and depth passes and the ground
truth are DATA's; the cached triangulation is left out (it comes from the wet photos: OUT triangulates its
own). scene.json records the training photos' samples under `resampled`. Measures what the renderer's noise
costs a training run (`python -m tools.render_noise` measures the noise), not a benchmark of its own."""

from __future__ import annotations

import argparse
import json
import shutil
from dataclasses import replace
from pathlib import Path

from ragsplat.datagen import flight
from ragsplat.datagen.build import _task, render_job, run_blender
from ragsplat.datagen.spec import SceneSpec
from ragsplat.dataset import layout
from ragsplat.dataset.colmap import STAMP, TRACKS, TRIANGULATED
from ragsplat.outputs import write_json

TRIANGULATION = "colmap/triangulation"  # the triangulation's scratch folder (`colmap.triangulate`)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.resample", description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("samples", type=int)
    args = parser.parse_args(argv)
    spec = SceneSpec.from_dict(json.loads((args.data / "scene" / "spec.json").read_text()))
    skip = {args.data / p for p in (TRIANGULATED, TRACKS, STAMP, TRIANGULATION)}
    shutil.copytree(args.data, args.out, ignore=lambda d, names: [n for n in names if Path(d) / n in skip],
                    dirs_exist_ok=True)
    train = [p for p in flight.plan(spec) if p.split == "train"]
    tasks = [_task(spec, "wet", p, layout.output_path(args.out, "wet", p.name)) for p in train]
    job = render_job(spec, args.out, train[0].camera, tasks)
    run_blender(replace(job, render=replace(job.render, samples=args.samples)), args.out / "scene")
    scene = json.loads((args.out / layout.SCENE).read_text())
    scene["resampled"] = {"from": str(args.data), "train_wet_samples": args.samples,
                          "views": [p.name for p in train]}
    write_json(args.out / layout.SCENE, scene)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
