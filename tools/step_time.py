"""Seconds a training step takes from a checkpoint, one training alone or K at once as a survey's tile workers
run them (one thread each, `cli.cluster`'s environment): `python -m tools.step_time DATA TRAIN --budget N
[--preset long] [--steps 40] [--at-once K]`.

DATA is a survey's imported data (RUN/data), TRAIN a training folder of it (RUN/train or a tile's; copied, so
it is left as it is), `--budget` the survey's Gaussian budget for it (its log). Each training takes 3 steps to
warm up, then times `--steps` more; prints each one's seconds a step and the steps a second of all together.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ragsplat.threads import THREAD_VARIABLES


def one(data: Path, train: Path, budget: int, preset: str, steps: int) -> float:
    """Seconds a step of the training in `train` (resumed from its checkpoint), after 3 to warm up."""
    from ragsplat.dataset.load import load_dataset
    from ragsplat.survey.stages.training import survey_training
    from ragsplat.train import Trainer
    from ragsplat.train.defaults import survey_variant

    ds = load_dataset(data, splits=("train",), load_dry=False)
    trainer = Trainer(survey_training(ds, preset, survey_variant(preset), budget=budget), ds, train)
    for _ in range(3):
        trainer.train_step()
    t0 = time.perf_counter()
    for _ in range(steps):
        trainer.train_step()
    return (time.perf_counter() - t0) / steps


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.step_time", description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("train", type=Path)
    parser.add_argument("--budget", type=int, required=True)
    parser.add_argument("--preset", default="long")
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--at-once", type=int, default=1, metavar="K")
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)  # a child: time, print, exit
    args = parser.parse_args(argv)
    if args.one:
        print(f"{one(args.data, args.train, args.budget, args.preset, args.steps):.4f}")
        return 0
    env = {**os.environ, **{name: "1" for name in THREAD_VARIABLES}}
    with tempfile.TemporaryDirectory() as tmp:
        children = []
        for k in range(args.at_once):
            copy = Path(tmp) / str(k)
            shutil.copytree(args.train, copy)
            children.append(subprocess.Popen(
                [sys.executable, "-m", "tools.step_time", str(args.data), str(copy), "--budget",
                 str(args.budget), "--preset", args.preset, "--steps", str(args.steps), "--one"],
                env=env, stdout=subprocess.PIPE, text=True))
        seconds = [float(c.communicate()[0].split()[-1]) for c in children]
    print(f"{args.at_once} at once, one thread each: "
          + ", ".join(f"{s:.3f}" for s in seconds) + f" s a step; {sum(1 / s for s in seconds):.2f} steps/s "
          "in all")
    return 0


if __name__ == "__main__":
    sys.exit(main())
