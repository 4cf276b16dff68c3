"""`python -m tools.ortho_score DATA ORTHO.tif [...]`: each orthophoto against the dataset's orthographic
truth over the wet cells (`ragsplat.eval.ortho`): PSNR, SSIM, the shift (cells and cm), the blocks' local
shifts and the share of the wet cells it draws, one Markdown table row each."""

from __future__ import annotations

import sys
from pathlib import Path

from ragsplat.eval.ortho import read_truth, score_orthophoto


def main(argv: list[str] | None = None) -> int:
    """`python -m tools.ortho_score DATA ORTHO.tif [...]`: one row per orthophoto."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) < 2:
        print(main.__doc__, file=sys.stderr)
        return 2
    root = Path(args[0])
    step = read_truth(root)[1]
    print("| orthophoto | PSNR (dB) | colours matched | SSIM | shift east, north (cells) | shift (cm) | "
          "local shift, median / p90 (cm) | wet cells drawn |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for path in map(Path, args[1:]):
        s = score_orthophoto(path, root)
        dx, dy = s["shift_cells"]
        local = s["local_shift_cells"]
        blocks = "n/a" if local["median"] is None else \
            f"{100 * step * local['median']:.1f} / {100 * step * local['p90']:.1f} ({local['blocks']} blocks)"
        shift = 100 * step * (dx * dx + dy * dy) ** 0.5
        print(f"| {path} | {s['psnr']:.2f} | {s['psnr_matched']:.2f} | {s['ssim']:.3f} | {dx:+.2f}, "
              f"{dy:+.2f} | {shift:.1f} | {blocks} | {100 * s['drawn']:.1f} % |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
