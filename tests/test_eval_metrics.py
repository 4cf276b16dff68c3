import math

import pytest
import torch

from eval import metrics
from eval.metrics import LPIPS, load_lin_weights, load_lpips, psnr, vgg16_features_init
from ragsplat_core.errors import ConfigError


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


def test_missing_backbone_gives_reason_and_a_wrong_path_is_an_error(tmp_path, monkeypatch):
    monkeypatch.setattr(metrics, "default_vgg16_path", lambda: tmp_path / "cache" / metrics.VGG16_FILE)
    metric, reason = load_lpips()  # not in the cache: LPIPS n/a, with the reason
    assert metric is None and "not found" in reason and "\n" not in reason
    with pytest.raises(ConfigError, match="nowhere.pth: no such file"):  # a path the user gave must exist
        load_lpips(tmp_path / "nowhere.pth")


def test_wrong_trunk_shape_rejected():
    trunk = vgg16_features_init()
    trunk["features.28.weight"] = torch.zeros(512, 256, 3, 3)
    with pytest.raises(ValueError, match="features.28.weight"):
        LPIPS(trunk, load_lin_weights())
