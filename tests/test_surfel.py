"""2D Gaussian surfel rasterizer (2DGS): the torch twin against geometry and a literal per-pixel 2DGS loop,
the cpu kernels against the twin (outputs and the gradient of every output), gsplat against the twin."""

import math

import numpy as np
import pytest
import torch

from ragsplat.camera import Camera
from ragsplat.errors import ConfigError
from ragsplat.gaussians import quat_to_rotmat, surfel_tangents
from ragsplat.rasterize import gsplat_available
from ragsplat.rasterize_surfels import depth_normals, rasterize_surfels
from ragsplat.refraction import apparent_jacobian, apparent_points
from ragsplat.water_surface import WaterSurface

NADIR_R = np.diag([1.0, -1.0, -1.0])  # looks down world -z; camera x = world x, camera y = world -y
BACKENDS = ["torch", "cpu"]
OUTPUTS = ["image", "alpha", "depth", "normals", "median_depth", "distortion"]
CHANNELS = [3, 1, 1, 3, 1, 1]


def nadir(width=40, height=30, fov=60.0, height_m=2.0):
    return Camera.from_fov(width, height, fov, NADIR_R, -NADIR_R @ np.array([0.0, 0.0, height_m]))


def render(params, cam, bg, backend, tangents=None, depth="ray"):
    """rasterize_surfels -> ({output name: tensor}, meta); params: means, quats, scales, opacities, colors."""
    image, alpha, depth, meta = rasterize_surfels(*params, cam, bg, tangents=tangents, backend=backend,
                                                  depth=depth)
    outs = {"image": image, "alpha": alpha, "depth": depth}
    outs.update({k: meta[k] for k in OUTPUTS[3:]})
    return outs, meta


def oblique_scene(n=150, seed=0):
    """Surfels of random orientation (many oblique, some nearly edge-on) and size (sub-pixel to a few tiles)
    on a 70 x 50 image (5 x 4 tiles, partial edge tiles), opacities up to 1 (the 0.99 clamp), stacks that
    saturate (the early stop)."""
    cam = Camera.look_at([0.3, -0.8, 2.0], [0.0, 0.0, 0.0], 70, 50, 60.0)
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([2.0, 1.6, 0.6],
                                                                                      dtype=torch.float64)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.exp(torch.empty(n, 2, dtype=torch.float64).uniform_(-4.5, -1.8, generator=g))
    opacities = torch.rand(n, generator=g, dtype=torch.float64)
    opacities[: n // 10] = 1.0
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    return cam, [means, quats, scales, opacities, colors], None


def refracted_scene(n=150, seed=1):
    """A bed of surfels 0.4-0.6 m under water seen obliquely, passed as RA-GS does: apparent centres and
    tangents t' = J t (J = apparent_jacobian), not orthogonal and not of equal length."""
    cam = Camera.look_at([0.9, -1.1, 1.6], [0.0, 0.0, -0.5], 70, 50, 60.0)
    centre = torch.tensor(cam.camera_center, dtype=torch.float64)
    water = WaterSurface(0.0, 1.33)
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5) * 1.6
    z = -0.5 + 0.1 * torch.sin(3 * xy[:, :1]) + 0.02 * torch.randn(n, 1, generator=g, dtype=torch.float64)
    true = torch.cat([xy, z], 1)
    tilt = torch.cat([torch.ones(n, 1, dtype=torch.float64), 0.2 * torch.randn(n, 3, generator=g,
                                                                                 dtype=torch.float64)], 1)
    scales = torch.exp(torch.empty(n, 2, dtype=torch.float64).uniform_(-4.0, -2.5, generator=g))
    tangents = apparent_jacobian(true, centre, water) @ surfel_tangents(tilt, scales)  # [N, 3, 2]
    opacities = 0.3 + 0.7 * torch.rand(n, generator=g, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    return cam, [apparent_points(true, centre, water), None, None, opacities, colors], tangents


SCENES = {"oblique": oblique_scene, "refracted": refracted_scene}


def grads_per_output(backend, cam, params, tangents, dtype, device="cpu", depth="ray"):
    """Outputs and, for each output, the gradients of sum(output * weights) with respect to every input
    (means, quats and scales or tangents, opacities, colors, background) and means2d; on the CPU."""
    params = [None if p is None else p.to(device, dtype).clone().requires_grad_(True) for p in params]
    tangents = None if tangents is None else tangents.to(device, dtype).clone().requires_grad_(True)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=dtype, device=device, requires_grad=True)
    outs, meta = render(params, cam, bg, backend, tangents, depth)
    geometry = params[1:3] if tangents is None else [tangents]
    inputs = [params[0], *geometry, *params[3:], bg]  # means, then quats and scales or tangents, ...
    g = torch.Generator().manual_seed(7)
    grads = {}
    for name, ch in zip(OUTPUTS, CHANNELS):
        w = torch.rand(cam.height, cam.width, ch, generator=g, dtype=torch.float64).to(device, dtype)
        grads[name] = [None if d is None else d.cpu() for d in torch.autograd.grad(
            (outs[name] * w).sum(), inputs + [meta["means2d"]], retain_graph=True, allow_unused=True)]
    return {k: v.detach().cpu() for k, v in outs.items()}, grads, meta


