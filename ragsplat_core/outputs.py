"""What every file ragsplat writes shares: atomic writes, the provenance stamp, the marker that says
an output directory is ragsplat's, and the key a kept product was made with.

Every result is written to a temporary sibling and renamed into place, so a killed run never leaves a
half-written file that looks finished. numpy only (no torch): the dataset generator uses it too.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import platform
import subprocess
from collections.abc import Iterator
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from ragsplat.errors import OutputError

ROOT = Path(__file__).resolve().parent.parent  # the source tree (for the git commit)
# The source folders and the packages they install as (pyproject.toml's package-dir): in a checkout each
# package is its folder, in a wheel ragsplat/ holds the other three.
SOURCE_PACKAGES = {"ragsplat_core": "ragsplat", "eval": "ragsplat.eval", "datagen": "ragsplat.datagen",
                   "blender_scenes": "ragsplat.blender_scenes"}


def temp_path(path: Path) -> Path:
    """A sibling name for writing `path` before an atomic rename (same folder: same file system)."""
    path = Path(path)
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yields a temporary path to write; on success it is renamed to `path` (parents are created), on an
    exception it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as err:
        if err.filename != str(tmp):
            raise
        # a full disk or a lost permission names the file the user asked for, not our temporary
        raise OSError(err.errno, err.strerror, str(path)) from err
    finally:
        tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def locked(path: str | Path) -> Iterator[None]:
    """Holds an exclusive lock on the file `path` (created with its parents) for the block: another process
    asking for it waits until this one leaves, so a product that several processes need is made once."""
    import fcntl

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_json(path: str | Path, obj, indent: int = 2) -> None:
    write_bytes(path, (json.dumps(obj, indent=indent) + "\n").encode())


def _package(name: str) -> str | None:
    try:
        return version(name)
    except PackageNotFoundError:
        return None


def git_commit() -> str | None:
    """HEAD of the source tree, or None outside a git checkout."""
    try:
        done = subprocess.run(["git", "rev-parse", "HEAD"], check=False, cwd=ROOT, capture_output=True,
                              text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() or None


def _package_dir(folder: str) -> Path:
    """Where the package of a source folder is imported from (the folder itself in a checkout)."""
    import importlib.util

    return Path(importlib.util.find_spec(SOURCE_PACKAGES[folder]).submodule_search_locations[0])


def source_digest(*dirs: str) -> str:
    """sha256 (16 hex digits) over the Python sources under the given folders or files of the source tree
    ("ragsplat_core", "eval/evaluate.py"): the code version of a result, also outside git and with uncommitted
    edits. Each file counts under its source-tree path, read where its package is installed, so a checkout
    and a wheel of the same sources agree (a folder's digest leaves out the packages a wheel nests in it)."""
    h = hashlib.sha256()
    for d in dirs:
        folder, _, rest = d.partition("/")
        base = _package_dir(folder)
        target = base / rest
        if target.is_file():
            files = [target]
        else:
            nested = [n for n in map(_package_dir, SOURCE_PACKAGES) if base in n.parents]
            files = sorted(p for p in target.rglob("*.py") if not any(n in p.parents for n in nested))
        for path in files:
            name = f"{folder}/{path.relative_to(base).as_posix()}"
            h.update(name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def versions(*packages: str) -> dict:
    """The provenance stamp: Python, platform, ragsplat, numpy, git commit, plus each named package's
    installed version (None when it is not installed)."""
    import numpy as np

    stamp = {"python": platform.python_version(), "platform": platform.platform(),
             "ragsplat": _package("ragsplat"), "numpy": np.__version__, "git_commit": git_commit()}
    stamp.update({name: _package(name) for name in packages})
    return stamp


def claim(out: Path, kind: str, legacy: tuple[str, ...] = ()) -> None:
    """Make `out` a directory of ragsplat's `kind` ("train run", "ablation"), or check that it is one:
    refuses a directory holding files that ragsplat did not write (nothing is overwritten). `legacy`: glob
    patterns of files that mark an output written before the marker existed."""
    out = Path(out)
    marker = out / ".ragsplat"
    if marker.is_file():
        try:
            found = json.loads(marker.read_text()).get("kind")
        except (OSError, ValueError):
            found = None
        if found != kind:
            raise OutputError(f"{out} holds a ragsplat {found or 'output'}, not a {kind}; choose another "
                              "--out")
        return
    if out.is_dir() and any(out.iterdir()) and not any(any(out.glob(g)) for g in legacy):
        raise OutputError(f"{out} is not empty and was not written by ragsplat; choose an empty or new --out")
    write_json(marker, {"kind": kind})


# ---------------------------------------------------------------- what a kept product was made with
# One scheme for every cache: the survey's stages (RUN/stages.json), each tile's model and bed, each
# ablation row, a COLMAP import. A key is the product's inputs as JSON holds them: settings as they are,
# files by their content (`dataset.layout.file_digest`, a dataset's `fingerprint`, the code's
# `source_digest`), a product made from another by that one's key or its `digest`. It is written once the
# product is whole, so a kill leaves no key that looks finished, and the product is kept only while its key
# compares equal as JSON reads it back (tuples come back as lists).


def jsonable(x):
    """JSON's own types: non-finite floats -> None (strict JSON), numpy scalars -> Python numbers, tuples
    -> lists, paths -> strings."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, Path):
        return str(x)
    if hasattr(x, "item") and getattr(x, "ndim", None) == 0:  # a numpy scalar (numpy is not imported here)
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def digest(*parts) -> str:
    """16 hex digits of sha256 over `parts` as JSON (what JSON cannot hold, as its text): a key short enough
    to name a product by."""
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


def changed(old, key) -> list[str]:
    """What differs between the key a product was made with (`old`; None: none recorded) and `key`: the names
    of the inputs that changed where both are dicts, else ["key"]; [] when they are the same."""
    key = jsonable(key)
    if old == key:
        return []
    if isinstance(old, dict) and isinstance(key, dict):
        return sorted(k for k in set(old) | set(key) if old.get(k) != key.get(k))
    return ["key"]


class Stamp:
    """The file beside a product that holds the key it was made with."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    def read(self):
        """The recorded key; None when there is none or it cannot be read (the product is made again)."""
        try:
            return json.loads(self.path.read_text())
        except (OSError, ValueError):
            return None

    def holds(self, key) -> bool:
        return not changed(self.read(), key)

    def write(self, key) -> None:
        write_json(self.path, jsonable(key), indent=1)
