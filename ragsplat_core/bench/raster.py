"""Rasterizer benchmark: median forward+backward time and peak memory per backend and Gaussian count.

The scene imitates a trained riverbed model: Gaussians spread over the ground footprint of a camera 3 m
above a gently rippled bed (tilted 20 degrees), flattened along the bed normal, each a few pixels across
(in-plane sigma 0.6-1.2x the mean spacing, times `footprint`), mostly opaque. Each configuration runs in
its own process so its peak RSS is its own. Rows also give the process CPU time (all threads) and the
1-minute load average: on a shared machine wall time depends on what else runs. With more runnable
threads than cores, OpenMP's default spin-waiting makes torch ops tens of times slower; the CLI's short
spin (GOMP_SPINCOUNT=2000) or OMP_WAIT_POLICY=PASSIVE (both recorded per row) or one thread avoid it.
`bench_rasterizer(...)` returns the rows; `format_table(rows)` formats them.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import time

import numpy as np
import torch

from ragsplat.bench import openmp_wait
from ragsplat.camera import Camera


def make_scene(n: int, size: int = 256, seed: int = 0, footprint: float = 1.0, dtype=torch.float32):
    """(means, quats, scales, opacities, colors, camera, background) of `n` Gaussians on a riverbed.

    `footprint` multiplies every Gaussian's in-plane size (2 = four times the overlap).
    """
    cam = Camera.look_at([0.0, -3.0 * math.tan(math.radians(20)), 3.0], [0.0, 0.0, 0.0], size, size, 60.0)
    # Ground footprint of the image: its corners cast onto z = 0, enlarged 10% (a model covers more
    # than one view).
    corners = np.array([[0, 0], [size, 0], [0, size], [size, size]], float)
    rays = cam.unproject(corners, np.ones(4)) - cam.camera_center
    ground = cam.camera_center + rays * (-cam.camera_center[2] / rays[:, 2:3])
    lo, hi = ground[:, :2].min(0), ground[:, :2].max(0)
    mid, half = (lo + hi) / 2, (hi - lo) / 2 * 1.1
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 2, generator=g, dtype=torch.float64) * 2 - 1
    xy = torch.as_tensor(mid) + u * torch.as_tensor(half)
    z = 0.05 * torch.sin(3 * xy[:, 0]) * torch.cos(2 * xy[:, 1]) + 0.01 * torch.randn(n, generator=g,
                                                                                       dtype=torch.float64)
    means = torch.cat([xy, z[:, None]], 1)
    spacing = math.sqrt(4 * half[0] * half[1] / n)
    sxy = footprint * spacing * (0.6 + 0.6 * torch.rand(n, 2, generator=g, dtype=torch.float64))
    scales = torch.cat([sxy, 0.1 * sxy.min(1, keepdim=True).values], 1)
    yaw = torch.rand(n, generator=g, dtype=torch.float64) * math.pi  # rotation about the bed normal
    tilt = 0.1 * torch.randn(n, 2, generator=g, dtype=torch.float64)
    quats = torch.stack([torch.cos(yaw / 2), tilt[:, 0], tilt[:, 1], torch.sin(yaw / 2)], 1)
    opacities = 0.5 + 0.5 * torch.rand(n, generator=g, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    tensors = [t.to(dtype) for t in (means, quats, scales, opacities, colors)]
    return (*tensors, cam, torch.tensor([0.0, 0.0, 0.0], dtype=dtype))


def time_one(backend: str, n: int, size: int, repeats: int, warmup: int = 2, seed: int = 0,
             device: str = "cpu", footprint: float = 1.0, threads: int | None = None) -> dict:
    """Median seconds of forward + backward of `rasterize` (projection included) in this process."""
    from ragsplat.rasterize import rasterize

    if threads:  # torch's and numba's pools; oversubscribed cores make 2 threads far slower than 1
        import numba

        torch.set_num_threads(threads)
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))

    *params, cam, bg = make_scene(n, size, seed, footprint)
    params = [p.to(device).requires_grad_(True) for p in params]
    means, quats, scales, opacities, colors = params
    bg = bg.to(device)
    weights = torch.rand(size, size, 3, generator=torch.Generator().manual_seed(seed + 1)).to(device)
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    rss_before = _rss_mb()
    times, fwd, cpu = [], [], []
    for it in range(warmup + repeats):
        sync()
        c0 = time.process_time()
        t0 = time.perf_counter()
        image, _, _, meta = rasterize(means, quats, scales, opacities, colors, cam, bg, backend=backend)
        sync()
        t1 = time.perf_counter()
        (image * weights).sum().backward()
        sync()
        t2 = time.perf_counter()
        c2 = time.process_time()
        for p in params:
            p.grad = None
        if it >= warmup:
            times.append(t2 - t0)
            fwd.append(t1 - t0)
            cpu.append(c2 - c0)
    name = "torch-cuda" if (backend, device) == ("torch", "cuda") else meta["backend"]
    row = {"backend": name, "n": n, "size": size, "footprint": footprint, "repeats": repeats,
           "median_s": statistics.median(times), "min_s": min(times),
           "forward_median_s": statistics.median(fwd),
           "cpu_median_s": statistics.median(cpu), "visible": int(meta["visible"].sum()),
           "mean_tiles_per_gaussian": float(meta["tiles_touched"].float().mean()),
           "rss_before_mb": rss_before, "peak_rss_mb": _rss_mb(), "threads": torch.get_num_threads(),
           "load_avg_1min": os.getloadavg()[0], **openmp_wait()}
    if device == "cuda":  # RSS says little about GPU memory
        row["peak_cuda_mb"] = torch.cuda.max_memory_allocated() / 2**20
    return row


# One (backend, N, ...) timed in a fresh interpreter, so its peak RSS is its own: kwargs of `time_one` in,
# the row as JSON out (last line of stdout).
_WORKER = ("import json, sys; from ragsplat.bench.raster import time_one; "
           "print(json.dumps(time_one(**json.loads(sys.argv[1]))))")
_ON_CUDA = {"torch-cuda": ("torch", "cuda"), "gsplat": ("gsplat", "cuda")}


def bench_rasterizer(sizes=(10_000, 40_000), size: int = 256, repeats: int = 7, backends=None,
                     footprints=(1.0,), threads=(0,)) -> list[dict]:
    """Runs every (backend, threads, footprint, N) in a fresh process and returns the rows. Backends are
    names of `available_backends()`; threads 0 = the libraries' default (one per core)."""
    backends = list(backends or available_backends())
    rows = []
    for name, nthreads, footprint, n in itertools.product(backends, threads, footprints, sizes):
        backend, device = _ON_CUDA.get(name, (name, "cpu"))
        kwargs = {"backend": backend, "n": n, "size": size, "repeats": repeats, "device": device,
                  "footprint": footprint, "threads": nthreads}
        done = subprocess.run([sys.executable, "-c", _WORKER, json.dumps(kwargs)], capture_output=True,
                              text=True, check=False)
        if done.returncode != 0:
            raise RuntimeError(f"benchmark of {name} at N={n} failed: {done.stderr.strip()[-500:]}")
        rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    return rows


def available_backends() -> list[str]:
    from ragsplat.rasterize import gsplat_available

    names = ["cpu", "torch"]
    if torch.cuda.is_available():
        names.append("torch-cuda")
        if gsplat_available():
            names.append("gsplat")
    return names


def format_table(rows: list[dict]) -> str:
    head = (f"{'backend':<10} {'thr':>3} {'N':>7} {'size':>5} {'footprint':>9} {'fwd+bwd s':>10} "
            f"{'fwd s':>7} {'CPU s':>6} {'peak RSS MB':>12} {'tiles/G':>8} {'load':>5}")
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r['backend']:<10} {r['threads']:>3} {r['n']:>7} {r['size']:>5} "
                     f"{r['footprint']:>9.1f} {r['median_s']:>10.3f} {r['forward_median_s']:>7.3f} "
                     f"{r['cpu_median_s']:>6.3f} {r['peak_rss_mb']:>12.0f} "
                     f"{r['mean_tiles_per_gaussian']:>8.2f} {r['load_avg_1min']:>5.1f}")
    return "\n".join(lines)


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux reports KiB
