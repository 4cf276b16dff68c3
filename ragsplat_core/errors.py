"""The errors ragsplat raises for problems that are the user's or the environment's, not bugs.

Library code raises these; only the command layer (`ragsplat.cli`) turns one into a single line on
stderr and exit code 2. Each message is one line that names the file, option or value at fault.
Errors about bad values are also `ValueError`s, so code that called the library before these classes
existed keeps catching them.
"""

from __future__ import annotations


class RagsplatError(Exception):
    """Base class: a one-line message for the user; nothing was deleted."""


class DatasetError(RagsplatError, ValueError):
    """A missing, unreadable or inconsistent dataset file."""


class SpecError(RagsplatError, ValueError):
    """A scene spec that cannot produce a bathymetric dataset."""


class ConfigError(RagsplatError, ValueError):
    """A training or evaluation setting that cannot be used (unknown variant or preset, bad value)."""


class OutputError(RagsplatError):
    """An output location that cannot be used: not writable, or holding results made with other inputs."""


class TrainingDiverged(RagsplatError):
    """A non-finite loss, gradient or parameter; the message names the iteration and the parameter."""
