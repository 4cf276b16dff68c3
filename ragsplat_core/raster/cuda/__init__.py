"""The "gsplat" backend: gsplat's CUDA kernels, imported when called (see `raster/__init__.py`)."""
