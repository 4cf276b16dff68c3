"""Rasterizer semantics (3DGS / gsplat classic), checked on the torch reference and the cpu backend."""

import math

import numpy as np
import pytest
import torch

from ragsplat.camera import Camera
from ragsplat.gaussians import covariance, quat_to_rotmat
from ragsplat.rasterize import rasterize

NADIR_R = np.diag([1.0, -1.0, -1.0])  # looks down world -z; camera x = world x, camera y = world -y
BACKENDS = ["torch", "cpu"]


def nadir(width=40, height=30, fov=60.0, height_m=2.0):
    return Camera.from_fov(width, height, fov, NADIR_R, -NADIR_R @ np.array([0.0, 0.0, height_m]))


def scene(n, seed, dtype=torch.float64, spread=(0.8, 0.6), size=(0.02, 0.08)):
    """Random Gaussians around the ground point under a nadir camera, all in front of it."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * torch.tensor([*spread, 0.4], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = size[0] + (size[1] - size[0]) * torch.rand(n, 3, generator=g, dtype=dtype)
    opacities = 0.05 + 0.95 * torch.rand(n, generator=g, dtype=dtype)
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    return [means, quats, scales, opacities, colors]


def literal_3dgs(means, quats, scales, opacities, colors, cam, bg):
    """The per-pixel loop of 3DGS's forward kernel over all Gaussians (no tiles, no boxes), in float64, with
    2DGS's median depth (the z of the Gaussian that takes T from above 0.5 to at most 0.5; 0 if none)."""
    from ragsplat.raster.reference.project import project

    proj = project(means, covariance(quats, scales), opacities, cam)
    m2, con, z = proj.means2d.detach().numpy(), proj.conics.detach().numpy(), proj.depths.detach().numpy()
    keep = (z >= 0.01) & (opacities.detach().numpy() >= 1 / 255)
    order = [k for k in np.argsort(z, kind="stable") if keep[k]]
    o, c = opacities.detach().numpy(), colors.detach().numpy()
    img = np.zeros((cam.height, cam.width, 3))
    alpha = np.zeros((cam.height, cam.width))
    depth = np.zeros((cam.height, cam.width))
    median = np.zeros((cam.height, cam.width))
    for j in range(cam.height):
        for i in range(cam.width):
            T, acc, dz = 1.0, np.zeros(3), 0.0
            for k in order:
                dx, dy = m2[k, 0] - (i + 0.5), m2[k, 1] - (j + 0.5)
                power = -0.5 * (con[k, 0] * dx * dx + con[k, 2] * dy * dy) - con[k, 1] * dx * dy
                if power > 0:
                    continue
                a = min(0.99, o[k] * math.exp(power))
                if a < 1 / 255:
                    continue
                if T * (1 - a) < 1e-4:
                    break
                acc += c[k] * a * T
                dz += z[k] * a * T
                if T > 0.5 >= T * (1 - a):
                    median[j, i] = z[k]
                T *= 1 - a
            img[j, i] = acc + T * np.asarray(bg)
            alpha[j, i] = 1 - T
            depth[j, i] = dz / (1 - T) if T < 1 else 0.0
    return img, alpha, depth, median


