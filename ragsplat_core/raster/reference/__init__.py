"""The reference rasterizer stages in plain PyTorch (the "torch" backend; see `raster/__init__.py`)."""
