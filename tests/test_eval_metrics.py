import math

import pytest
import torch

from ragsplat.errors import ConfigError
from ragsplat.eval import metrics
from ragsplat.eval.metrics import (
    LPIPS,
    load_lin_weights,
    load_lpips,
    psnr,
    sha256,
    ssim,
    ssim_standard,
    vgg16_features_init,
)
from ragsplat.ssim import ssim_map


def test_psnr_hand_value():
    a = torch.zeros(4, 5, 3)
    b = torch.full((4, 5, 3), 0.1)  # mse 0.01 -> 20 dB
    assert psnr(a, b).item() == pytest.approx(20.0, abs=1e-5)
    b[0, 0, 0] = 1.0  # one pixel channel off by 1: mse = (59 * 0.01 + 1) / 60
    assert psnr(a, b).item() == pytest.approx(-10 * math.log10((59 * 0.01 + 1) / 60), abs=1e-5)
    assert psnr(a, a).item() == math.inf


@pytest.fixture(scope="module")
def random_trunk_lpips():
    # the shipped learned heads on a random trunk: a valid metric, just not the published one
    return LPIPS(vgg16_features_init(seed=0), load_lin_weights())


def test_lpips_structure_with_random_trunk(random_trunk_lpips):
    gen = torch.Generator().manual_seed(0)
    a = torch.rand(32, 32, 3, generator=gen)
    b = (a + 0.2 * torch.rand(32, 32, 3, generator=gen)).clamp(0, 1)
    c = torch.rand(32, 32, 3, generator=gen)
    m = random_trunk_lpips
    assert m(a, a).item() == pytest.approx(0.0, abs=1e-7)
    ab, ba = m(a, b).item(), m(b, a).item()
    assert ab > 0 and ab == pytest.approx(ba, rel=1e-5)
    assert m(a, c).item() > ab  # an unrelated image is further than a perturbed one
    # both layouts give the same number
    bchw = m(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]).item()
    assert bchw == pytest.approx(ab, rel=1e-5)


def test_lpips_is_differentiable(random_trunk_lpips):
    a = torch.rand(32, 32, 3, requires_grad=True)
    random_trunk_lpips(a, torch.rand(32, 32, 3)).backward()
    assert torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0


def test_shipped_head_weights_are_lpips_v01():
    lins = load_lin_weights()
    assert [tuple(w.shape) for w in lins] == [(1, c, 1, 1) for c in (64, 128, 256, 512, 512)]
    assert all((w >= 0).all() for w in lins)  # LPIPS clamps its learned weights non-negative


def test_fabricated_backbone_fails_checksum(tmp_path):
    fake = tmp_path / metrics.VGG16_FILE  # right name, wrong content
    torch.save(vgg16_features_init(seed=1), fake)
    metric, reason = load_lpips(fake)
    assert metric is None
    assert "sha256" in reason and "397923af" in reason and "\n" not in reason


@pytest.fixture
def no_network(monkeypatch):
    """Every download attempt fails as offline (and is recorded); no test touches the network."""
    import urllib.error

    tries = []

    def offline(dst):
        tries.append(dst)
        raise urllib.error.URLError(OSError(-2, "Name or service not known"))

    monkeypatch.setattr(metrics, "download_vgg16", offline)
    return tries


def test_missing_backbone_gives_reason_and_a_wrong_path_is_an_error(tmp_path, monkeypatch, no_network):
    cached = tmp_path / "cache" / metrics.VGG16_FILE
    monkeypatch.setattr(metrics, "default_vgg16_path", lambda: cached)
    metric, reason = load_lpips(download=False)  # not in the cache, no download: LPIPS n/a, with the reason
    assert metric is None and "not found" in reason and "download off" in reason and "\n" not in reason
    assert no_network == []
    with pytest.raises(ConfigError, match="nowhere.pth: no such file"):  # a path the user gave must exist
        load_lpips(tmp_path / "nowhere.pth")
    assert no_network == []  # ... and is never downloaded to