@pytest.mark.parametrize("backend", BACKENDS)
def test_matches_the_literal_3dgs_loop(backend):
    # Gaussians of all sizes crossing tile borders (the image is 3 x 2 tiles) and stacking to saturation.
    cam = nadir(40, 30)
    params = scene(60, seed=1, size=(0.01, 0.15))
    bg = [0.2, 0.5, 0.9]
    want = literal_3dgs(*params, cam, bg)
    image, alpha, depth, meta = rasterize(*params, cam, bg, backend=backend, median=True)
    tol = 1e-9 if backend == "torch" else 2e-5  # cpu composites in float32
    np.testing.assert_allclose(image.numpy(), want[0], atol=tol)
    np.testing.assert_allclose(alpha[..., 0].numpy(), want[1], atol=tol)
    np.testing.assert_allclose(depth[..., 0].numpy(), want[2], atol=tol * 100)
    np.testing.assert_allclose(meta["median_depth"][..., 0].numpy(), want[3], atol=tol * 100)
    assert (alpha > 0.5).any() and (alpha < 0.5).any()
    assert len(np.unique(want[3])) > 10  # many Gaussians are some pixel's median, and 0 where T > 0.5


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize(("o1", "o2", "layer"), [(0.6, 0.3, 1), (0.3, 0.6, 2), (0.2, 0.2, 0)])
def test_median_depth_of_two_layers(backend, o1, o2, layer):
    # Two sheets much wider than the view at 1.2 m and 1.7 m from a nadir camera: alpha = o at every pixel.
    # T falls to <= 0.5 at the first sheet (1 - 0.6), at the second (0.7 x 0.4), or never (0.8 x 0.8).
    cam = nadir(32, 32, height_m=2.0)
    means = torch.tensor([[0.0, 0.0, 0.8], [0.0, 0.0, 0.3]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2, dtype=torch.float64)
    scales = torch.tensor([[1e3, 1e3, 1e-3]] * 2, dtype=torch.float64)
    opac = torch.tensor([o1, o2], dtype=torch.float64)
    _, _, depth, meta = rasterize(means, quats, scales, opac, torch.rand(2, 3, dtype=torch.float64), cam,
                                  [0.0, 0.0, 0.0], backend=backend, median=True)
    want = {0: 0.0, 1: 1.2, 2: 1.7}[layer]
    np.testing.assert_allclose(meta["median_depth"].numpy(), want, atol=1e-5)
    assert float((depth - meta["median_depth"]).abs().min()) > 0.05  # the expected depth is another thing


@pytest.mark.parametrize("backend", BACKENDS)
def test_median_depth_is_opt_in_and_changes_nothing_else(backend):
    # Bit-identical is the promise: the median is a second output computed outside the graph, so both calls
    # run the same operations on the gradient path, in one process (a 5- vs 6-channel concatenation once made
    # the backward a different graph, and one gradient differed in the last bit on some CPUs).
    cam, params = nadir(40, 30), scene(60, seed=1, size=(0.01, 0.15))
    params = [p.requires_grad_(True) for p in params]
    plain = rasterize(*params, cam, [0.2, 0.5, 0.9], backend=backend)
    both = rasterize(*params, cam, [0.2, 0.5, 0.9], backend=backend, median=True)
    assert plain[3]["median_depth"] is None and not both[3]["median_depth"].requires_grad
    for a, b in zip(plain[:3], both[:3]):
        assert torch.equal(a, b)
    grads = [torch.autograd.grad(out[0].sum() + out[2].sum(), params) for out in (plain, both)]
    for a, b in zip(*grads):
        assert torch.equal(a, b)


@pytest.mark.parametrize("backend", BACKENDS)
def test_single_isotropic_gaussian_footprint(backend):
    # A sphere of radius sigma at camera-frame point p projects to a 2D Gaussian with covariance
    # J J^T sigma^2 + 0.3 I (J = d(u, v)/d(x, y, z) at p), centred on the projected pixel.
    cam = nadir(48, 36, fov=60.0, height_m=2.0)
    mean = np.array([0.13, -0.07, 0.1])  # off-axis, so J has its off-diagonal terms
    sigma, opacity, color, bg = 0.03, 0.8, np.array([1.0, 0.5, 0.25]), np.array([0.1, 0.1, 0.1])
    x, y, z = cam.R @ mean + cam.t
    J = np.array([[cam.fx / z, 0, -cam.fx * x / z**2], [0, cam.fy / z, -cam.fy * y / z**2]])
    cov = sigma**2 * J @ J.T + 0.3 * np.eye(2)
    centre = np.array([cam.fx * x / z + cam.cx, cam.fy * y / z + cam.cy])
    jj, ii = np.mgrid[0:cam.height, 0:cam.width]
    d = np.stack([ii + 0.5, jj + 0.5], -1) - centre
    g = opacity * np.exp(-0.5 * np.einsum("hwi,ij,hwj->hw", d, np.linalg.inv(cov), d))
    a = np.where(g >= 1 / 255, np.minimum(g, 0.99), 0.0)
    want = a[..., None] * color + (1 - a[..., None]) * bg

    t = [torch.tensor(np.array(v), dtype=torch.float64) for v in
         ([mean], [[0.3, 0.1, -0.5, 0.2]], [[sigma] * 3], [opacity], [color], bg)]
    image, alpha, depth, meta = rasterize(*t[:5], cam, t[5], backend=backend)
    tol = 1e-9 if backend == "torch" else 1e-5
    np.testing.assert_allclose(image.numpy(), want, atol=tol)
    np.testing.assert_allclose(alpha[..., 0].numpy(), a, atol=tol)
    np.testing.assert_allclose(depth[..., 0].numpy(), np.where(a > 0, z, 0.0), atol=tol * 10)
    np.testing.assert_allclose(meta["means2d"].detach().numpy()[0], centre, atol=1e-9)
    # The brightest pixel is the one containing the projected centre.
    assert np.unravel_index(alpha[..., 0].argmax(), a.shape) == (int(centre[1]), int(centre[0]))
    assert int(meta["radii"][0]) > 0 and bool(meta["visible"][0])


@pytest.mark.parametrize("backend", BACKENDS)
def test_input_order_does_not_matter(backend):
    cam = nadir()
    params = scene(50, seed=2)
    perm = torch.randperm(50, generator=torch.Generator().manual_seed(0))
    a = rasterize(*params, cam, [0.0, 0.0, 0.0], backend=backend)
    b = rasterize(*[p[perm] for p in params], cam, [0.0, 0.0, 0.0], backend=backend)
    for x, y in zip(a[:3], b[:3]):
        torch.testing.assert_close(x, y, atol=1e-6, rtol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_pixel_stops_before_transmittance_drops_below_1e_4(backend):
    # Five large Gaussians of opacity 0.95 on the optical axis, 10 cm apart. At the centre pixel
    # (alpha ~ 0.95) T goes 0.05, 2.5e-3, 1.25e-4 and the 4th would give 6.25e-6 < 1e-4: only 3 count.
    cam = nadir(17, 17)  # odd size: the optical axis hits the centre of pixel (8, 8)
    n = 5
    means = torch.tensor([[0.0, 0.0, -0.1 * k] for k in range(n)], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0]] * n, dtype=torch.float64)
    scales = torch.full((n, 3), 0.5, dtype=torch.float64)
    colors = torch.eye(3, dtype=torch.float64)[[0, 1, 2, 0, 1]].clone().requires_grad_(True)
    opacities = torch.full((n,), 0.95, dtype=torch.float64)
    bg = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    image, alpha, _, _ = rasterize(means, quats, scales, opacities, colors, cam, bg, backend=backend)
    a = float(0.95 * torch.exp(-0.5 * torch.tensor(0.0)))  # centre pixel: d = 0 up to the 0.3 px dilation
    # Weights of the first three: a, a(1-a), a(1-a)^2; T = (1-a)^3 of background blue shows through.
    px = image[8, 8].detach()
    assert float(alpha[8, 8].detach()) == pytest.approx(1 - (1 - a) ** 3, abs=1e-4)
    assert float(px[0]) == pytest.approx(a, abs=1e-4)
    assert float(px[1]) == pytest.approx(a * (1 - a), abs=1e-4)
    assert float(px[2]) == pytest.approx(a * (1 - a) ** 2 + (1 - a) ** 3, abs=1e-4)
    image[8, 8].sum().backward()
    assert torch.all(colors.grad[3:] == 0) and torch.all(colors.grad[:3] > 0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_background_where_nothing_is_drawn(backend):
    cam = nadir()
    params = scene(10, seed=3, spread=(0.1, 0.1), size=(0.005, 0.01))  # a small cluster in the middle
    bg = torch.tensor([0.3, 0.6, 0.9], dtype=torch.float64)
    image, alpha, depth, _ = rasterize(*params, cam, bg, backend=backend)
    empty = alpha[..., 0] == 0
    assert empty.sum() > 0.8 * empty.numel() and (~empty).sum() > 0
    assert torch.equal(image[empty], bg.expand(int(empty.sum()), 3))
    assert torch.all(depth[empty] == 0) and torch.all(depth[~empty] > 0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_behind_near_plane_is_culled(backend):
    cam = nadir(height_m=2.0)
    params = scene(3, seed=4)
    params[0] = torch.tensor([[0.0, 0.0, 1.995], [0.0, 0.0, 3.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    params[3] = torch.full((3,), 0.9, dtype=torch.float64)
    _, _, depth, meta = rasterize(*params, cam, [0.0, 0.0, 0.0], backend=backend)
    assert meta["radii"].tolist()[:2] == [0, 0] and int(meta["radii"][2]) > 0
    assert meta["visible"].tolist() == [False, False, True]
    assert float(depth.max()) == pytest.approx(2.0, abs=1e-5)  # only the Gaussian 2 m away is seen


@pytest.mark.parametrize("backend", BACKENDS)
def test_covariances_replace_quats_and_scales(backend):
    cam = nadir()
    means, quats, scales, opacities, colors = scene(30, seed=5)
    covars = covariance(quats, scales)
    a = rasterize(means, quats, scales, opacities, colors, cam, [0.1, 0.1, 0.1], backend=backend)
    b = rasterize(means, None, None, opacities, colors, cam, [0.1, 0.1, 0.1], covars=covars, backend=backend)
    c = rasterize(means, 3.7 * quats, scales, opacities, colors, cam, [0.1, 0.1, 0.1], backend=backend)
    for x, y, z in zip(a[:3], b[:3], c[:3]):
        torch.testing.assert_close(x, y, atol=1e-6, rtol=0)
        torch.testing.assert_close(x, z, atol=1e-6, rtol=0)


def test_quaternion_convention_is_wxyz():
    # 90 degrees about z: (w, x, y, z) = (cos 45, 0, 0, sin 45) maps x to y.
    q = torch.tensor([[math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]], dtype=torch.float64)
    R = quat_to_rotmat(q)[0]
    torch.testing.assert_close(R @ torch.tensor([1.0, 0, 0], dtype=torch.float64),
                               torch.tensor([0.0, 1.0, 0], dtype=torch.float64))


def test_torch_reference_gradients_match_finite_differences():
    cam = nadir(20, 16)
    params = scene(8, seed=6, size=(0.05, 0.12))
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64)
    g = torch.Generator().manual_seed(1)
    w_img, w_a, w_d = (torch.rand(16, 20, k, generator=g, dtype=torch.float64) for k in (3, 1, 1))

    def loss(*p):
        image, alpha, depth, _ = rasterize(*p, cam, bg, backend="torch")
        return (image * w_img).sum() + (alpha * w_a).sum() + (depth * w_d).sum()

    inputs = [p.clone().requires_grad_(True) for p in params]
    # fast mode: checks random directional derivatives, a few renders instead of two per input element
    assert torch.autograd.gradcheck(loss, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_means2d_gradient_is_available_for_densification():
    cam = nadir()
    params = [p.requires_grad_(True) for p in scene(20, seed=7)]
    image, _, _, meta = rasterize(*params, cam, [0.0, 0.0, 0.0], backend="torch")
    image.sum().backward()
    grad = meta["means2d"].grad
    assert grad is not None and grad.shape == (20, 2)
    assert (meta["width"], meta["height"]) == (cam.width, cam.height)
    assert torch.all(grad[~meta["visible"]] == 0) and grad[meta["visible"]].abs().sum() > 0


def test_backend_choice_and_errors():
    cam = nadir()
    params = scene(5, seed=8)
    assert rasterize(*params, cam, [0.0, 0.0, 0.0])[3]["backend"] == "cpu"  # auto on CPU tensors
    with pytest.raises(ValueError, match="unknown rasterizer backend"):
        rasterize(*params, cam, [0.0, 0.0, 0.0], backend="opengl")
    with pytest.raises(ValueError, match="gsplat"):
        rasterize(*params, cam, [0.0, 0.0, 0.0], backend="gsplat")  # CPU tensors: never gsplat
    with pytest.raises(ValueError, match="scales must be a tensor of shape"):
        rasterize(params[0], params[1], params[2][:3], *params[3:], cam, [0.0, 0.0, 0.0])


def test_no_gaussians_renders_background():
    cam = nadir(8, 8)
    empty = [torch.zeros((0, *shape), dtype=torch.float64) for shape in ((3,), (4,), (3,), (), (3,))]
    for backend in BACKENDS:
        image, alpha, depth, _ = rasterize(*empty, cam, [0.5, 0.5, 0.5], backend=backend)
        assert torch.all(image == 0.5) and torch.all(alpha == 0) and torch.all(depth == 0)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 2e-4)])
def test_cpu_projection_matches_its_twin(dtype, tol):
    # the numba EWA projection against project.project: outputs, boxes, and the gradients to the means and
    # the covariances; with Gaussians behind the camera, too faint to draw, and far outside the view (where
    # the Jacobian's x/z, y/z are clamped)
    from ragsplat.raster.cpu import project as project_cpu
    from ragsplat.raster.reference.project import project

    cam = nadir(width=48, height=36)
    means, quats, scales, opacities, _ = scene(600, 8, dtype=torch.float64, spread=(6.0, 5.0),
                                               size=(0.01, 0.2))
    means[::13, 2] = 3.0  # behind the camera (at 2 m, looking down)
    opacities[::17] = 1e-3  # below 1/255
    covars = covariance(quats, scales)
    gen = torch.Generator().manual_seed(9)
    weights = [torch.randn(600, k, generator=gen, dtype=torch.float64).to(dtype) for k in (2, 3, 1)]
    res = []
    for fn in (project, project_cpu.project):
        # own grads
        m, c = means.to(dtype).clone().requires_grad_(), covars.to(dtype).clone().requires_grad_()
        p = fn(m, c, opacities.to(dtype), cam)
        ((p.means2d * weights[0]).sum() + (p.conics * weights[1]).sum() + (p.depths * weights[2][:, 0]).sum()
         ).backward()
        res.append((p, m.grad, c.grad))
    (want, g_m, g_c), (got, f_m, f_c) = res
    for name in ("means2d", "conics", "depths"):
        torch.testing.assert_close(getattr(got, name), getattr(want, name), rtol=tol, atol=tol)
    torch.testing.assert_close(f_m, g_m, rtol=tol, atol=tol)
    torch.testing.assert_close(f_c, g_c, rtol=tol, atol=tol)
    if dtype == torch.float64:
        for name in ("box", "visible", "radii"):
            assert torch.equal(getattr(got, name), getattr(want, name)), name
    assert 0 < int(want.visible.sum()) < 500


def test_cpu_projection_gradients_match_finite_differences():
    from ragsplat.raster.cpu import project as project_cpu

    cam = nadir(width=48, height=36)
    means, quats, scales, opacities, _ = scene(15, 3, spread=(3.0, 2.5))
    covars = covariance(quats, scales).requires_grad_()

    def outputs(m, c):
        p = project_cpu.project(m, c, opacities, cam)
        return p.means2d, p.conics, p.depths

    assert torch.autograd.gradcheck(outputs, (means.requires_grad_(), covars))
