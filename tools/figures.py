"""docs/benchmark.md's figures of a rendered dataset: one view with and without the water, and the
ground-truth height map with its waterline and evaluated region. `python -m tools.figures DATA docs/figures
[VIEW]`."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from ragsplat.dataset import layout
from ragsplat.outputs import atomic_path


def write_figures(data: Path, out: Path, view: str | None = None) -> list[Path]:
    """`OUT/<preset>_views.png` (view `view`, default the first 20-degree oblique: wet | dry) and
    `OUT/<preset>_ground_truth.png` (bed height relative to the water, waterline, evaluated region)."""
    from ragsplat.pages import pyplot

    plt = pyplot()

    data, out = Path(data), Path(out)
    tf = json.loads((data / layout.TRANSFORMS).read_text())
    scene = json.loads((data / layout.SCENE).read_text())
    name = scene["spec"]["preset"]
    frame = next(f for f in tf["frames"] if (f["name"] == view if view else f["kind"] == "oblique20"))
    pair = np.hstack([layout.read_png(data / frame["file_path"]),
                      layout.read_png(data / frame["dry_file_path"])])
    views = out / f"{name}_views.png"
    layout.write_png(views, pair)

    surface = layout.Surface.load(data / layout.GT_SURFACE)
    water = tf["water"] or {"level": 0.0}
    k = surface.heights.shape[0]
    ext = [surface.x0, surface.x0 + (k - 1) * surface.cell] * 2
    c = surface.x0 + np.arange(k) * surface.cell
    sx, sy = water.get("slope", (0.0, 0.0))
    above = surface.heights - (water["level"] + sx * c[None, :] + sy * c[:, None])  # [j (y), i (x)]
    fig, ax = plt.subplots(figsize=(6.4, 5.2), constrained_layout=True)
    im = ax.imshow(above, origin="lower", extent=ext, cmap="terrain")
    fig.colorbar(im, ax=ax, label="bed height above the water (m)")
    if (data / layout.GT_WATERLINE).is_file():
        for line in json.loads((data / layout.GT_WATERLINE).read_text())["geometry"]["coordinates"]:
            line = np.asarray(line)
            ax.plot(line[:, 0], line[:, 1], color="navy", lw=0.7)
    r = scene["eval_region"]
    ax.plot([r["xmin"], r["xmax"], r["xmax"], r["xmin"], r["xmin"]],
            [r["ymin"], r["ymin"], r["ymax"], r["ymax"], r["ymin"]], "r--", lw=1, label="evaluated region")
    ax.set_xlabel("x (m), along the flow")
    ax.set_ylabel("y (m)")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"{name}: ground truth, waterline (blue)")
    truth = out / f"{name}_ground_truth.png"
    with atomic_path(truth) as tmp:
        fig.savefig(tmp, dpi=80, format="png")
    plt.close(fig)
    return [views, truth]


if __name__ == "__main__":
    for path in write_figures(*sys.argv[1:4]):
        print(path)
