"""Where a training step's time goes, on the device it runs on: `python -m tools.step_profile [--count N]
[--variants full 2dgs+full] [--steps 20] [--device cuda]`.

The `ragsplat bench train-step` scene (256 px, N Gaussians, SH degree 3, no refinement in the timed steps):
for each variant the median step, torch.profiler's operators ranked by their device time and by their own
host time over `--steps` steps, and on CUDA the host's waits for the device inside a step (torch's sync
debug mode: each synchronising call, counted by where it was made).
"""

from __future__ import annotations

import argparse
import collections
import statistics
import time
import warnings

import torch


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.step_profile",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=200_000)
    parser.add_argument("--variants", nargs="+", default=["full", "2dgs+full"])
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--rows", type=int, default=20, help="operators shown per table")
    args = parser.parse_args(argv)
    from ragsplat.bench.train_step import DEPTH, _dataset
    from ragsplat.train import Trainer, preset_config
    from ragsplat.water_surface import WaterSurface

    cuda = args.device.startswith("cuda")
    ds = _dataset(args.count, WaterSurface(0.0, 1.33), args.device)
    for variant in args.variants:
        cfg = preset_config("paper", variant=variant, device=args.device, init_depth=DEPTH,
                            init_count=args.count, sh_degree_every=1, checkpoint_every=0)
        tr = Trainer(cfg, ds, None)
        for _ in range(5):  # warm-up: every view's matrices on the device, the kernels loaded
            tr.train_step()
        times = []
        for _ in range(args.steps):
            t0 = time.perf_counter()
            tr.train_step()
            if cuda:
                torch.cuda.synchronize()
            times.append(time.perf_counter() - t0)
        print(f"\n== {variant}: {tr.num_gaussians} Gaussians, median step {statistics.median(times):.4f} s "
              f"({args.steps} steps, {args.device})")
        if cuda:  # the synchronising calls of one step, by their place in the code
            torch.cuda.set_sync_debug_mode("warn")
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                tr.train_step()
                torch.cuda.synchronize()
            torch.cuda.set_sync_debug_mode("default")
            sites = collections.Counter(f"{w.filename.rsplit('/', 2)[-2:]}:{w.lineno}" for w in caught
                                        if "synchroniz" in str(w.message))
            print(f"host waits in one step: {sum(sites.values())}")
            for site, k in sites.most_common():
                print(f"  {k:3d} {site}")
        activities = [torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA] if cuda
                                                               else [])
        with torch.profiler.profile(activities=activities) as prof:
            for _ in range(args.steps):
                tr.train_step()
            if cuda:
                torch.cuda.synchronize()
        table = prof.key_averages()
        if cuda:
            print(table.table(sort_by="self_cuda_time_total", row_limit=args.rows, max_name_column_width=60))
        print(table.table(sort_by="self_cpu_time_total", row_limit=args.rows, max_name_column_width=60))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
