"""Measuring tools kept apart from the core: the refraction stability sweep, the solver, rasterizer and
training-step benchmarks, and the small synthetic scenes they and the tests render. The `ragsplat
stability` and `ragsplat bench` commands (in `ragsplat_core.cli`) print and save what these return."""
