"""The survey's geometry from first principles: the similarity fit (exact without noise, robust to wrong
positions), the projection through the water (the pinhole at n = 1 and above the water, the per-camera RA-GS
transform below it, the principal point at nadir), its Jacobians against finite differences, and the bundle
adjustment recovering tilted cameras from observations made through the water where a pinhole adjustment
leaves the bed too shallow. The positions CSV and the EXIF focal length as a drone writes them."""

import math

import numpy as np
import pytest
import torch

from ragsplat.camera import Camera
from ragsplat.dataset import layout, photos
from ragsplat.errors import DatasetError
from ragsplat.refraction import apparent_points
from ragsplat.survey import bundle, georef
from ragsplat.water_surface import WaterSurface

WATER = WaterSurface(0.0, 1.33)


def rotation(axis, angle):
    return torch.linalg.matrix_exp(bundle.skew(torch.tensor([axis], dtype=torch.float64) * angle))[0].numpy()


def test_similarity_is_exact_without_noise_and_ignores_wrong_positions():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(30, 3)) * [20, 20, 2]
    true = georef.Similarity(3.7, rotation([0.3, -0.5, 0.8], 0.9), np.array([4.5e5, 5.2e6, 230.0]))
    fit = georef.fit_similarity(src, true.apply(src))
    assert fit.scale == pytest.approx(true.scale, rel=1e-12) and np.allclose(fit.R, true.R, atol=1e-12)
    dst = true.apply(src) + rng.normal(size=src.shape) * 0.02
    dst[[3, 17]] += [5.0, -3.0, 1.0]  # two positions recorded wrong
    sim, inliers = georef.ransac_similarity(src, dst, threshold=0.2)
    assert not inliers[[3, 17]].any() and inliers.sum() == 28
    assert np.abs(sim.apply(src) - true.apply(src)).max() < 0.05
    with pytest.raises(ValueError, match="at least 3"):
        georef.ransac_similarity(src[:2], dst[:2], 0.2)


def cameras(tilts=(0, 25), size=(400, 300)):
    out = []
    for x in np.linspace(-12, 12, 4):
        for y in np.linspace(-8, 8, 3):
            for tilt in tilts:
                eye = np.array([x, y, 30.0])
                out.append(Camera.look_at(eye, eye + [0, 30 * math.tan(math.radians(tilt)), -30], *size,
                                          70.0))
    return out


def stack(cams):
    R = torch.tensor(np.stack([c.R for c in cams]))
    C = torch.tensor(np.stack([c.camera_center for c in cams]))
    K = torch.tensor([[c.fx, c.fy, c.cx, c.cy] for c in cams], dtype=torch.float64)
    return R, C, K


def test_the_tilt_heights_leave_open_is_their_plane_fit_s_spread():
    """`georef.tilt_allowed`: k standard deviations of the steepest slope of the plane fitted to heights of
    the given accuracy, against the spread of 4 000 fits to noisy heights (within 5 %); a tenth of the
    noise allows a tenth of the tilt; cameras on a line leave it open."""
    rng = np.random.default_rng(0)
    xy = np.column_stack([np.tile(np.linspace(-40, 40, 9), 2), np.repeat([-12.0, 12.0], 9)])  # two lines
    sigma = np.full(18, 3.0)
    A = np.column_stack([xy, np.ones(18)])
    fits = np.linalg.lstsq(A, rng.normal(size=(18, 4000)) * 3.0, rcond=None)[0][:2]  # [2, 4000] slopes
    steepest = np.sqrt(np.linalg.eigvalsh(np.cov(fits))[-1])
    assert georef.tilt_allowed(xy, sigma, k=1.0) == pytest.approx(steepest, rel=0.05)
    assert georef.tilt_allowed(xy, sigma / 10) == pytest.approx(georef.tilt_allowed(xy, sigma) / 10)
    assert georef.tilt_allowed(xy[:9], sigma[:9]) == math.inf


