"""Where a survey's lens estimate comes from: its structure from motion's tracks (RUN/sfm/sparse/0, the
photos' own pixels) adjusted through the true water with k1, k2 free, the cameras' centres held three
ways: at the truth, loosely around the truth, and loosely around the photos' geotags
(DATA/survey/positions.csv), loosely meaning the geotags' RTK sigma as survey.json records it. The
rotations and the points are free in all three, and the level is held at the truth or freed. Where the
lens comes out right at the true centres and off at the geotags, it is the geotags' errors that the lens
and a dome in the frame take up, not the observations.

    python -m tools.lens_given_cameras RUN DATA   # e.g. runs/nadir-s7 data/small-nadir-s7
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def tracks(run: Path, cameras: dict):
    """The registered photos that the truth has, their true R [I, 3, 3], C [I, 3], K [I, 4] and projection
    matrices [I, 3, 4], and their observations: point [M], image [M], pixels [M, 2] (COLMAP's, centres at
    i + 0.5)."""
    import pycolmap
    import torch

    rec = pycolmap.Reconstruction(str(run / "sfm" / "sparse" / "0"))
    ids = [i for i in rec.reg_image_ids() if Path(rec.images[i].name).stem in cameras]
    cams = [cameras[Path(rec.images[i].name).stem] for i in ids]
    R = np.array([np.asarray(c.w2c, float)[:3, :3] for c in cams])
    C = np.array([c.camera_center for c in cams])
    K = np.array([[c.fx, c.fy, c.cx, c.cy] for c in cams])
    P = np.stack([c.K @ np.asarray(c.w2c, float)[:3] for c in cams])
    pid, obs = {}, []
    for k, i in enumerate(ids):
        obs += [(pid.setdefault(p.point3D_id, len(pid)), k, *p.xy) for p in rec.images[i].points2D
                if p.has_point3D()]
    obs = np.array(obs)
    names = [Path(rec.images[i].name).stem for i in ids]
    as_t = (lambda a: torch.tensor(a, dtype=torch.float64))
    return names, as_t(R), as_t(C), as_t(K), P, torch.tensor(obs[:, 0].astype(int)), \
        torch.tensor(obs[:, 1].astype(int)), as_t(obs[:, 2:])


def pinhole_points(P: np.ndarray, point, image, pixels) -> np.ndarray:
    """[N, 3] linear triangulation of every track by the cameras' projections P [I, 3, 4], ignoring the
    water (the adjustment's start)."""
    point, image, pixels = (t.numpy() for t in (point, image, pixels))
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

    from ragsplat.dataset import layout
    from ragsplat.dataset.load import load_dataset
    from ragsplat.survey.bundle import adjust

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("data", type=Path)
    a = ap.parse_args()
    views = load_dataset(a.data, splits=("train",), load_dry=False)
    cameras = {Path(v.file_path).stem: v.camera for v in views.train}
    names, R, C, K, P, point, image, pixels = tracks(a.run, cameras)
    start = torch.tensor(pinhole_points(P, point, image, pixels))
    water = views.water
    level = float(water.level)
    positions = layout.read_positions(a.data / layout.SURVEY_POSITIONS)
    tags = {Path(name).stem: xyz for name, xyz in positions.items()}
    geotags = torch.tensor(np.array([tags[n] for n in names]), dtype=torch.float64)
    record = json.loads((a.data / layout.SURVEY_RECORD).read_text())
    rtk = tuple(record["geo"][layout.SURVEY_IMAGES]["rtk_std_m"])
    print(f"{len(names)} photos, {len(start)} tracks; the geotags' error (RMS, cm): "
          f"{np.round(100 * (geotags - C).pow(2).mean(0).sqrt().numpy(), 2).tolist()}")
    loose = " / ".join(f"{100 * v:g}" for v in rtk) + " cm"
    for centres, prior, sigma in (("true, held", C, (1e-5,) * 3), (f"true, {loose}", C, rtk),
                                  (f"geotags, {loose}", geotags, rtk)):
        for free in (("lens",), ("lens", "level")):
            b = adjust(R, C, K, start, point, image, pixels, water, prior_C=prior,
                       prior_sigma=sigma, free=free, iterations=40)
            print(f"centres {centres:22s} level {'free' if 'level' in free else 'held'}: k1 {b.lens[0]:+.4f} "
                  f"+- {b.sigma['k1']:.4f}, k2 {b.lens[1]:+.4f}, level error "
                  f"{100 * (float(b.water.level) - level):+.1f} cm, "
                  f"RMS {b.residuals.pow(2).mean().sqrt():.3f} px")


if __name__ == "__main__":
    main()