def assert_close_scaled(got, want, rel, name, floor=0.0):
    """Max abs difference within rel x the largest reference magnitude (or `floor` if larger); None (an
    input an output does not depend on) on both sides or none, or zeros where the reference has None
    (gsplat's backward returns a zero gradient for the background of the alpha)."""
    if want is None:
        assert got is None or not got.any(), name
        return
    assert got is not None, name
    err = float((got.double() - want.double()).abs().max())
    scale = max(float(want.abs().max()), floor)
    assert err <= rel * max(scale, 1e-12), f"{name}: max error {err:.3g} vs scale {scale:.3g}"


def assert_gradients_close(grads, ref_grads, rel, outputs=OUTPUTS, inputs=None):
    """Every d output / d input within rel of its largest reference magnitude, or of 1% of the largest
    gradient of that input over all outputs when it is smaller: some are exactly 0 (a depth does not
    change with the surfel's scales), where float32 leaves round-off of the other terms' size."""
    for i in range(len(ref_grads["image"])) if inputs is None else inputs:
        floor = 0.01 * max(float(g[i].abs().max()) for g in ref_grads.values() if g[i] is not None)
        for name in outputs:
            assert_close_scaled(grads[name][i], ref_grads[name][i], rel, f"d {name} / d input {i}", floor)


@pytest.mark.parametrize("depth", ["ray", "centre"])
@pytest.mark.parametrize("scene", SCENES)
def test_cpu_matches_torch_outputs_and_every_gradient(scene, depth):
    # float64 inputs: both backends project alike, so this compares the float32 kernels with the twin.
    cam, params, tangents = SCENES[scene]()
    f64 = torch.float64
    ref_out, ref_grads, ref_meta = grads_per_output("torch", cam, params, tangents, f64, "cpu", depth)
    out, grads, meta = grads_per_output("cpu", cam, params, tangents, f64, "cpu", depth)
    for name in OUTPUTS:
        assert_close_scaled(out[name], ref_out[name], 5e-5, name)
    assert_gradients_close(grads, ref_grads, 2e-4)
    for i in range(len(ref_grads["image"])):  # every input gets a gradient from the image
        assert float(ref_grads["image"][i].abs().max()) > 0, i
    # the geometry gets one from each (a median depth at the centres moves with the means alone)
    for name in ("depth", "normals", "median_depth", "distortion"):
        inputs = (0,) if depth == "centre" and name == "median_depth" else (0, 1, -1)
        assert all(float(ref_grads[name][i].abs().max()) > 0 for i in inputs), name
    # integers from float64 boxes of the same projection (tangents: numba vs torch, ~1e-16 apart): the nearest
    # box edge is 2e-4 px from a pixel boundary here (measured), far beyond round-off
    assert torch.equal(meta["radii"], ref_meta["radii"])
    assert torch.equal(meta["tiles_touched"], ref_meta["tiles_touched"])
    alpha = ref_out["alpha"]
    assert float(alpha.min()) < 0.5 and float(alpha.max()) > 0.99  # gaps and saturated pixels
    assert float(ref_out["distortion"].max()) > 0 and (ref_out["median_depth"] > 0).any()


def test_cpu_float32_end_to_end():
    # float32 all the way (projection too): oblique surfels amplify the projection's rounding a little.
    cam, params, tangents = oblique_scene(n=100, seed=3)
    ref_out, ref_grads, _ = grads_per_output("torch", cam, params, tangents, torch.float64)
    out, grads, _ = grads_per_output("cpu", cam, params, tangents, torch.float32)
    for name in OUTPUTS:
        assert out[name].dtype == torch.float32
        assert_close_scaled(out[name], ref_out[name], 1e-4, name)
        assert all(g is None or g.dtype == torch.float32 for g in grads[name])
    assert_gradients_close(grads, ref_grads, 2e-3)


