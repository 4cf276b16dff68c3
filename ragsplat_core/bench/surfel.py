"""Surfel rasterizer benchmark: forward+backward of the surfel kernels next to the 3DGS kernels, one process.

The scene is `bench.raster.make_scene` (Gaussians on a riverbed seen by a 256 x 256 camera); the surfels
are the same Gaussians without their thin third axis (scales[:, :2]), so both rasterizers draw the same
footprints. In one fresh process per (backend, N, threads), each timed iteration runs 3DGS `rasterize`
forward+backward, then `rasterize_surfels` with an image loss, then with a loss on every surfel output
(image, depth, normals, median depth, distortion), so all three see the same machine load; rows give
the medians and the median of the per-iteration ratios surfel / 3DGS.
`bench_surfels(...)` returns the rows; `format_table(rows)` formats them.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time

import torch

from ragsplat.bench import openmp_wait
from ragsplat.bench.raster import make_scene

_LOSSES = ("image", "all")


def time_pair(backend: str, n: int, size: int, repeats: int, warmup: int = 2, seed: int = 0,
              footprint: float = 1.0, threads: int | None = None) -> dict:
    """Median seconds of forward + backward (projection included) of 3DGS and of surfels, interleaved."""
    from ragsplat.rasterize import rasterize
    from ragsplat.rasterize_surfels import rasterize_surfels

    if threads:  # torch's and numba's pools; oversubscribed cores make 2 threads far slower than 1
        import numba

        torch.set_num_threads(threads)
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))

    *params, cam, bg = make_scene(n, size, seed, footprint)
    params = [p.requires_grad_(True) for p in params]
    means, quats, scales, opacities, colors = params
    scales2 = scales.detach()[:, :2].clone().requires_grad_(True)
    g = torch.Generator().manual_seed(seed + 1)
    w_img, w_depth, w_normal, w_median, w_dist = (torch.rand(size, size, k, generator=g)
                                                  for k in (3, 1, 3, 1, 1))

    def gauss():
        image = rasterize(means, quats, scales, opacities, colors, cam, bg, backend=backend)[0]
        return (image * w_img).sum()

    def surfel(loss):
        image, _, depth, meta = rasterize_surfels(means, quats, scales2, opacities, colors, cam, bg,
                                                  backend=backend)
        total = (image * w_img).sum()
        if loss == "all":
            total = total + (depth * w_depth).sum() + (meta["normals"] * w_normal).sum()
            total = total + (meta["median_depth"] * w_median).sum() + (meta["distortion"] * w_dist).sum()
        return total

    runs = {"3dgs": gauss, **{f"surfel-{loss}": (lambda loss=loss: surfel(loss)) for loss in _LOSSES}}
    times = {name: [] for name in runs}
    fwd = {name: [] for name in runs}
    for it in range(warmup + repeats):
        for name, run in runs.items():
            t0 = time.perf_counter()
            loss = run()
            t1 = time.perf_counter()
            loss.backward()
            t2 = time.perf_counter()
            for p in (*params, scales2):
                p.grad = None
            if it >= warmup:
                times[name].append(t2 - t0)
                fwd[name].append(t1 - t0)
    row = {"backend": backend, "n": n, "size": size, "footprint": footprint, "repeats": repeats,
           "threads": torch.get_num_threads(), "load_avg_1min": os.getloadavg()[0], **openmp_wait()}
    for name in runs:
        row[f"{name}_median_s"] = statistics.median(times[name])
        row[f"{name}_forward_median_s"] = statistics.median(fwd[name])
        if name != "3dgs":
            row[f"{name}_ratio"] = statistics.median(s / g for s, g in zip(times[name], times["3dgs"]))
    return row


# One (backend, N, threads) timed in a fresh interpreter: kwargs of `time_pair` in, the row as JSON out.
_WORKER = ("import json, sys; from ragsplat.bench.surfel import time_pair; "
           "print(json.dumps(time_pair(**json.loads(sys.argv[1]))))")


def bench_surfels(sizes=(40_000,), size: int = 256, repeats: int = 7, backend: str = "cpu",
                  threads=(0,)) -> list[dict]:
    """Runs every (threads, N) in a fresh process and returns the rows (threads 0 = one per core)."""
    rows = []
    for nthreads in threads:
        for n in sizes:
            kwargs = {"backend": backend, "n": n, "size": size, "repeats": repeats, "threads": nthreads}
            done = subprocess.run([sys.executable, "-c", _WORKER, json.dumps(kwargs)], capture_output=True,
                                  text=True, check=False)
            if done.returncode != 0:
                raise RuntimeError(f"surfel benchmark at N={n} failed: {done.stderr.strip()[-500:]}")
            rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    return rows


def format_table(rows: list[dict]) -> str:
    head = (f"{'backend':<8} {'thr':>3} {'N':>7} {'size':>5} {'3dgs s':>8} {'surfel s':>9} {'ratio':>6} "
            f"{'surfel+all s':>13} {'ratio':>6} {'load':>5}")
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r['backend']:<8} {r['threads']:>3} {r['n']:>7} {r['size']:>5} "
                     f"{r['3dgs_median_s']:>8.3f} {r['surfel-image_median_s']:>9.3f} "
                     f"{r['surfel-image_ratio']:>6.2f} {r['surfel-all_median_s']:>13.3f} "
                     f"{r['surfel-all_ratio']:>6.2f} {r['load_avg_1min']:>5.1f}")
    return "\n".join(lines)
