import math

import pytest
import torch

from ragsplat.gaussians import (
    activated,
    colors_for_view,
    eval_sh,
    init_grid,
    init_points,
    num_sh_bases,
    rgb_to_sh,
    sh_degree,
)
from ragsplat.raster.backends import backend
from ragsplat.water_surface import WaterSurface


def _sphere(n=6_000):
    """Fibonacci sphere: near-uniform unit directions [n, 3] for quadrature (weights 4 pi / n)."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (3 - math.sqrt(5)) * i
    r = torch.sqrt(1 - z * z)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


def _basis(dirs, degree):
    k = num_sh_bases(degree)
    # each basis function alone: one-hot coefficients, the same in all three channels
    c = torch.eye(k, dtype=dirs.dtype)[:, None, :, None].expand(k, len(dirs), k, 3).reshape(-1, k, 3)
    return eval_sh(degree, c, dirs.repeat(k, 1))[:, 0].reshape(k, len(dirs)).T  # [n, k]


def test_sh_basis_is_orthonormal():
    dirs = _sphere()
    Y = _basis(dirs, 3)
    gram = Y.T @ Y * (4 * math.pi / len(dirs))
    assert torch.allclose(gram, torch.eye(16, dtype=gram.dtype), atol=2e-3)


def test_sh_signs_match_3dgs():
    # 3DGS: band 1 is (-C1 y, C1 z, -C1 x); a +x direction must give a negative Y_3
    d = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]], dtype=torch.float64)
    Y = _basis(d, 1)
    assert Y[0, 3] < 0 and Y[1, 1] < 0 and Y[2, 2] > 0


def test_lower_degree_ignores_higher_coeffs():
    g = torch.Generator().manual_seed(0)
    c = torch.randn(5, 16, 3, generator=g, dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.randn(5, 3, generator=g, dtype=torch.float64), dim=-1)
    c2 = c.clone()
    c2[:, 4:] = 0
    assert torch.allclose(eval_sh(1, c, d), eval_sh(3, c2, d))
    assert not torch.allclose(eval_sh(3, c, d), eval_sh(1, c, d))


def test_rgb_round_trip_and_view_colors():
    splats = init_grid(-1, 1, -1, 1, -2.0, 0.5, degree=2, rgb=0.3, dtype=torch.float64)
    assert sh_degree(splats) == 2
    cam = torch.tensor([0.0, 0.0, 5.0], dtype=torch.float64)
    assert torch.allclose(colors_for_view(splats, cam, 2), torch.full((16, 3), 0.3, dtype=torch.float64))
    with torch.no_grad():
        splats["shN"][:, 0] = 1.0  # band-1 y term: the colour now depends on the view
    c_active0 = colors_for_view(splats, cam, 0)
    assert torch.allclose(c_active0, torch.full_like(c_active0, 0.3))
    assert not torch.allclose(colors_for_view(splats, cam, 1), c_active0)
    assert float(colors_for_view(splats, cam, 1).detach().min()) >= 0.0  # clamped
    assert torch.allclose(rgb_to_sh(torch.tensor(0.5)), torch.tensor(0.0))


def test_init_grid_layout():
    s = init_grid(0.0, 2.0, -1.0, 1.0, -10.0, 0.25, degree=3, opacity=0.1)
    assert s["means"].shape == (8 * 8, 3) and s["shN"].shape == (64, 15, 3) and s["sh0"].shape == (64, 1, 3)
    assert torch.allclose(s["means"][:, 2], torch.tensor(-10.0))
    xs = torch.unique(s["means"][:, 0])
    assert torch.allclose(xs, 0.125 + 0.25 * torch.arange(8.0))
    scales, quats, opac = activated(s)
    assert torch.allclose(scales, torch.tensor(0.25)) and torch.allclose(opac, torch.tensor(0.1))
    assert torch.allclose(quats, torch.tensor([1.0, 0, 0, 0]).expand(64, 4))
    assert "shN" not in init_grid(0, 1, 0, 1, 0, 0.5, degree=0)
    with pytest.raises(ValueError, match="degree"):
        init_grid(0, 1, 0, 1, 0, 0.5, degree=4)
    with pytest.raises(ValueError, match="spacing"):
        init_grid(0, 1, 0, 1, 0, 0.0)


def test_init_points_scales_underwater_depth():
    pts = torch.tensor([[0.0, 0, 1.0], [1.0, 0, -3.0], [0, 1.0, -6.0], [1.0, 1.0, -1.5]], dtype=torch.float64)
    rgb = torch.rand(4, 3, dtype=torch.float64)
    water = WaterSurface(level=-1.0, n=1.5)
    s = init_points(pts, rgb, water, degree=1)
    # depth below the level (level - z) times n; the point above the water unchanged
    assert torch.allclose(s["means"][:, 2], torch.tensor([1.0, -4.0, -8.5, -1.75], dtype=torch.float64))
    assert torch.allclose(s["means"][:, :2], pts[:, :2])
    assert torch.allclose(colors_for_view(s, torch.zeros(3, dtype=torch.float64), 0), rgb)
    assert torch.allclose(init_points(pts, rgb, water, depth_scale=1.0)["means"], pts)
    assert torch.allclose(init_points(pts, rgb, None)["means"], pts)
    # scale: mean distance to the 3 nearest neighbours (all other points here)
    m = s["means"]
    d0 = torch.cdist(m, m)[0, 1:].mean()
    assert torch.allclose(torch.exp(s["scales"][0]), d0.expand(3))
    with pytest.raises(ValueError, match="non-finite"):
        init_points(pts * float("nan"), rgb, None)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
@pytest.mark.parametrize("degree", [1, 2, 3])
def test_sh_kernel_matches_its_twin(degree, dtype, tol):
    # the numba view colours against the PyTorch ones: values, and the gradients to sh0, shN and the means;
    # some colours clamped at 0 (no gradient there), every direction, and more coefficients than used
    gen = torch.Generator().manual_seed(degree)
    n = 500
    splats = {"means": torch.randn(n, 3, generator=gen, dtype=torch.float64) * 3,
              "sh0": torch.randn(n, 1, 3, generator=gen, dtype=torch.float64),
              "shN": torch.randn(n, 15, 3, generator=gen, dtype=torch.float64) * 0.5}
    center = torch.tensor([0.3, -0.2, 4.0], dtype=torch.float64)
    out, grads = {}, {}
    for fast in (False, True):
        leaves = {k: v.to(dtype).clone().requires_grad_() for k, v in splats.items()}  # own grads
        colors = backend("cpu" if fast else "torch").colors(leaves, center.to(dtype), degree)
        weights = torch.randn(n, 3, generator=torch.Generator().manual_seed(7), dtype=torch.float64).to(dtype)
        (colors * weights).sum().backward()
        out[fast], grads[fast] = colors.detach(), {k: v.grad for k, v in leaves.items()}
    assert 0.05 < float((out[False] == 0).double().mean()) < 0.5  # the clamp is exercised
    torch.testing.assert_close(out[True], out[False], rtol=tol, atol=tol)
    for k in ("sh0", "shN", "means"):
        torch.testing.assert_close(grads[True][k], grads[False][k], rtol=tol, atol=tol)
    unused = grads[True]["shN"][:, (degree + 1) ** 2 - 1:]
    assert unused.numel() == 0 or float(unused.abs().max()) == 0.0  # no gradient to the unused degrees


def test_sh_kernel_gradient_matches_finite_differences():
    # the means' gradient (through the view direction) from first principles, in float64
    from ragsplat.raster.cpu.sh import view_colors

    gen = torch.Generator().manual_seed(3)
    means = torch.randn(20, 3, generator=gen, dtype=torch.float64).requires_grad_()
    sh0 = torch.randn(20, 1, 3, generator=gen, dtype=torch.float64).requires_grad_()
    shN = (torch.randn(20, 15, 3, generator=gen, dtype=torch.float64) * 0.3).requires_grad_()
    center = torch.tensor([0.0, 0.0, 5.0], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda m, a, b: view_colors(a, b, m, center, 3), (means, sh0, shN))


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_shape_kernels_match_their_twins(dtype, tol):
    # numba covariance R S S^T R^T and surfel tangents R[:, :2] diag(s) against the PyTorch ones: values and
    # the gradients to the (unnormalised) quaternions and the scales
    gen = torch.Generator().manual_seed(5)
    quats = (torch.randn(400, 4, generator=gen, dtype=torch.float64) * 2).to(dtype)
    scales = (torch.rand(400, 3, generator=gen, dtype=torch.float64) + 0.05).to(dtype)
    for shape, cols in (("covariance", 3), ("tangents", 2)):
        weights = torch.randn(400, 3, cols, generator=gen, dtype=torch.float64).to(dtype)
        res = []
        for name in ("torch", "cpu"):
            q, s = quats.clone().requires_grad_(), scales[:, :cols].clone().requires_grad_()
            out = getattr(backend(name), shape)(q, s)
            (out * weights).sum().backward()
            res.append((out.detach(), q.grad, s.grad))
        for got, want in zip(res[1], res[0]):
            torch.testing.assert_close(got, want, rtol=tol, atol=tol)


def test_shape_kernels_gradients_match_finite_differences():
    from ragsplat.raster.cpu.rotation import covariance_cpu as cov_fast
    from ragsplat.raster.cpu.rotation import tangents_cpu as tangents

    gen = torch.Generator().manual_seed(6)
    quats = torch.randn(12, 4, generator=gen, dtype=torch.float64).requires_grad_()
    scales = (torch.rand(12, 3, generator=gen, dtype=torch.float64) + 0.1).requires_grad_()
    assert torch.autograd.gradcheck(cov_fast, (quats, scales))
    assert torch.autograd.gradcheck(tangents, (quats, scales[:, :2].detach().clone().requires_grad_()))
