"""The command layer, the top of the import graph: the `ragsplat` entry point (`main`) and every subcommand,
one module each (`dataset`, `train`, `render`, `score` (a run or any bed file), `ablation`,
`export`, `survey`, `stability`, `bench`); `main.COMMANDS` names only modules of this package.

A command module defines `add_arguments(parser)` and `run(args) -> int`: it parses the arguments, calls
library functions (of `ragsplat`, `ragsplat.datagen` or `ragsplat.eval`), prints and sets the exit code;
`main` turns every `RagsplatError` into one line on stderr and exit code 2. The helpers beside the commands
(`args`: argument types; `progress`: bars and deferred interrupts; `cluster`: the Dask client) are for them
alone.

The arrows point one way (tests/test_layout.py checks them): of the core, only this package imports
`ragsplat.eval` and `ragsplat.datagen`, and nothing outside it imports it (the tests excepted). Defaults
that a command shares with the library or with another command live in the library (`train.config`,
`train.defaults`, `ragsplat.eval.ablation`), so a library function and its command agree without an import
up.
Operational scripts that are not `ragsplat` commands (dataset copies, tuning sweeps, the GPU check) are in
`tools/` at the repository root, not installed.
"""