def test_missing_backbone_download_fails_offline(tmp_path, monkeypatch, no_network):
    cached = tmp_path / "cache" / metrics.VGG16_FILE
    monkeypatch.setattr(metrics, "default_vgg16_path", lambda: cached)
    lines = []
    metric, reason = load_lpips(log=lines.append)  # not in the cache: tried, failed: n/a with the reason
    assert metric is None and no_network == [cached] and len(lines) == 1 and metrics.VGG16_URL in lines[0]
    assert "not found" in reason and "downloading" in reason and metrics.VGG16_URL in reason
    assert "Name or service not known" in reason and "\n" not in reason


def test_download_failures_of_any_kind_are_a_reason(tmp_path, monkeypatch):
    monkeypatch.setattr(metrics, "default_vgg16_path", lambda: tmp_path / metrics.VGG16_FILE)
    for err in (RuntimeError('invalid hash value (expected "397923af", got "00")\nmore'),
                PermissionError(13, "no"), TimeoutError(), ConnectionResetError(104, "reset")):
        def fail(dst, err=err):
            raise err
        monkeypatch.setattr(metrics, "download_vgg16", fail)
        metric, reason = load_lpips()
        assert metric is None and "downloading" in reason and "\n" not in reason
    monkeypatch.setattr(metrics, "download_vgg16", lambda dst: None)  # "succeeds" without a file
    left_none = (f"VGG16 ImageNet weights not found at {tmp_path / metrics.VGG16_FILE}; "
                 f"downloading {metrics.VGG16_URL} left no file there")
    assert load_lpips() == (None, left_none)


def test_download_then_lpips_and_the_network_is_recorded(tmp_path, monkeypatch):
    cached = tmp_path / "cache" / metrics.VGG16_FILE
    monkeypatch.setattr(metrics, "default_vgg16_path", lambda: cached)
    stand_in = tmp_path / "stand_in.pth"  # the real file is 528 MB: a random trunk, its checksum accepted
    torch.save(vgg16_features_init(seed=2), stand_in)
    monkeypatch.setattr(metrics, "VGG16_SHA256_PREFIX", sha256(stand_in)[:8])

    def download(dst):
        dst.parent.mkdir(parents=True)
        dst.write_bytes(stand_in.read_bytes())

    monkeypatch.setattr(metrics, "download_vgg16", download)
    metric, reason = load_lpips()
    assert reason == "" and isinstance(metric, LPIPS)
    assert metric.network == {"net": "vgg16 (torchvision ImageNet, vgg16-397923af.pth)",
                              "lin": "lpips v0.1 (lpips_vgg_v0.1.pth)", "source": str(cached),
                              "downloaded_from": "https://download.pytorch.org/models/vgg16-397923af.pth"}
    a = torch.rand(32, 32, 3)
    assert metric(a, a).item() == pytest.approx(0.0, abs=1e-7)
    # the next run finds it in the cache: no download, same network, no URL
    monkeypatch.setattr(metrics, "download_vgg16", lambda dst: pytest.fail("downloaded again"))
    again, _ = load_lpips()
    assert again.network == {**metric.network, "downloaded_from": None}
    # a given path: the same record, with that path
    assert load_lpips(stand_in)[0].network["source"] == str(stand_in)


def test_download_is_torch_hubs_with_the_hash_check(tmp_path, monkeypatch):
    # what download_vgg16 asks of torch.hub (no network: the hub call is replaced)
    calls = []
    monkeypatch.setattr(torch.hub, "download_url_to_file", lambda *a, **k: calls.append((a, k)))
    metrics.download_vgg16(tmp_path / "new" / metrics.VGG16_FILE)
    assert calls == [((metrics.VGG16_URL, str(tmp_path / "new" / metrics.VGG16_FILE)),
                      {"hash_prefix": "397923af", "progress": False})]
    assert (tmp_path / "new").is_dir()


def test_lpips_built_directly_says_so(random_trunk_lpips):
    assert random_trunk_lpips.network["source"] is None and "unchecked" in random_trunk_lpips.network["net"]


