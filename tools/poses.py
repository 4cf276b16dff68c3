"""`python -m tools.poses MODEL TRUTH [GEOREF.json]`: how far a survey's recovered poses are from the
synthetic truth (`ragsplat.eval.poses`), one line and per tilt band."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from ragsplat.eval.poses import pose_errors, summary


def main(argv: list[str] | None = None) -> int:
    """`python -m tools.poses MODEL TRUTH [GEOREF.json]`: the pose errors of a COLMAP model, one line, and
    per tilt band."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) not in (2, 3):
        print(main.__doc__, file=sys.stderr)
        return 2
    sim = json.loads(Path(args[2]).read_text()) if len(args) == 3 else None
    errors = pose_errors(Path(args[0]), Path(args[1]), sim)
    print(summary(errors))
    for band, row in errors["by_tilt"].items():
        print(f"  tilt {band} deg: {summary(row)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
