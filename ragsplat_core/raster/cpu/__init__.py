"""The "cpu" backend's numba kernels, twins of `reference/` and of `gaussians` (see `raster/__init__.py`)."""
