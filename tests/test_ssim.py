import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from ragsplat.ssim import ssim, ssim_map

PAD = 5  # half the 11-tap window: beyond it the zero padding of 3DGS and skimage's reflection differ


def _pair(seed=0, h=40, w=48):
    rng = np.random.default_rng(seed)
    a = rng.random((h, w, 3))
    # a correlated, not identical, second image so SSIM is away from 0 and 1
    b = np.clip(0.7 * a + 0.3 * rng.random((h, w, 3)) + 0.05, 0, 1)
    return a, b


def test_matches_skimage_on_interior_crop():
    a, b = _pair()
    _, ref = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                   data_range=1.0, channel_axis=-1, full=True)  # ref: [H, W, 3]
    ours = ssim_map(torch.from_numpy(a), torch.from_numpy(b))[0].permute(1, 2, 0).numpy()
    inner = (slice(PAD, -PAD), slice(PAD, -PAD))
    np.testing.assert_allclose(ours[inner], ref[inner], rtol=0, atol=1e-10)
    # the padding makes the border differ, so the crop above is really what is being compared
    assert np.abs(ours - ref).max() > 1e-3


def test_layouts_agree_and_identical_is_one():
    a, b = _pair(1)
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    hwc = ssim(ta, tb)
    bchw = ssim(ta.permute(2, 0, 1)[None], tb.permute(2, 0, 1)[None])
    assert torch.allclose(hwc, bchw, atol=1e-12)
    assert 0.0 < hwc.item() < 1.0
    assert ssim(ta, ta).item() == pytest.approx(1.0, abs=1e-12)


def test_differentiable_and_float32():
    a, b = _pair(2)
    x = torch.from_numpy(a).float().requires_grad_(True)
    y = torch.from_numpy(b).float()
    loss = 1 - ssim(x, y)
    loss.backward()
    assert loss.dtype == torch.float32
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    # gradient check in float64 on a small image
    xs = torch.from_numpy(a[:9, :8]).requires_grad_(True)
    ys = torch.from_numpy(b[:9, :8])
    assert torch.autograd.gradcheck(lambda t: ssim(t, ys), (xs,), fast_mode=True)


def test_bad_shapes_rejected():
    with pytest.raises(ValueError):
        ssim(torch.zeros(8, 8, 4), torch.zeros(8, 8, 4))
    with pytest.raises(ValueError):
        ssim(torch.zeros(8, 8, 3), torch.zeros(8, 9, 3))


def test_matches_the_2d_window_of_3dgs_everywhere():
    # 3DGS's own formulation: one grouped 2-D conv per moment with an 11x11 window, padding 5
    import torch.nn.functional as F

    from ragsplat.ssim import C1, C2, gaussian_window

    a, b = (torch.from_numpy(x).permute(2, 0, 1)[None] for x in _pair(3, 23, 29))
    g = gaussian_window(dtype=torch.float64)
    w = (g[:, None] * g[None, :]).expand(3, 1, 11, 11)

    def blur(x):
        return F.conv2d(x, w, padding=5, groups=3)

    mu1, mu2 = blur(a), blur(b)
    s1, s2, s12 = blur(a * a) - mu1**2, blur(b * b) - mu2**2, blur(a * b) - mu1 * mu2
    ref = ((2 * mu1 * mu2 + C1) * (2 * s12 + C2)) / ((mu1**2 + mu2**2 + C1) * (s1 + s2 + C2))
    assert torch.allclose(ssim_map(a, b), ref, rtol=0, atol=1e-12)
    two = ssim_map(torch.cat([a, b]), torch.cat([b, a]))  # a batch of two
    assert torch.allclose(two[0], ref[0], atol=1e-12) and torch.allclose(two[1], ref[0], atol=1e-12)
