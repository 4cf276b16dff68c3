"""Operational scripts: what the maintainers run beside the `ragsplat` commands (a slim dataset copy for a
lent GPU, the tuning sweeps, the figures, the GPU check). Not installed (pyproject.toml's package list leaves
`tools` out); run from the repository root, `python -m tools.NAME ...` (`bash tools/gpu_check.sh` for the
shell one). A tool parses its arguments, calls the library and prints; anything another module imports lives
in the library instead."""

from ragsplat.threads import openmp_waits

openmp_waits()  # as the `ragsplat` command does, before any tool imports torch (tools run side by side)