def literal_2dgs(means, tangents, opacities, colors, cam, bg):
    """2DGS per pixel, from the geometry: each pixel's ray meets each surfel's plane (a 3 x 3 solve), over
    all surfels by centre depth (no tiles, no boxes), float64 numpy; distortion as the explicit pair sum
    2 sum_{j<i} w_i w_j (z_i - z_j)."""
    R, t = cam.R, cam.t
    means, tangents = means.detach().numpy(), tangents.detach().numpy()
    o, c = opacities.detach().numpy(), colors.detach().numpy()
    pc = means @ R.T + t
    ab = np.einsum("ij,njk->nik", R, tangents)  # [N, 3, 2] camera frame
    normals = np.cross(tangents[:, :, 0], tangents[:, :, 1])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals *= np.where(np.sum(normals * (cam.camera_center - means), 1) < 0, -1.0, 1.0)[:, None]
    uv_c = cam.project(means)[0]
    jj, ii = np.mgrid[0:cam.height, 0:cam.width]
    pix = np.stack([ii.ravel() + 0.5, jj.ravel() + 0.5], -1)  # [P, 2]
    rays = np.stack([(pix[:, 0] - cam.cx) / cam.fx, (pix[:, 1] - cam.cy) / cam.fy, np.ones(len(pix))], -1)
    order = [k for k in np.argsort(pc[:, 2], kind="stable") if pc[k, 2] >= 0.01 and o[k] >= 1 / 255]
    alpha, depth = np.zeros((len(order), len(pix))), np.zeros((len(order), len(pix)))
    for row, k in enumerate(order):
        a, b = (np.broadcast_to(ab[k, :, i], rays.shape) for i in (0, 1))
        A = np.stack([a, b, -rays], -1)  # [P, 3, 3]: p + u a + v b = z r
        u, v, z = np.linalg.solve(A, np.broadcast_to(-pc[k], rays.shape)[..., None])[..., 0].T
        rho3, rho2 = u * u + v * v, 2 * np.sum((pix - uv_c[k]) ** 2, 1)
        rho = np.minimum(rho3, rho2)
        g = o[k] * np.exp(-rho / 2)
        alpha[row] = np.where(g >= 1 / 255, np.minimum(0.99, g), 0)
        depth[row] = np.where(rho3 <= rho2, z, pc[k, 2])
    out = {name: np.zeros((len(pix), ch)) for name, ch in zip(OUTPUTS, CHANNELS)}
    for q in range(len(pix)):
        T, ws, zs = 1.0, [], []
        for row, k in enumerate(order):
            a = alpha[row, q]
            if a == 0:
                continue
            if T * (1 - a) < 1e-4:
                break
            w, zq = a * T, depth[row, q]
            out["image"][q] += w * c[k]
            out["normals"][q] += w * normals[k]
            if T > 0.5 >= T * (1 - a):
                out["median_depth"][q] = zq
            ws.append(w)
            zs.append(zq)
            T *= 1 - a
        ws, zs = np.array(ws), np.array(zs)
        out["image"][q] += T * np.asarray(bg)
        out["alpha"][q] = 1 - T
        out["depth"][q] = (ws @ zs) / (1 - T) if T < 1 else 0.0
        out["distortion"][q] = 2 * np.sum(np.tril(np.outer(ws, ws) * (zs[:, None] - zs[None, :]), -1))
    return {k: v.reshape(cam.height, cam.width, -1) for k, v in out.items()}


@pytest.mark.parametrize("backend", BACKENDS)
def test_matches_the_literal_2dgs_loop(backend):
    cam = nadir(40, 30)
    g = torch.Generator().manual_seed(4)
    n = 40
    means = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([0.9, 0.7, 0.5],
                                                                                      dtype=torch.float64)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = 0.01 + 0.09 * torch.rand(n, 2, generator=g, dtype=torch.float64)
    opacities = 0.05 + 0.95 * torch.rand(n, generator=g, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    bg = [0.2, 0.5, 0.9]
    want = literal_2dgs(means, surfel_tangents(quats, scales), opacities, colors, cam, bg)
    outs, _ = render([means, quats, scales, opacities, colors], cam, bg, backend)
    tol = 1e-9 if backend == "torch" else 3e-5  # cpu composites in float32
    for name in OUTPUTS:
        np.testing.assert_allclose(outs[name].numpy(), want[name], atol=tol * (100 if "depth" in name else 1),
                                   err_msg=name)
    assert (want["alpha"] > 0.5).any() and (want["alpha"] < 0.5).any() and (want["distortion"] > 0).any()


@pytest.mark.parametrize("backend", BACKENDS)
def test_surfel_facing_the_camera_renders_its_gaussian_footprint(backend):
    # A surfel in the ground plane under a nadir camera: at each pixel the ray meets the ground at X and
    # G = exp(-|S^-1 R^T (X - mu)|^2 / 2), the low-pass filter is exp(-d^2) around the projected centre.
    cam = nadir(48, 36)
    mean, scale, angle, opacity = np.array([0.13, -0.07, 0.0]), np.array([0.15, 0.08]), 0.4, 0.8
    color, bg = np.array([1.0, 0.5, 0.25]), np.array([0.1, 0.1, 0.1])
    jj, ii = np.mgrid[0:cam.height, 0:cam.width]
    ground = cam.unproject(np.stack([ii + 0.5, jj + 0.5], -1).reshape(-1, 2), np.full(ii.size, 2.0))
    rot = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    uv = (ground[:, :2] - mean[:2]) @ rot / scale
    centre = cam.project(mean[None])[0][0]
    filt = np.exp(-((ii + 0.5 - centre[0]) ** 2 + (jj + 0.5 - centre[1]) ** 2))
    g = opacity * np.maximum(np.exp(-0.5 * (uv ** 2).sum(1)).reshape(ii.shape), filt)
    a = np.where(g >= 1 / 255, np.minimum(g, 0.99), 0.0)

    quat = [[math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)]]  # about z: the surfel lies in the ground
    t = [torch.tensor(np.array(v), dtype=torch.float64) for v in ([mean], quat, [scale], [opacity], [color])]
    outs, meta = render(t, cam, torch.tensor(bg), backend)
    tol = 1e-9 if backend == "torch" else 1e-5
    np.testing.assert_allclose(outs["alpha"][..., 0].numpy(), a, atol=tol)
    want = a[..., None] * color + (1 - a[..., None]) * bg
    np.testing.assert_allclose(outs["image"].numpy(), want, atol=tol)
    np.testing.assert_allclose(outs["depth"][..., 0].numpy(), np.where(a > 0, 2.0, 0.0), atol=tol * 10)
    np.testing.assert_allclose(outs["median_depth"][..., 0].numpy(), np.where(a >= 0.5, 2.0, 0.0),
                               atol=tol * 10)
    np.testing.assert_allclose(outs["normals"].numpy(), a[..., None] * [0.0, 0.0, 1.0], atol=tol)  # faces up
    np.testing.assert_allclose(outs["distortion"].numpy(), 0.0, atol=tol)
    np.testing.assert_allclose(meta["means2d"].detach().numpy()[0], centre, atol=1e-9)
    assert (a > 0).sum() > 150 and (g > filt * opacity + 0.1).any()  # the surfel, not the filter, is drawn


