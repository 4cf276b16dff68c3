"""`tools.track_bias.triangulate` from physics: tracks projected exactly through the water (and in air) by
three nadir cameras come back where they were, from a start 10 cm off; through the wrong surface (air) a
submerged track does not."""

import numpy as np
import torch

from ragsplat.camera import Camera
from ragsplat.refraction import apparent_points
from ragsplat.water_surface import WaterSurface
from tools.track_bias import triangulate


def test_tracks_projected_through_the_water_triangulate_back_to_where_they_were():
    water = WaterSurface(0.0, 1.33, (-0.003, 0.001))
    cams = [Camera.look_at([x, y, 30.0], [x, y, 0.0], 1200, 900, 81.0) for x, y in ((-8, 0), (0, 1), (8, -1))]
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-6, 6, 20), rng.uniform(-4, 4, 20), rng.uniform(-3, -0.2, 20)])
    track, camera, xy = [], [], []
    for k, p in enumerate(points):
        for j, c in enumerate(cams):
            seen = apparent_points(torch.tensor(p[None]), torch.tensor(c.camera_center), water).numpy()
            track.append(k), camera.append(j), xy.append(c.project(seen)[0][0])
    track, camera, xy = np.array(track), np.array(camera), np.array(xy)
    start = points + rng.normal(0, 0.1, points.shape)
    got = triangulate(start, track, camera, xy, cams, water)
    assert np.abs(got - points).max() < 1e-5  # 10 um: central differences, 8 steps
    in_air = triangulate(start, track, camera, xy, cams, None)
    assert np.abs(in_air[:, 2] - points[:, 2]).min() > 0.04  # seen raised: the check has teeth
    dry = points + [0.0, 0.0, 3.5]  # above the surface: the air's pinhole
    xy_dry = np.array([cams[j].project(dry[k][None])[0][0] for k, j in zip(track, camera)])
    assert np.abs(triangulate(dry + 0.1, track, camera, xy_dry, cams, None) - dry).max() < 1e-5


def test_matches_read_photo_files_as_they_read_arrays(tmp_path):
    """A twin's photos go in as its files (the renderer's PNG, the survey's JPEG) and come out matched as the
    same pixels given as arrays."""
    import cv2
    from scipy import ndimage

    from tools.track_bias import matches

    rng = np.random.default_rng(3)
    tex = ndimage.gaussian_filter(rng.random((260, 400)), 2.0)
    tex = (255 * (tex - tex.min()) / np.ptp(tex)).astype(np.uint8)
    images = [tex[:240, :360], tex[12:252, 30:390]]  # the second 30 px right and 12 px down
    files = []
    for k, img in enumerate(images):
        files.append(tmp_path / f"photo{k}.png")
        cv2.imwrite(str(files[-1]), img)
    cams = [Camera.look_at([0.0, 0.0, 30.0], [0.0, 0.0, 0.0], 360, 240, 60.0)] * 2
    from_arrays = matches(tmp_path / "arrays", cams, images)
    from_files = matches(tmp_path / "files", cams, files)
    assert len(from_arrays[0]) > 100
    for a, b in zip(from_arrays, from_files):
        np.testing.assert_array_equal(a, b)
    shift = from_arrays[2][1::2] - from_arrays[2][0::2]  # the second view's keypoint less the first's
    assert np.abs(np.median(shift, 0) - [-30.0, -12.0]).max() < 0.1