def test_projection_is_the_pinhole_above_the_water_and_the_ra_gs_transform_below():
    cams = cameras()
    R, C, K = stack(cams)
    pts = torch.tensor(np.random.default_rng(1).uniform([-10, -8, -3], [10, 8, 1], size=(50, 3)))
    for i, cam in enumerate(cams):
        n = len(pts)
        idx = torch.full((n,), i)
        got = bundle.project(R[idx], C[idx], K[idx], pts, WATER).numpy()
        want = cam.project(apparent_points(pts, torch.tensor(cam.camera_center), WATER).numpy())[0]
        np.testing.assert_allclose(got, want, atol=1e-9)  # the same physics by another code path
        plain = bundle.project(R[idx], C[idx], K[idx], pts, None).numpy()
        np.testing.assert_allclose(plain, cam.project(pts.numpy())[0], atol=1e-9)
        dry = pts[:, 2] >= 0
        np.testing.assert_allclose(got[dry], plain[dry], atol=1e-12)
        one = bundle.project(R[idx], C[idx], K[idx], pts, WaterSurface(0.0, 1.0)).numpy()
        np.testing.assert_allclose(one, plain, atol=1e-12)  # n = 1 is the pinhole
    nadir = cams[0]  # straight down: a point below the centre is seen at the principal point, at any depth
    below = torch.tensor([[*nadir.camera_center[:2], -2.5]])
    uv = bundle.project(R[:1], C[:1], K[:1], below, WATER)[0].numpy()
    np.testing.assert_allclose(uv, [nadir.cx, nadir.cy], atol=1e-9)


def scene(seed=0, points=1500, noise_px=0.3, water=WATER):
    """Cameras at 30 m over a channel 3 m deep between dry banks (falling with `water` where it slopes);
    exact observations through the water."""
    rng = np.random.default_rng(seed)
    cams = cameras()
    xy = rng.uniform([-20, -14], [20, 14], size=(points, 2))
    pts = np.column_stack([xy, 0.8 - 3.0 * np.exp(-(xy[:, 1] / 8) ** 2) + water.height(xy)])
    obs = []
    for i, c in enumerate(cams):
        uv, depth = c.project(apparent_points(torch.tensor(pts), torch.tensor(c.camera_center),
                                              water).numpy())
        seen = (depth > 0) & (uv[:, 0] > 0) & (uv[:, 0] < c.width) & (uv[:, 1] > 0) & (uv[:, 1] < c.height)
        obs += [(p, i, *uv[p]) for p in np.nonzero(seen)[0]]
    obs = np.array(obs)
    keep = np.bincount(obs[:, 0].astype(int), minlength=points) >= 2
    remap = np.cumsum(keep) - 1
    obs = obs[keep[obs[:, 0].astype(int)]]
    point = torch.tensor(remap[obs[:, 0].astype(int)])
    pixels = torch.tensor(obs[:, 2:]) + torch.tensor(rng.normal(0, noise_px, (len(obs), 2)))
    return cams, torch.tensor(pts[keep]), point, torch.tensor(obs[:, 1].astype(np.int64)), pixels


