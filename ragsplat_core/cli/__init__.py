"""The command layer: the `ragsplat` entry point (`main`) and the commands that live in the core.

Commands import the library, never the reverse. A command module defines `add_arguments(parser)` and
`run(args) -> int`; `main` turns every `RagsplatError` into one line on stderr and exit code 2.
"""