@pytest.mark.parametrize("backend", BACKENDS)
def test_surfel_seen_edge_on_leaves_only_the_low_pass_filter(backend):
    # A surfel whose plane contains the viewing ray of its centre covers no area on screen: what remains is
    # the 2DGS low-pass filter, o exp(-d^2) around the projected centre (about 5 px across), at the centre's
    # depth. Its image line runs at 30 degrees, so no other pixel centre lies on it.
    cam = nadir(33, 27)
    centre_px = np.array([20.5, 11.5])  # a pixel centre
    mean = cam.unproject(centre_px[None], np.array([1.7]))[0]
    view = mean - cam.camera_center
    across = cam.R.T @ np.array([math.cos(math.pi / 6), math.sin(math.pi / 6), 0.0])  # image direction
    tangents = np.stack([0.2 * view / np.linalg.norm(view), 0.2 * across], -1)  # large: 0.2 m both ways
    opacity = 0.9
    t = [torch.tensor(np.array(v), dtype=torch.float64) for v in ([mean], [opacity], [[0.3, 0.6, 0.9]])]
    outs, meta = render([t[0], None, None, t[1], t[2]], cam, [0.0, 0.0, 0.0], backend,
                        tangents=torch.tensor(tangents[None]))
    jj, ii = np.mgrid[0:cam.height, 0:cam.width]
    g = opacity * np.exp(-((ii + 0.5 - centre_px[0]) ** 2 + (jj + 0.5 - centre_px[1]) ** 2))
    a = np.where(g >= 1 / 255, np.minimum(g, 0.99), 0.0)
    tol = 1e-9 if backend == "torch" else 1e-5
    np.testing.assert_allclose(outs["alpha"][..., 0].numpy(), a, atol=tol)
    np.testing.assert_allclose(outs["depth"][..., 0].numpy(), np.where(a > 0, 1.7, 0.0), atol=tol * 10)
    assert int((a > 0).sum()) == 21 and int(meta["radii"][0]) >= 10  # d^2 <= ln(255 o): 21 px of a long box