def rotation_error_deg(Ra, Rb):
    M = Ra @ Rb.mT
    return torch.rad2deg(torch.arccos(((M.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)))


def test_jacobians_match_finite_differences():
    cams, pts, point, image, _ = scene(points=200, noise_px=0.0)
    R, C, K = stack(cams)
    m = slice(0, 400)
    turn = torch.zeros(400, 3, dtype=torch.float64, requires_grad=True)
    Cm, X = C[image[m]].clone().requires_grad_(True), pts[point[m]].clone().requires_grad_(True)
    uv = bundle.project(R[image[m]] @ (torch.eye(3, dtype=torch.float64) + bundle.skew(turn)), Cm,
                        K[image[m]], X, WATER)
    grads = torch.autograd.grad(uv[:, 0].sum(), (turn, Cm, X))
    h = 1e-6
    for which, (g, base) in enumerate(zip(grads, (torch.zeros(400, 3, dtype=torch.float64), C[image[m]],
                                                   pts[point[m]]))):
        for j in range(3):
            e = torch.zeros_like(base)
            e[:, j] = h
            args = [torch.zeros(400, 3, dtype=torch.float64), C[image[m]], pts[point[m]]]
            lo, hi = list(args), list(args)
            lo[which], hi[which] = base - e, base + e
            f = [bundle.project(R[image[m]] @ torch.linalg.matrix_exp(bundle.skew(a[0])), a[1], K[image[m]],
                                a[2], WATER)[:, 0] for a in (lo, hi)]
            np.testing.assert_allclose(g[:, j].numpy(), ((f[1] - f[0]) / (2 * h)).numpy(), rtol=1e-5,
                                       atol=1e-4)


def started(points: int, water=WATER):
    """`scene`'s survey, its cameras as tensors, and where an adjustment starts: the cameras turned by a
    degree (structure from motion's tilts) and moved 5 cm, the points 20 cm off, RTK positions 2 / 3 cm
    off."""
    cams, pts, point, image, pixels = scene(points=points, water=water)
    R, C, K = stack(cams)
    rng = np.random.default_rng(3)
    R0 = bundle._rotate(R, torch.tensor(rng.normal(0, math.radians(1.0), (len(cams), 3))))
    C0 = C + torch.tensor(rng.normal(0, 0.05, C.shape))
    P0 = pts + torch.tensor(rng.normal(0, 0.2, pts.shape))
    rtk = C + torch.tensor(rng.normal(size=C.shape) * [0.02, 0.02, 0.03])
    return cams, pts, point, image, pixels, R, C, K, R0, C0, P0, rtk


def test_adjustment_through_the_water_recovers_tilted_cameras_and_the_bed():
    _cams, pts, point, image, pixels, R, C, K, R0, C0, P0, rtk = started(700)
    wet = pts[:, 2] < 0
    got = bundle.adjust(R0, C0, K, P0, point, image, pixels, WATER, prior_C=rtk)
    assert got.residuals.pow(2).mean().sqrt() < 0.5  # at the noise: 0.3 px per axis
    assert rotation_error_deg(got.R, R).median() < 0.1 and (got.C - C).norm(dim=1).median() < 0.03
    assert (got.points[wet, 2] - pts[wet, 2]).abs().median() < 0.05
    # a pinhole adjustment explains the same pixels with the bed at its apparent depth, far too shallow
    pin = bundle.adjust(R0, C0, K, P0, point, image, pixels, None, prior_C=rtk)
    assert (pin.points[wet, 2] - pts[wet, 2]).median() > 0.1
    # a camera without a position (NaN) is adjusted without a prior
    rtk[0] = float("nan")
    assert (rotation_error_deg(bundle.adjust(R0, C0, K, P0, point, image, pixels, WATER, prior_C=rtk).R,
                               R).median() < 0.1)


def test_the_sparse_camera_system_in_chunks_is_the_dense_one(monkeypatch):
    """The reduced system gathered a few observation pairs at a time and solved sparse on the CPU (a river
    survey's path) gives the dense path's adjustment to round-off, the free level's sigmas included; its
    camera pairs are those that share a point."""
    cams, pts, point, image, pixels, _R, _C, K, R0, C0, P0, rtk = started(300)
    run = lambda sparse: bundle.adjust(R0, C0, K, P0, point, image, pixels, WaterSurface(0.2, 1.33),
                                       prior_C=rtk, free=("level",), iterations=8, sparse=sparse)
    dense = run(False)
    monkeypatch.setattr(bundle, "PAIR_CHUNK", 97)  # many chunks, a point's pairs never split
    couples = bundle._Couples(point, image, len(pts), len(cams))
    assert len(couples.chunks) > 10
    seen = {(int(a), int(b)) for p in range(len(pts)) for a in image[point == p] for b in image[point == p]}
    assert {tuple(x) for x in couples.pairs.tolist()} == seen | {(i, i) for i in range(len(cams))}
    chunked = run(True)
    assert chunked.iterations == dense.iterations
    for a, b in ((chunked.R, dense.R), (chunked.C, dense.C), (chunked.points, dense.points)):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-9)
    assert chunked.water.level == pytest.approx(dense.water.level, abs=1e-8)  # round-off, via its differences
    for name in ("level",):
        assert chunked.sigma[name] == pytest.approx(dense.sigma[name], rel=1e-8)
        assert chunked.sigma_given_cameras[name] == pytest.approx(dense.sigma_given_cameras[name], rel=1e-8)


