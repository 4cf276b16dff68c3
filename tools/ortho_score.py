"""`python -m tools.ortho_score DATA ORTHO.tif [...]`: each orthophoto against the dataset's orthographic
truth over the wet cells (`ragsplat.eval.ortho`): PSNR, SSIM, the shift by phase correlation (cells and cm)
and the share of the wet cells it draws, one Markdown table row each."""

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
    print("| orthophoto | PSNR (dB) | SSIM | shift east, north (cells) | shift (cm) | wet cells drawn |")
    print("| --- | --- | --- | --- | --- | --- |")
    for path in map(Path, args[1:]):
        s = score_orthophoto(path, root)
        dx, dy = s["shift_cells"]
        print(f"| {path} | {s['psnr']:.2f} | {s['ssim']:.3f} | {dx:+.2f}, {dy:+.2f} | "
              f"{100 * step * (dx * dx + dy * dy) ** 0.5:.1f} | {100 * s['drawn']:.1f} % |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
