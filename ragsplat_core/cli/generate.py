"""`ragsplat generate`: render the synthetic riverbed benchmark (resumable, shardable)."""

from __future__ import annotations

import argparse
from dataclasses import replace

from ragsplat.cli.args import count, out_dir


def shard(text: str) -> tuple[int, int]:
    """`i/N` -> (i, N) with N >= 1 and 0 <= i < N (an argparse type: errors exit 2 with the usage)."""
    try:
        i, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must look like i/N (e.g. 0/4), got {text!r}") from None
    if not (n >= 1 and 0 <= i < n):
        raise argparse.ArgumentTypeError(f"{text}: need N >= 1 and 0 <= i < N")
    return i, n


def render_progress(label: str, quiet: bool = False):
    """`datagen.build.generate`'s progress callback drawing a bar per render job, and the list of its bars
    (close them when done)."""
    from ragsplat.cli.progress import bar

    bars = []

    def progress(event: dict) -> None:
        if event["event"] == "plan":
            bars.append(bar(event["images"], f"{label}: {event['views']} views x {event['passes']}", "img",
                            disable=quiet))
        elif event["event"] == "retry":
            bars[-1].close()
            print(f"the renderer crashed (signal {event['signal']}, see {event['log']}); "
                  "starting it again from the finished images", flush=True)
        else:
            bars[-1].update(1)

    return progress, bars


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ragsplat.datagen.spec import PRESETS

    parser.add_argument("--preset", default="small",
                        help=f"scene size: {', '.join(PRESETS)} (default: small)")
    parser.add_argument("--out", required=True, type=out_dir,
                        help="dataset directory (created; reruns resume)")
    parser.add_argument("--shard", default=(0, 1), type=shard, metavar="i/N",
                        help="render only views k with k mod N == i (0 <= i < N); merge when all are done")
    parser.add_argument("--seed", type=count, default=0, help="scene seed (default 0): same seed, same data")
    parser.add_argument("--stretch", type=float, nargs=2, metavar=("X0", "X1"),
                        help="only a stretch of a reach, for development work: the wet training photos "
                             "within half a footprint of x in [X0, X1) (m), then OUT/stretch_X0_X1/ with "
                             "their survey and the ground truth of that core (`ragsplat score --truth` reads "
                             "it)")
    parser.add_argument("--no-water", action="store_true", help="dry scene: render only the dry set")
    parser.add_argument("--water-slope", type=float, metavar="S",
                        help="the water surface falls by the fraction S downstream (+x; 0.01: 1 %%), the bed "
                             "and banks with it (depths as in the flat preset); default: the preset's")
    parser.add_argument("--no-radiance-scale", action="store_true",
                        help="water refraction colour 1 instead of 1/n^2 (no radiance drop at the interface)")
    parser.add_argument("--turbidity", type=float, metavar="S",
                        help="field conditions: the water body's absorption and scattering times S (clear "
                             "river water, the small-field default, is 1; 0 is clear water)")
    parser.add_argument("--reflection", action=argparse.BooleanOptionalAction, default=None,
                        help="field conditions: Fresnel reflection of sky and sun (glint) at the water "
                             "surface")
    parser.add_argument("--ripple-amplitude", type=float, metavar="M",
                        help="field conditions: rms height (m) of the ripples, a new surface in every photo; "
                             "0: flat")
    parser.add_argument("--sun-elevation", type=float, metavar="DEG",
                        help="sun elevation above the horizon (deg)")
    parser.add_argument("--sun-azimuth", type=float, metavar="DEG",
                        help="sun azimuth (deg, counter-clockwise from +x): with --sun-elevation, where the "
                             "glint falls")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from ragsplat.datagen import flight
    from ragsplat.datagen.build import generate, overhead_fraction, stretch
    from ragsplat.datagen.spec import preset, validate, with_conditions, with_slope

    spec = preset(args.preset, seed=args.seed)
    if args.no_radiance_scale and spec.water is not None:
        spec = replace(spec, water=replace(spec.water, radiance_scale=False))
    if args.water_slope is not None:
        spec = with_slope(spec, args.water_slope)
    if args.no_water:
        spec = replace(spec, water=None)
    if (args.turbidity, args.reflection, args.ripple_amplitude) != (None, None, None):
        spec = with_conditions(spec, args.turbidity, args.reflection, args.ripple_amplitude)
    sun = {k: v for k, v in (("sun_elevation", args.sun_elevation), ("sun_azimuth", args.sun_azimuth))
           if v is not None}
    spec = replace(spec, light=replace(spec.light, **sun))
    validate(spec)
    print(f"{spec.preset}: {len(flight.plan(spec))} views, {spec.flight.width} px, ground sample distance "
          f"{flight.gsd(spec) * 100:.2f} cm/px on the bed ({spec.bed.depth:g} m deep), seed {spec.seed}")
    progress, bars = render_progress(spec.preset, args.quiet)
    try:
        if args.stretch is not None:
            print(f"{stretch(spec, args.out, tuple(args.stretch), progress=progress)}: the stretch's photos, "
                  "survey and ground truth")
            return 0
        summary = generate(spec, args.out, shard=args.shard, progress=progress)
    finally:
        for b in bars:
            b.close()
    if summary["damaged"]:
        print(f"{len(summary['damaged'])} damaged files rendered again: {', '.join(summary['damaged'][:5])}"
              + (" ..." if len(summary["damaged"]) > 5 else ""))
    if summary["rendered"]:
        per = summary["render_s"] / summary["rendered"]
        print(f"rendered {summary['rendered']} images on {summary['device']} in {summary['wall_s']:.1f} s: "
              f"Cycles {summary['render_s']:.1f} s ({per:.2f} s/image), overhead "
              f"{100 * overhead_fraction(summary):.1f} % of Cycles time (scene build "
              f"{summary['build_s']:.1f} s); {summary['skipped']} already present")
    else:
        print(f"nothing to render: {summary['skipped']} images already present")
    state = "complete: metadata written" if summary["complete"] else "incomplete: other shards still missing"
    print(f"{args.out}: {state}")
    return 0