def test_the_adjustment_finds_an_unmeasured_water_surface():
    """The level (and a plane's slope) left free: from 30 cm above or below, the adjustment through the
    water comes to the true surface within its own reported uncertainty, which is a few centimetres for
    0.3 px of noise from 30 m."""
    _cams, pts, point, image, pixels, _R, _C, K, R0, C0, P0, rtk = started(700)
    wet = pts[:, 2] < 0
    for start in (0.3, -0.3):
        got = bundle.adjust(R0, C0, K, P0, point, image, pixels, WaterSurface(start, 1.33), prior_C=rtk,
                            free=("level",))
        assert 0.01 < got.sigma["level"] < 0.1 and abs(got.water.level) < 3 * got.sigma["level"]
        assert got.water.slope == (0.0, 0.0) and (got.points[wet, 2] - pts[wet, 2]).abs().median() < 0.05
    both = bundle.adjust(R0, C0, K, P0, point, image, pixels, WaterSurface(0.3, 1.33), prior_C=rtk,
                         free=("level", "slope"))
    assert set(both.sigma) == {"level", "slope_x", "slope_y"}
    for name, value in zip(("slope_x", "slope_y"), both.water.slope):
        assert abs(value) < 3 * both.sigma[name] < 0.03
    fixed = bundle.adjust(R0, C0, K, P0, point, image, pixels, WATER, prior_C=rtk)
    assert fixed.water is WATER and fixed.sigma is None
    with pytest.raises(ValueError, match="free parameters are"):
        bundle.adjust(R0, C0, K, P0, point, image, pixels, WATER, prior_C=rtk, free=("n",))


@pytest.mark.parametrize("fall", [0.0, 0.02])
def test_a_rivers_fall_is_kept_where_it_stands_clear_of_level_and_of_the_frames_tilt(fall, monkeypatch):
    """In a frame the positions hold (RTK, 2 / 3 cm), the water's plane is tried with its slope free: a river
    falling 2 % keeps it, within its sigmas of the truth; flat water keeps the level alone. A fall within
    the tilt that the positions leave open, or steeper than water falls, is refused and recorded."""
    from ragsplat.survey.stages import water as stage

    truth = WaterSurface(0.0, 1.33, (-fall, 0.0))
    cams, _pts, point, image, pixels, _R, _C, K, R0, C0, P0, rtk = started(700, truth)
    adjusted = lambda free, level=0.3: bundle.adjust(R0, C0, K, P0, point, image, pixels,
                                                      WaterSurface(level, 1.33), prior_C=rtk, free=free)
    left_open = georef.tilt_allowed(rtk[:, :2].numpy(), np.full(len(cams), 0.03))
    assert left_open < 0.005
    estimated = {"relative_level": False}
    fit = stage._with_fall(adjusted, estimated, left_open)
    trial = estimated["fall"]
    assert trial["kept"] == (fall > 0) == (fit is not None) and trial["tilt_left_open"] == left_open
    if fall:
        assert estimated["free"] == ["level", "slope"] and fit.water.tilted
        for name, got, want in zip(("slope_x", "slope_y"), fit.water.slope, truth.slope):
            assert abs(got - want) < 3 * fit.sigma[name], (got, want, fit.sigma)
        assert "; the water falls 2." in stage._say_fall(trial)
        refused = {"relative_level": False}  # the positions' heights leave a 3 % tilt open
        assert stage._with_fall(adjusted, refused, 0.03) is None and not refused["fall"]["kept"]
        assert "leave the frame's tilt open to 3.00 %" in stage._say_fall(refused["fall"])
        monkeypatch.setattr(stage, "MAX_FALL", 0.01)  # water falling at most 1 %
        refused = {"relative_level": False}
        assert stage._with_fall(adjusted, refused, left_open) is None and not refused["fall"]["kept"]
        assert "steeper than water falls (1 %)" in stage._say_fall(refused["fall"])
    else:
        assert "free" not in estimated and trial["standard_deviations"] < stage.FALL_SIGNIFICANT
        assert stage._say_fall(trial) == ""


