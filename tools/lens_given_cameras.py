"""Where a survey's lens estimate comes from: its structure from motion's tracks (RUN/sfm/sparse/0, the
photos' own pixels) adjusted through the true water with k1, k2 free, the cameras' centres held three ways:
at the truth, loosely (2 / 2 / 3 cm) around the truth, and loosely around the photos' geotags
(DATA/survey/positions.csv, their RTK noise). The rotations and the points are free in all three, and the
level is held at the truth or freed. Where the lens comes out right at the true centres and off at the
geotags, it is the geotags' errors that the lens and a dome in the frame take up, not the observations.

    python -m tools.lens_given_cameras RUN DATA   # e.g. runs/nadir-s7 data/small-nadir-s7
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np


def tracks(run: Path, cameras: dict):
    """The registered photos that the truth has, their true R [I, 3, 3], C [I, 3], K [I, 4], and their
    observations: point [M], image [M], pixels [M, 2] (COLMAP's, centres at i + 0.5)."""
    import pycolmap
    import torch

    rec = pycolmap.Reconstruction(str(run / "sfm" / "sparse" / "0"))
    ids = [i for i in rec.reg_image_ids() if Path(rec.images[i].name).stem in cameras]
    cams = [cameras[Path(rec.images[i].name).stem] for i in ids]
    R = np.array([np.asarray(c.w2c, float)[:3, :3] for c in cams])
    C = np.array([c.camera_center for c in cams])
    K = np.array([[c.fx, c.fy, c.cx, c.cy] for c in cams])
    pid, obs = {}, []
    for k, i in enumerate(ids):
        obs += [(pid.setdefault(p.point3D_id, len(pid)), k, *p.xy) for p in rec.images[i].points2D
                if p.has_point3D()]
    obs = np.array(obs)
    names = [Path(rec.images[i].name).stem for i in ids]
    as_t = (lambda a: torch.tensor(a, dtype=torch.float64))
    return names, as_t(R), as_t(C), as_t(K), torch.tensor(obs[:, 0].astype(int)), \
        torch.tensor(obs[:, 1].astype(int)), as_t(obs[:, 2:])


def pinhole_points(R, C, K, point, image, pixels) -> np.ndarray:
    """[P, 3] linear triangulation of every track, ignoring the water (the adjustment's start)."""
    R, C, K, point, image, pixels = (t.numpy() for t in (R, C, K, point, image, pixels))
    P = np.stack([np.array([[k[0], 0, k[2]], [0, k[1], k[3]], [0, 0, 1]]) @ np.c_[r, -r @ c]
                  for r, c, k in zip(R, C, K)])  # [I, 3, 4]
    out = np.zeros((point.max() + 1, 3))
    for p in range(len(out)):
        m = point == p
        Pm, uv = P[image[m]], pixels[m]
        A = np.concatenate([uv[:, :1] * Pm[:, 2] - Pm[:, 0], uv[:, 1:] * Pm[:, 2] - Pm[:, 1]])
        X = np.linalg.svd(A)[2][-1]
        out[p] = X[:3] / X[3]
    return out


def main() -> None:
    import torch

    from ragsplat.dataset.load import load_dataset
    from ragsplat.survey.bundle import adjust
    from ragsplat.water_surface import WaterSurface

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("data", type=Path)
    a = ap.parse_args()
    views = load_dataset(a.data, splits=("train",), load_dry=False)
    cameras = {Path(v.file_path).stem: v.camera for v in views.train}
    names, R, C, K, point, image, pixels = tracks(a.run, cameras)
    start = torch.tensor(pinhole_points(R, C, K, point, image, pixels))
    level = float(json.loads((a.data / "scene.json").read_text())["water"]["level"])
    with open(a.data / "survey" / "positions.csv") as f:
        tags = {Path(r["name"]).stem: [float(r[k]) for k in "xyz"] for r in csv.DictReader(f)}
    geotags = torch.tensor([tags[n] for n in names], dtype=torch.float64)
    print(f"{len(names)} photos, {len(start)} tracks; the geotags' error (RMS, cm): "
          f"{np.round(100 * (geotags - C).pow(2).mean(0).sqrt().numpy(), 2).tolist()}")
    rtk = (0.02, 0.02, 0.03)
    for centres, prior, sigma in (("true, held", C, (1e-5,) * 3), ("true, 2 / 2 / 3 cm", C, rtk),
                                  ("geotags, 2 / 2 / 3 cm", geotags, rtk)):
        for free in (("lens",), ("lens", "level")):
            b = adjust(R, C, K, start, point, image, pixels, WaterSurface(level, 1.33), prior_C=prior,
                       prior_sigma=sigma, free=free, iterations=40)
            print(f"centres {centres:22s} level {'free' if 'level' in free else 'held'}: k1 {b.lens[0]:+.4f} "
                  f"+- {b.sigma['k1']:.4f}, k2 {b.lens[1]:+.4f}, level error "
                  f"{100 * (float(b.water.level) - level):+.1f} cm, "
                  f"RMS {b.residuals.pow(2).mean().sqrt():.3f} px")


if __name__ == "__main__":
    main()
