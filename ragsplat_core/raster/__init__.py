"""Parts of the Gaussian rasterizers; the public entries are `ragsplat.rasterize.rasterize` (3D
Gaussians, 3DGS) and `ragsplat.rasterize_surfels.rasterize_surfels` (2D surfels, 2DGS).

    backends.py             the table: which function each backend runs at each stage, and `choose_backend`
    reference/              plain PyTorch, autograd, any device: the semantics, and the twin of every kernel
        project.py              3DGS EWA projection, tile lists; the constants and types every backend reads
        composite.py            3DGS compositing
        surfel_project.py       surfel projection (every backend's)
        surfel_composite.py     surfel compositing
    cpu/                    numba kernels with hand-written backwards, CPU tensors (the "cpu" backend)
        project.py              3DGS projection, tile lists
        composite.py            3DGS compositing
        surfel_composite.py     surfel compositing
        rotation.py, sh.py      covariances and surfel tangents, view colours (twins in `gaussians`)
    cuda/                   gsplat's CUDA kernels, optional (the "gsplat" backend)
        render.py               3DGS: gsplat's fused rasterization
        surfel_composite.py     surfel compositing by gsplat's 2DGS stage

Grouped by implementation, because that is what a change touches (a semantics change goes into
reference/ and then into each kernel folder, its tests comparing them), and what an install has or lacks
(numba for cpu/, gsplat and CUDA for cuda/); the same file name in two folders is the same stage, twins
of each other, 3DGS files bare and surfel files prefixed `surfel_` (as `rasterize` / `rasterize_surfels`).
"""