def test_positions_csv(tmp_path):
    path = tmp_path / "positions.csv"
    layout.write_positions(path, ["a.jpg", "b.jpg"], np.array([[451234.5678, 5212345.1, 231.42], [1, 2, 3]]))
    got = layout.read_positions(path)
    assert list(got) == ["a.jpg", "b.jpg"] and np.allclose(got["a.jpg"], [451234.5678, 5212345.1, 231.42])
    path.write_text("z, y, x, name\n3,2,1,c.jpg\n\n")  # any column order, spaces, a blank line
    assert np.allclose(layout.read_positions(path)["c.jpg"], [1, 2, 3])
    for text, message in (("name,x,y\na,1,2\n", "header name,x,y,z"),
                          ("name,x,y,z\na,1,2,q\n", "must be numbers"),
                          ("name,x,y,z\na,1,2,3\na,1,2,3\n", "appears twice"), ("name,x,y,z\n", "no rows"),
                          ("name,x,y,z\na,1,2\n", "3 values for the 4 columns")):
        path.write_text(text)
        with pytest.raises(DatasetError, match=message):
            layout.read_positions(path)


def test_jpeg_carries_its_focal_length_as_structure_from_motion_reads_it(tmp_path):
    import pycolmap

    image = (np.random.default_rng(0).random((120, 160, 3)) * 255).astype(np.uint8)
    photos.write_jpeg(tmp_path / "images" / "a.jpg", image, focal_px=137.25)
    pycolmap.extract_features(tmp_path / "db.db", tmp_path / "images", device=pycolmap.Device.cpu)
    with pycolmap.Database.open(tmp_path / "db.db") as db:
        (cam,) = db.read_all_cameras()
    assert cam.has_prior_focal_length and cam.params[0] == pytest.approx(137.25, abs=1e-3)