@pytest.mark.parametrize("backend", BACKENDS)
def test_tilted_plane_of_surfels_renders_the_plane_depth(backend):
    # Overlapping surfels all lying in the plane z = 0.3 x - 0.2 y + 0.1: every ray-splat intersection is
    # the ray's point on that plane, so depth and median depth are the plane's z-depth at every covered
    # pixel, the distortion vanishes and the normals are the plane's (turned to the camera), times alpha.
    cam = Camera.look_at([0.4, -1.2, 2.0], [0.0, 0.0, 0.0], 40, 30, 50.0)
    normal = np.array([-0.3, 0.2, 1.0]) / np.linalg.norm([-0.3, 0.2, 1.0])
    e1 = np.array([1.0, 0.0, 0.3]) / np.linalg.norm([1.0, 0.0, 0.3])
    e2 = np.cross(normal, e1)
    gx, gy = np.meshgrid(np.linspace(-1.5, 1.5, 31), np.linspace(-1.5, 1.5, 31))
    xy = np.stack([gx.ravel(), gy.ravel()], -1)
    means = np.column_stack([xy, 0.3 * xy[:, 0] - 0.2 * xy[:, 1] + 0.1])
    n = len(means)
    tangents = np.broadcast_to(np.stack([0.25 * e1, 0.2 * e2], -1), (n, 3, 2))
    t = [torch.tensor(np.ascontiguousarray(v), dtype=torch.float64) for v in (means, tangents)]
    params = [t[0], None, None, torch.full((n,), 0.9, dtype=torch.float64),
              torch.rand(n, 3, dtype=torch.float64)]
    outs, _ = render(params, cam, [0.0, 0.0, 0.0], backend, tangents=t[1])
    jj, ii = np.mgrid[0:cam.height, 0:cam.width]
    rays = np.stack([(ii + 0.5 - cam.cx) / cam.fx, (jj + 0.5 - cam.cy) / cam.fy, np.ones(ii.shape)], -1)
    dirs = rays @ cam.R  # world directions whose camera z is 1
    c = cam.camera_center
    depth = (normal @ (means[0] - c)) / (dirs @ normal)  # ray parameter = z-depth
    covered = outs["alpha"][..., 0].numpy() > 0.999
    assert covered.mean() > 0.9
    tol = 1e-9 if backend == "torch" else 2e-5
    np.testing.assert_allclose(outs["depth"][..., 0].numpy()[covered], depth[covered], rtol=tol)
    np.testing.assert_allclose(outs["median_depth"][..., 0].numpy()[covered], depth[covered], rtol=tol)
    np.testing.assert_allclose(outs["distortion"].numpy()[covered], 0.0, atol=tol * 10)
    facing = normal if normal @ (c - means[0]) > 0 else -normal
    np.testing.assert_allclose((outs["normals"] / outs["alpha"]).numpy()[covered], np.broadcast_to(
        facing, (int(covered.sum()), 3)), atol=tol * 10)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("o_front, o_back, median_is", [(0.6, 0.9, "front"), (0.3, 0.9, "back"),
                                                         (0.3, 0.1, "none")])