def test_wrong_trunk_shape_rejected():
    trunk = vgg16_features_init()
    trunk["features.28.weight"] = torch.zeros(512, 256, 3, 3)
    with pytest.raises(ValueError, match="features.28.weight"):
        LPIPS(trunk, load_lin_weights())


# ---- SSIM: the 3DGS one (`ssim`) and the standard one (`ssim_standard`) ----------------------------------

def ssim_test_images():
    gen = torch.Generator().manual_seed(3)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, 40, dtype=torch.float64),
                            torch.linspace(0, 1, 53, dtype=torch.float64), indexing="ij")
    ramp = torch.stack([xx, yy, 0.5 * (xx + yy)], dim=-1)
    checker = ((torch.arange(40)[:, None] // 4 + torch.arange(53)[None] // 4) % 2).double()
    checker = checker[..., None].expand(40, 53, 3).clone()
    noise = torch.rand(40, 53, 3, generator=gen, dtype=torch.float64)
    pairs = [
        (noise, torch.rand(40, 53, 3, generator=gen, dtype=torch.float64)),  # unrelated noise
        (noise, (noise + 0.1 * torch.randn(40, 53, 3, generator=gen, dtype=torch.float64)).clamp(0, 1)),
        (ramp, (ramp * 0.8 + 0.1).clamp(0, 1)),  # smooth, contrast and brightness changed
        (checker, (0.7 * checker + 0.3 * ramp)),  # edges
        (checker, torch.roll(checker, 2, dims=1)),  # shifted pattern: negative local correlation
        (ramp, ramp),  # identical
    ]
    return pairs


def test_ssim_standard_is_scikit_images():
    skm = pytest.importorskip("skimage.metrics")
    for a, b in ssim_test_images():
        ref = skm.structural_similarity(a.numpy(), b.numpy(), gaussian_weights=True, sigma=1.5,
                                        use_sample_covariance=False, data_range=1.0, channel_axis=-1)
        got = ssim_standard(a, b)
        assert got.dtype == torch.float64
        assert got.item() == pytest.approx(ref, abs=1e-9)
        # [B,3,H,W] gives the same; float32 inputs too (computed in float64)
        bchw = ssim_standard(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None])
        assert bchw.item() == pytest.approx(ref, abs=1e-9)
        assert ssim_standard(a.float(), b.float()).item() == pytest.approx(ref, abs=1e-6)


def test_ssim_standard_batch_is_the_mean_of_its_images():
    pairs = ssim_test_images()[:3]
    batch_a = torch.stack([a.permute(2, 0, 1) for a, _ in pairs])
    batch_b = torch.stack([b.permute(2, 0, 1) for _, b in pairs])
    per_image = [ssim_standard(a, b).item() for a, b in pairs]
    assert ssim_standard(batch_a, batch_b).item() == pytest.approx(sum(per_image) / 3, abs=1e-12)


def test_ssim_standard_differs_from_the_3dgs_ssim_only_at_the_border():
    a, b = ssim_test_images()[1]
    assert ssim_standard(a, a).item() == pytest.approx(1.0, abs=1e-12)
    # the 3DGS SSIM: zero padding biases its border, and the border counts
    assert abs(ssim(a, b).item() - ssim_standard(a, b).item()) > 1e-3
    # on the interior the two maps agree: 3DGS's map cropped by 5 pixels gives the standard value
    interior = ssim_map(a, b)[..., 5:-5, 5:-5].mean().item()
    assert interior == pytest.approx(ssim_standard(a, b).item(), abs=1e-12)


def test_ssim_standard_rejects_bad_input():
    with pytest.raises(ValueError, match="shapes differ"):
        ssim_standard(torch.zeros(20, 20, 3), torch.zeros(20, 21, 3))
    with pytest.raises(ValueError, match="smaller than the 11-pixel window"):
        ssim_standard(torch.zeros(10, 20, 3), torch.zeros(10, 20, 3))
