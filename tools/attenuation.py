"""What the water does to the bed's light in a dataset's photos, and where a finished run put it:
`python -m tools.attenuation DATA [RUN ...]`.

The photos: for each nadir training view, every submerged pixel of the dry photo is paired with where the
wet photo shows its bed point through the flat water (the refraction transform), and, per 20 cm depth bin
and channel, the wet linear radiance is regressed on the dry one. The slope is the bed's transmission (the
intercept holds the veil and the sky's reflection); its log falls with depth by c (L / d + k), c the
scene's extinction, so that rate over c is the metres of path per metre of depth the photos hold, the
view's and the daylight's (`TrainConfig.downwelling` k is the second).

A run: its c against the scene's, and the trend with depth of its opaque submerged Gaussians' degree-0
colours (`train.albedo.albedo_trend`) counted by opacity and by their share of the images
(`train.albedo.image_shares` over the training views, as the trainer counts them), with
the c each would give if moved into it (c - b / (1 + k)).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

from ragsplat.dataset import load_dataset
from ragsplat.dataset.layout import NO_HIT, read_depth
from ragsplat.gaussians import SH_C0
from ragsplat.refraction import apparent_points, srgb_to_linear
from ragsplat.runs import load_model
from ragsplat.surface import ExtractConfig
from ragsplat.train.albedo import albedo_trend, image_shares

BIN = 0.2  # metres of depth


def photos(root: Path) -> np.ndarray:
    """[3] the log transmission's fall per metre of depth, per channel, in the nadir training photos."""
    ds = load_dataset(root, splits=("train",))
    pairs = []
    for view in ds.train:
        if view.kind != "nadir":
            continue
        cam = view.camera
        wet, dry = (srgb_to_linear(img.double() / 255).numpy() for img in (view.rgb, view.dry_rgb))
        z = read_depth(root / view.gt_depth_file_path).astype(np.float64).reshape(-1)  # [H W]
        u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
        points = cam.unproject(np.stack([u.reshape(-1), v.reshape(-1)], -1), z)  # [H W, 3] world
        wet_px = (z < NO_HIT) & (points[:, 2] < ds.water.level - 0.05)
        seen = apparent_points(torch.from_numpy(points[wet_px]), torch.from_numpy(cam.camera_center),
                               ds.water).numpy()
        col, row = np.floor(cam.project(seen)[0]).astype(int).T  # the pixel that shows it
        inside = (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        pairs.append(np.column_stack([ds.water.level - points[wet_px, 2][inside],
                                      dry.reshape(-1, 3)[wet_px][inside], wet[row[inside], col[inside]]]))
    d, dry, wet = np.split(np.concatenate(pairs), [1, 4], axis=1)
    d = d[:, 0]
    centres, slopes = [], []
    for lo in np.arange(0.0, d.max(), BIN):
        m = (d >= lo) & (d < lo + BIN)
        if m.sum() >= 2000:
            centres.append(lo + BIN / 2)
            slopes.append([np.polyfit(dry[m, c], wet[m, c], 1)[0] for c in range(3)])
    slopes = np.array(slopes)
    return np.array([-np.polyfit(centres, np.log(slopes[:, c]), 1)[0] for c in range(3)])


def run_trends(run: Path, root: Path) -> dict:
    model, ds = load_model(run, root, splits=("train",))
    views = ds.split("train")
    centers = [torch.tensor(v.camera.camera_center, dtype=torch.float32) for v in views]
    seen = image_shares(model.splats, [v.camera for v in views], centers, model.water, model.flags,
                        model.cfg.surfels, model.backend, depth=model.cfg.surfel_depth)
    with torch.no_grad():
        depth = model.water.depth(model.splats["means"])
        opacity = torch.sigmoid(model.splats["opacities"])
        wet = (depth > 0) & (opacity >= ExtractConfig.min_opacity)
        lin = srgb_to_linear(SH_C0 * model.splats["sh0"][:, 0] + 0.5)  # as the trainer fits them
        k = 1 + model.cfg.downwelling
        c = model.attenuation
        out = {"c": c.tolist()}
        for name, weight in (("opacity", opacity), ("share of the images", seen)):
            b, _ = albedo_trend(lin[wet], depth[wet], weight[wet])
            out[name] = {"trend": b.tolist(), "c_moved": (c - b / k).tolist()}
        share = seen[wet].sort(descending=True).values / seen[wet].sum()  # of the opaque submerged ones
        least = seen[wet] <= seen[wet].median()
        b, _ = albedo_trend(lin[wet][least], depth[wet][least], opacity[wet][least])
        out["concentration"] = {"top_1%": float(share[: max(1, len(share) // 100)].sum()),
                                "least_seen_half": float(share[len(share) // 2:].sum()),
                                "least_seen_half_trend": b.tolist()}
    return out


def main(argv: list[str]) -> None:
    root = Path(argv[0])
    ext = np.array(json.loads((root / "scene.json").read_text())["conditions"]["extinction_per_m"])
    rate = photos(root)
    print(f"{root}: extinction {np.round(ext, 3).tolist()} 1/m; the photos' transmission falls by "
          f"{np.round(rate, 3).tolist()} per m of depth: {np.round(rate / ext, 2).tolist()} m of path per m")
    for run in map(Path, argv[1:]):
        r = run_trends(run, root)
        print(f"{run}: c / scene {np.round(np.array(r['c']) / ext, 2).tolist()}")
        for name in ("opacity", "share of the images"):
            print(f"  colours' trend counted by {name}: {np.round(r[name]['trend'], 3).tolist()} /m; "
                  f"moved into c: {np.round(np.array(r[name]['c_moved']) / ext, 2).tolist()} of the scene's")
        h = r["concentration"]
        print(f"  the most seen 1 % of the opaque submerged Gaussians make {h['top_1%']:.0%} of their share, "
              f"the least seen half {h['least_seen_half']:.0%}; that half's trend by opacity "
              f"{np.round(h['least_seen_half_trend'], 3).tolist()} /m")


if __name__ == "__main__":
    main(sys.argv[1:])
