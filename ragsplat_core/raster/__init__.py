"""Parts of the Gaussian rasterizer; the public entry is `ragsplat_core.rasterize.rasterize`."""