def test_two_layers_median_expected_depth_and_distortion(backend, o_front, o_back, median_is):
    # Two large surfels facing a nadir camera, 1.5 m and 1.8 m away, centred on the optical axis (the centre
    # of pixel (8, 8)): there G = 1, so alpha = o and the weights are o_f, (1 - o_f) o_b.
    cam = nadir(17, 17)
    means = torch.tensor([[0.0, 0.0, 0.5], [0.0, 0.0, 0.2]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2, dtype=torch.float64)
    scales = torch.full((2, 2), 0.3, dtype=torch.float64)
    opacities = torch.tensor([o_front, o_back], dtype=torch.float64)
    params = [means, quats, scales, opacities, torch.eye(3, dtype=torch.float64)[:2]]
    outs, _ = render(params, cam, [0.0, 0.0, 0.0], backend)
    z1, z2 = 1.5, 1.8
    w1, w2 = o_front, (1 - o_front) * o_back
    px = {k: float(v[8, 8, 0]) for k, v in outs.items()}
    tol = 1e-9 if backend == "torch" else 1e-5
    assert px["depth"] == pytest.approx((w1 * z1 + w2 * z2) / (w1 + w2), abs=tol)
    assert px["median_depth"] == pytest.approx({"front": z1, "back": z2, "none": 0.0}[median_is], abs=tol)
    assert px["distortion"] == pytest.approx(2 * w1 * w2 * (z2 - z1), abs=tol)  # sum_ij w_i w_j |z_i - z_j|


def test_torch_twin_gradients_match_finite_differences():
    cam = nadir(20, 16)
    g = torch.Generator().manual_seed(6)
    n = 6
    means = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([0.6, 0.5, 0.4],
                                                                                      dtype=torch.float64)
    tangents = 0.08 * torch.randn(n, 3, 2, generator=g, dtype=torch.float64)  # oblique, sheared
    opacities = 0.3 + 0.6 * torch.rand(n, generator=g, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64)
    weights = [torch.rand(16, 20, ch, generator=g, dtype=torch.float64) for ch in CHANNELS]

    def loss(means, tangents, opacities, colors, bg):
        outs, _ = render([means, None, None, opacities, colors], cam, bg, "torch", tangents)
        return sum((outs[name] * w).sum() for name, w in zip(OUTPUTS, weights))

    inputs = [x.clone().requires_grad_(True) for x in (means, tangents, opacities, colors, bg)]
    assert torch.autograd.gradcheck(loss, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


@pytest.mark.parametrize("backend", BACKENDS)
def test_tangents_replace_quats_and_scales(backend):
    cam, (means, quats, scales, opacities, colors), _ = oblique_scene(n=40, seed=5)
    a, _ = render([means, quats, scales, opacities, colors], cam, [0.1, 0.1, 0.1], backend)
    b, _ = render([means, None, None, opacities, colors], cam, [0.1, 0.1, 0.1], backend,
                  tangents=surfel_tangents(quats, scales))
    c, _ = render([means, 3.7 * quats, scales, opacities, colors], cam, [0.1, 0.1, 0.1], backend)
    for name in OUTPUTS:
        torch.testing.assert_close(a[name], b[name], atol=1e-6, rtol=0)
        torch.testing.assert_close(a[name], c[name], atol=1e-6, rtol=0)
    # The normal is the third rotation column, t_u x t_v.
    np.testing.assert_allclose(np.cross(*surfel_tangents(quats, torch.ones_like(scales)).unbind(-1)),
                               quat_to_rotmat(quats)[:, :, 2], atol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_culling(backend):
    # Centre behind the near plane; a surfel whose disk reaches the camera's plane (no bounded image);
    # opacity below 1/255; and one ordinary surfel.
    cam = nadir(height_m=2.0)
    means = torch.tensor([[0.0, 0.0, 1.995], [0.0, 0.0, 1.9], [0.0, 0.0, 0.0], [0.05, 0.0, 0.0]],
                         dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0], [math.cos(0.6), math.sin(0.6), 0.0, 0.0],
                          [1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    scales = torch.tensor([[0.05, 0.05], [0.05, 0.2], [0.05, 0.05], [0.05, 0.05]], dtype=torch.float64)
    opacities = torch.tensor([0.9, 0.9, 0.003, 0.9], dtype=torch.float64)
    outs, meta = render([means, quats, scales, opacities, torch.rand(4, 3, dtype=torch.float64)], cam,
                        [0.0, 0.0, 0.0], backend)
    assert meta["visible"].tolist() == [False, False, False, True]
    assert meta["radii"].tolist()[:3] == [0, 0, 0] and int(meta["radii"][3]) > 0
    assert float(outs["depth"].max()) == pytest.approx(2.0, abs=1e-5)


def test_means2d_gradient_for_densification():
    cam, params, _ = oblique_scene(n=60, seed=8)
    params = [p.clone().requires_grad_(True) for p in params]
    image, _, _, meta = rasterize_surfels(*params, cam, [0.0, 0.0, 0.0], backend="torch")
    image.sum().backward()
    grad = meta["means2d"].grad
    assert grad is not None and grad.shape == (60, 2)
    assert torch.all(grad[~meta["visible"]] == 0) and grad[meta["visible"]].abs().sum() > 0


def test_backend_choice_and_errors():
    cam, params, _ = oblique_scene(n=5, seed=9)
    assert rasterize_surfels(*params, cam, [0.0, 0.0, 0.0])[3]["backend"] == "cpu"  # auto on CPU tensors
    with pytest.raises(ValueError, match="unknown rasterizer backend"):
        rasterize_surfels(*params, cam, [0.0, 0.0, 0.0], backend="opengl")
    with pytest.raises(ConfigError, match="gsplat"):
        rasterize_surfels(*params, cam, [0.0, 0.0, 0.0], backend="gsplat")  # CPU tensors: never gsplat
    with pytest.raises(ValueError, match="scales must be a tensor of shape"):
        rasterize_surfels(params[0], params[1], params[2][:, :1].expand(5, 3), *params[3:], cam, [0.0] * 3)
    with pytest.raises(ValueError, match="tangents must be a tensor of shape"):
        rasterize_surfels(params[0], None, None, *params[3:], cam, [0.0] * 3, tangents=torch.zeros(5, 3, 3))


@pytest.mark.parametrize("backend", BACKENDS)
def test_no_surfels_renders_background(backend):
    cam = nadir(8, 8)
    empty = [torch.zeros((0, *shape), dtype=torch.float64) for shape in ((3,), (4,), (2,), (), (3,))]
    outs, _ = render(empty, cam, [0.5, 0.5, 0.5], backend)
    assert torch.all(outs["image"] == 0.5) and torch.all(outs["alpha"] == 0)
    for name in OUTPUTS[2:]:
        assert torch.all(outs[name] == 0), name


def test_ray_transforms_meet_the_pixel_rays_where_the_kernels_do():
    """gsplat's rasterization stage reads each surfel as T = K [a b p]: its per-pixel intersection (the
    kernel's formula, written out here) gives the (u, v) of the rays the torch and cpu kernels use, for
    oblique and refracted surfels; and the physics: a surfel facing a nadir camera at z metres, tangent
    length s, has u = dx z / (fx s) at dx pixels from its centre."""
    from ragsplat.raster.reference.surfel_project import project_surfels

    # gsplat 1.5 RasterizeToPixels2DGSFwd.cu: h_u = px T_2 - T_0, h_v = py T_2 - T_1
    def kernel_uv(T, px, py):
        h = torch.linalg.cross(px[..., None] * T[:, 2] - T[:, 0], py[..., None] * T[:, 2] - T[:, 1])
        return h[..., 0] / h[..., 2], h[..., 1] / h[..., 2]

    for scene in SCENES.values():
        cam, params, tangents = scene()
        if tangents is None:
            tangents = surfel_tangents(params[1], params[2])
        means, tangents = params[0].clone().requires_grad_(True), tangents.clone().requires_grad_(True)
        proj = project_surfels(means, tangents, params[3], cam, transforms=True)
        g = torch.Generator().manual_seed(3)
        px, py = (torch.rand(2, 500, len(tangents), generator=g, dtype=torch.float64) - 0.5) * 40
        px, py = px + proj.means2d[:, 0].detach(), py + proj.means2d[:, 1].detach()  # [500, N] around centres
        dx, dy = px - proj.means2d[:, 0], py - proj.means2d[:, 1]
        r = proj.rays
        q2 = r[:, 4] * dx + r[:, 5] * dy + r[:, 6]
        want = torch.stack([(r[:, 0] * dx + r[:, 1] * dy) / q2, (r[:, 2] * dx + r[:, 3] * dy) / q2])
        got = torch.stack(kernel_uv(proj.transforms, px, py))  # [2, 500, N]
        ok = proj.visible & (q2.abs() > 1e-3 * r[:, 6].abs())  # rays that meet the plane in front
        assert torch.allclose(got[:, ok], want[:, ok], rtol=1e-9,
                              atol=1e-9 * float(want[:, ok].detach().abs().max()))
        # and the same gradients: to the surfel, and to means2d (the translation of its image, at fixed rays)
        w = torch.rand(2, *ok.shape, generator=g, dtype=torch.float64) * ok
        inputs = (means, tangents, proj.means2d)
        for d_got, d_want in zip(torch.autograd.grad((torch.where(ok, got, 0) * w).sum(), inputs,
                                                     retain_graph=True),
                                 torch.autograd.grad((torch.where(ok, want, 0) * w).sum(), inputs)):
            assert torch.allclose(d_got, d_want, rtol=1e-7, atol=1e-9 * float(d_want.abs().max()))
    cam = nadir(40, 30, height_m=2.0)
    s, z = 0.05, 2.0 - 0.3  # a surfel at world z 0.3 under a camera at 2 m
    tangents = torch.tensor([[[s, 0.0], [0.0, s], [0.0, 0.0]]], dtype=torch.float64)
    proj = project_surfels(torch.tensor([[0.0, 0.0, 0.3]], dtype=torch.float64), tangents,
                           torch.tensor([0.5], dtype=torch.float64), cam, transforms=True)
    u, v = kernel_uv(proj.transforms, proj.means2d[:, 0] + 3.0, proj.means2d[:, 1])
    assert float(u) == pytest.approx(3.0 * z / (cam.fx * s), rel=1e-12) and abs(float(v)) < 1e-12


def clamped(params):
    """Opacities below 0.98: gsplat clamps alpha at 0.999, the twin at 0.99."""
    return [*params[:3], params[3].clamp(max=0.98), params[4]]


CUDA_GSPLAT = pytest.mark.skipif(not (torch.cuda.is_available() and gsplat_available()),
                                 reason="needs CUDA and gsplat")


@CUDA_GSPLAT
@pytest.mark.parametrize("scene", SCENES)
def test_gsplat_matches_torch_outputs_and_every_gradient(scene):
    # float64 projection on both sides; gsplat composites in float32 (with __expf) where the twin uses
    # float64: a pixel at the 1/255 cut can fall on either side, so the tolerance is a few 1e-3. Depth,
    # median depth and distortion are per-surfel centre z in gsplat (see the next test).
    cam, params, tangents = SCENES[scene]()
    params = clamped(params)
    ref_out, ref_grads, ref_meta = grads_per_output("torch", cam, params, tangents, torch.float64)
    out, grads, meta = grads_per_output("gsplat", cam, params, tangents, torch.float64, device="cuda")
    assert meta["backend"] == "gsplat"
    for name in ("image", "alpha", "normals"):
        assert_close_scaled(out[name], ref_out[name], 5e-3, name)
    assert_gradients_close(grads, ref_grads, 2e-2, outputs=("image", "alpha", "normals"))
    assert torch.equal(meta["radii"].cpu(), ref_meta["radii"])
    for i in range(len(ref_grads["image"])):
        assert float(grads["image"][i].abs().max()) > 0, i


@pytest.mark.parametrize("backend", BACKENDS)
def test_centre_depth_is_each_surfels_centre_z(backend):
    # One tilted surfel: with depth="ray" its depth map is the tilted plane's (it varies across the disk),
    # with depth="centre" the centre's camera z wherever it is drawn, as gsplat composites it; image and alpha
    # do not change, and the median depth and the distortion (0 for one surfel) follow the depth.
    cam = nadir(60, 60)
    quat = torch.tensor([[np.cos(0.3), np.sin(0.3), 0.0, 0.0]], dtype=torch.float64)  # 34 degrees about x
    params = [torch.tensor([[0.05, -0.02, 0.1]], dtype=torch.float64), quat,
              torch.tensor([[0.3, 0.2]], dtype=torch.float64), torch.tensor([0.9], dtype=torch.float64),
              torch.tensor([[0.5, 0.5, 0.5]], dtype=torch.float64)]
    ray, _ = render(params, cam, [0.0, 0.0, 0.0], backend)
    centre, meta = render(params, cam, [0.0, 0.0, 0.0], backend, depth="centre")
    drawn = ray["alpha"][..., 0] > 0.05
    assert int(drawn.sum()) > 200
    assert float(ray["depth"][..., 0][drawn].std()) > 0.05  # the tilted plane
    zc = float(meta["depths"][0])  # the centre's camera z: 2 m - 0.1 m
    assert abs(zc - 1.9) < 1e-9
    assert torch.allclose(centre["depth"][..., 0][drawn], torch.full_like(centre["depth"][..., 0][drawn], zc),
                          atol=1e-5)
    for name in ("image", "alpha", "normals"):
        assert torch.equal(centre[name], ray[name]), name
    median = centre["median_depth"][..., 0]
    assert torch.allclose(median[median > 0], torch.full_like(median[median > 0], zc), atol=1e-5)
    assert float(centre["distortion"].abs().max()) < 1e-6
    with pytest.raises(ValueError, match="depth must be one of"):
        render(params, cam, [0.0, 0.0, 0.0], backend, depth="mean")
    from ragsplat.errors import ConfigError
    from ragsplat.train.config import TrainConfig

    with pytest.raises(ConfigError, match="surfel_depth"):
        TrainConfig(surfel_depth="mean")


@CUDA_GSPLAT
def test_gsplat_depths_of_surfels_facing_the_camera():
    # Surfels parallel to a nadir camera's image plane: the ray-plane z is the centre's z at every pixel, so
    # gsplat's per-surfel depth is the twin's; gradients compared except to the quaternions (tilting a surfel
    # moves the twin's per-pixel z, not gsplat's centre z).
    cam = nadir(70, 50)
    g = torch.Generator().manual_seed(10)
    n = 200
    means = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([2.0, 1.4, 0.6])
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64).expand(n, 4)
    scales = torch.exp(torch.empty(n, 2, dtype=torch.float64).uniform_(-4.5, -2.0, generator=g))
    params = [means, quats, scales, 0.1 + 0.85 * torch.rand(n, generator=g, dtype=torch.float64),
              torch.rand(n, 3, generator=g, dtype=torch.float64)]
    ref_out, ref_grads, _ = grads_per_output("torch", cam, params, None, torch.float64)
    out, grads, _ = grads_per_output("gsplat", cam, params, None, torch.float64, device="cuda")
    for name in OUTPUTS:
        assert_close_scaled(out[name], ref_out[name], 5e-3, name)
    assert float(ref_out["distortion"].max()) > 0 and (ref_out["median_depth"] > 0).any()
    assert_gradients_close(grads, ref_grads, 2e-2, inputs=[0, 2, 3, 4, 5, 6])  # all but the quaternions


def test_benchmark_rows():
    from ragsplat.bench.surfel import format_table, time_pair

    row = time_pair("cpu", 300, 64, repeats=1, warmup=0)
    assert row["surfel-image_median_s"] > 0 and row["surfel-all_ratio"] > 0 and row["3dgs_median_s"] > 0
    assert "surfel+all" in format_table([row])


def test_depth_normals_of_a_tilted_plane():
    """The normal from depth of a plane z = 0.3 x - 2 seen obliquely is the plane's unit normal, turned
    towards the camera, away from the border."""
    cam = Camera.look_at([0.5, -1.0, 1.5], [0.0, 0.0, -2.0], 24, 20, 60.0)
    v, u = torch.meshgrid(torch.arange(20, dtype=torch.float64) + 0.5,
                          torch.arange(24, dtype=torch.float64) + 0.5, indexing="ij")
    # ray-plane intersection per pixel: world ray C + t d, with d from the unprojection at z-depth 1
    C = torch.as_tensor(cam.camera_center)
    d = cam.unproject(torch.stack([u, v], -1), torch.ones_like(u)) - C  # [H, W, 3], camera z-depth 1
    t = (-2.0 - C[2] + 0.3 * C[0]) / (d[..., 2] - 0.3 * d[..., 0])
    normals = depth_normals(t, cam)  # z-depth = t since d has unit camera z
    want = torch.tensor([-0.3, 0.0, 1.0], dtype=torch.float64) / math.hypot(0.3, 1.0)
    torch.testing.assert_close(normals[1:-1, 1:-1], want.expand(18, 22, 3))
    assert bool((normals[0] == 0).all() and (normals[:, -1] == 0).all())
    t[5, 5] = 0  # a pixel without depth: its neighbours' differences are undefined
    assert bool((depth_normals(t, cam)[[4, 6, 5, 5], [5, 5, 4, 6]] == 0).all())