def test_levelling_turns_a_tilted_water_plane_level():
    """`georef.levelling`: every point of a tilted plane comes to its height above the origin, by a proper
    rotation about that point (lengths kept); a level surface is left where it is."""
    water = WaterSurface(0.3, 1.33, (0.2, -0.05))
    rng = np.random.default_rng(0)
    xy = rng.uniform(-20, 20, (50, 2))
    on = np.column_stack([xy, water.height(xy)])
    sim = georef.levelling(water)
    np.testing.assert_allclose(sim.apply(on)[:, 2], 0.3, atol=1e-12)
    np.testing.assert_allclose(sim.apply(np.array([[0.0, 0.0, 0.3]])), [[0.0, 0.0, 0.3]], atol=1e-12)
    np.testing.assert_allclose(sim.R @ sim.R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(sim.R) == pytest.approx(1.0) and sim.scale == 1.0
    np.testing.assert_allclose(np.linalg.norm(sim.apply(on[:1]) - sim.apply(on[1:]), axis=1),
                               np.linalg.norm(on[:1] - on[1:], axis=1), atol=1e-9)
    flat = georef.levelling(WaterSurface(0.3, 1.33))
    np.testing.assert_allclose(flat.apply(on), on, atol=1e-12)


def test_the_adjustment_estimates_a_lens_distortion_through_the_water():
    """Observations through a lens with barrel distortion (k1 -0.08, k2 0.02) and through the water: with
    the lens free the adjustment recovers k1 and k2 within a few of its sigmas and the bed as without
    distortion; held at none (a pinhole), the residuals stay well above the noise (the pinhole poses and
    points absorb part of it)."""
    cams, pts, point, image, _ = scene(points=700, noise_px=0.0)
    R, C, K = stack(cams)
    rng = np.random.default_rng(4)
    lens = (-0.08, 0.02)
    pixels = bundle.project(R[image], C[image], K[image], pts[point], WATER, lens)
    pixels = pixels + torch.tensor(rng.normal(0, 0.3, pixels.shape))
    R0 = bundle._rotate(R, torch.tensor(rng.normal(0, math.radians(1.0), (len(cams), 3))))
    C0 = C + torch.tensor(rng.normal(0, 0.05, C.shape))
    P0 = pts + torch.tensor(rng.normal(0, 0.2, pts.shape))
    rtk = C + torch.tensor(rng.normal(size=C.shape) * [0.02, 0.02, 0.03])
    wet = pts[:, 2] < 0
    got = bundle.adjust(R0, C0, K, P0, point, image, pixels, WATER, prior_C=rtk, free=("lens",))
    for k, name in enumerate(("k1", "k2")):
        assert abs(got.lens[k] - lens[k]) < max(4 * got.sigma[name], 1e-3), (got.lens, got.sigma)
    assert (got.residuals.pow(2).mean().sqrt() < 0.5
            and (got.points[wet, 2] - pts[wet, 2]).abs().median() < 0.05)
    pin = bundle.adjust(R0, C0, K, P0, point, image, pixels, WATER, prior_C=rtk)
    assert (pin.residuals.pow(2).mean().sqrt() > 1.5 * got.residuals.pow(2).mean().sqrt()
            and pin.lens == (0.0, 0.0))


def test_the_level_s_sigma_against_the_bed_is_the_full_covariance_s_and_the_spread_of_the_depths_offset():
    """The level's standard deviation relative to the submerged points' mean height (the depths' common
    offset), with loosely held heights (a barometer's 30 cm) and the lens free, so that cameras, points and
    level trade: equal to f^T N^-1 f from the full normal matrix of every unknown (its Jacobian by central
    differences of the residuals, nothing of the reduced system's), and the spread of that offset over
    noise draws, where the level's sigma with the cameras held is well below it."""
    cams, pts, point, image, exact = scene(points=300, noise_px=0.0)
    R, C, K = stack(cams)
    wet = pts[:, 2] < 0
    sig = torch.tensor([1.0, 1.0, 0.3], dtype=torch.float64)
    free = ("level", "lens")

    def draw(seed):
        rng = np.random.default_rng(seed)
        pixels = exact + torch.tensor(rng.normal(0, 0.3, exact.shape))
        prior = C + torch.tensor(rng.normal(size=C.shape)) * sig
        got = bundle.adjust(R, C, K, pts, point, image, pixels, WaterSurface(0.0, 1.33), prior_C=prior,
                            prior_sigma=tuple(sig.tolist()), free=free)
        return got, pixels, prior

    got, pixels, prior = draw(5)
    assert got.sigma_level_to_bed > 1.5 * got.sigma_given_cameras["level"]
    problem = bundle._Problem(C, K, len(pts), point, image, pixels, got.water, [0, 3, 4], prior, sig, None,
                              0.01, 1.0, 2.0, False)
    theta = torch.tensor([got.water.level, 0.0, 0.0, *got.lens], dtype=torch.float64)
    n_img, n_pts = len(C), len(pts)

    def residuals(x):  # every observation's and every prior's, at the adjusted state moved by x
        turn, move = x[: 3 * n_img].reshape(-1, 3), x[3 * n_img: 6 * n_img].reshape(-1, 3)
        P = got.points + x[6 * n_img: 6 * n_img + 3 * n_pts].reshape(-1, 3)
        th = theta.clone()
        th[[0, 3, 4]] += x[6 * n_img + 3 * n_pts:]
        Cx = got.C + move
        return torch.cat([problem.residual(bundle._rotate(got.R, turn), Cx, P, th).reshape(-1),
                          ((Cx - prior) / sig).reshape(-1)])

    size = 6 * n_img + 3 * n_pts + 3
    r0 = residuals(torch.zeros(size, dtype=torch.float64))
    steps = 1e-7 * torch.eye(size, dtype=torch.float64)
    J = torch.stack([(residuals(e) - residuals(-e)) / 2e-7 for e in steps], 1)
    m = 2 * len(point)
    scale = float((r0[:m] ** 2).sum()) / (m - size)
    f = torch.zeros(size, dtype=torch.float64)
    f[6 * n_img + 3 * n_pts] = 1.0  # the level
    below = torch.nonzero(got.water.depth(got.points) > 0)[:, 0]
    f[6 * n_img + 3 * below + 2] = -1.0 / len(below)  # less the submerged points' mean height
    dense = math.sqrt(float(f @ torch.linalg.solve(J.T @ J, f)) * scale)
    assert got.sigma_level_to_bed == pytest.approx(dense, rel=1e-3)
    # the offset's spread over noise draws (pixels and the heights' prior): the sigma against the bed, not
    # the level's with the cameras held
    errors, held = [], []
    for seed in range(10, 16):
        got = draw(seed)[0]
        errors.append(got.water.level - float(got.points[wet, 2].mean()) + float(pts[wet, 2].mean()))
        held.append(got.sigma_given_cameras["level"])
    spread = math.sqrt(np.mean(np.square(errors)))
    assert 0.6 < spread / dense < 1.6 and spread > 1.5 * max(held)
