"""A run's checkpoint on disk: written atomically, read back only for the same dataset and settings."""

from __future__ import annotations

import pickle
from dataclasses import fields
from pathlib import Path

import torch

from ragsplat.errors import OutputError
from ragsplat.outputs import atomic_path
from ragsplat.train.config import RUN_ONLY, TrainConfig

CHECKPOINT = "ckpt.pt"


def write_checkpoint(path: Path, data: dict) -> Path:
    with atomic_path(path) as tmp:  # a kill never leaves a half-written checkpoint
        torch.save(data, tmp)
    return path


def read_checkpoint(path: Path, cfg: TrainConfig, fingerprint: str | None, root) -> tuple[dict, int | None]:
    """(the checkpoint's data, the iteration count it was written for when `cfg` extends it, else None).
    Refused: an unreadable file, another dataset's, or other settings than `cfg`'s (more iterations
    excepted)."""
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, KeyError, EOFError, ValueError, pickle.UnpicklingError) as err:  # truncated, junk
        raise OutputError(f"{path}: not a readable checkpoint ({type(err).__name__}); move it away to "
                          "start over") from None
    theirs = data.get("dataset_fingerprint")
    if theirs is not None and fingerprint is not None and theirs != fingerprint:
        raise OutputError(f"{path}: checkpoint of another dataset (fingerprint {theirs}, {root} "
                          f"is {fingerprint}); use another output directory")
    saved = TrainConfig.from_dict(data["config"])
    diff = [f.name for f in fields(TrainConfig)
            if f.name not in RUN_ONLY and getattr(saved, f.name) != getattr(cfg, f.name)]
    # More iterations extend a run (the schedule stretches to the new count from here on, so the result
    # is not that of a fresh run of that length); anything else would mix two configurations.
    if diff == ["iterations"] and cfg.iterations >= int(data["step"]):
        return data, saved.iterations
    if diff:
        raise OutputError(f"{path}: checkpoint was written with different settings ({', '.join(diff)}); "
                          "use another output directory or the same settings")
    return data, None
