"""`ragsplat render RUN --view NAME|all [--wet|--dry|--depth] [--split train|test|all] [--out DIR] [--data
DIR]`.

Renders a finished training run at the camera poses of its dataset, without retraining
(`ragsplat.runs.Model`): through the water as trained (`--wet`), the true Gaussians without the
interface (`--dry`: the bed as if drained), or the z-depth of the dry render (`--depth`: EXR in metres and a
colour PNG). Writes NAME.png (and NAME.exr) per view into --out (default RUN/renders/KIND).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ragsplat.cli.args import dataset_dir, out_dir


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, metavar="RUN", help="a finished `ragsplat train` output directory")
    parser.add_argument("--view", required=True, metavar="NAME|all",
                        help="a frame name of the dataset (e.g. 0060), or all")
    kind = parser.add_mutually_exclusive_group()
    kind.add_argument("--wet", dest="kind", action="store_const", const="wet",
                      help="what the camera sees through the water, as trained (default)")
    kind.add_argument("--dry", dest="kind", action="store_const", const="dry",
                      help="the true Gaussians without the interface: the bed as if drained")
    kind.add_argument("--depth", dest="kind", action="store_const", const="depth",
                      help="z-depth (m) of the dry render: NAME.exr (float32, channel Y) and a colour "
                           "NAME.png")
    parser.set_defaults(kind="wet")
    parser.add_argument("--split", choices=("train", "test", "all"), default="all",
                        help="the views --view chooses from (default: all)")
    parser.add_argument("--out", type=out_dir, metavar="DIR",
                        help="output directory (default: RUN/renders/KIND)")
    parser.add_argument("--data", type=dataset_dir, metavar="DIR",
                        help="the run's dataset directory (default: the one RUN/config.json names)")


def run(args: argparse.Namespace) -> int:
    from ragsplat.cli.progress import bar
    from ragsplat.dataset.load import SPLITS
    from ragsplat.runs import load_model, render_views, select_views

    model, ds = load_model(args.run, args.data, SPLITS if args.split == "all" else (args.split,))
    views = select_views(ds, args.view, args.split)
    out = args.out if args.out is not None else args.run / "renders" / args.kind
    with bar(len(views), f"render {args.kind}", "view", disable=len(views) == 1) as b:
        written = render_views(model, views, args.kind, out, on_view=lambda view: b.update(1))
    print(f"wrote {written[0]}" if len(written) == 1 else f"wrote {len(written)} files for {len(views)} "
          f"view{'s' * (len(views) > 1)} to {out}")
    return 0
