"""Appearance metrics for Table 1: PSNR, two SSIMs, and LPIPS (VGG).

Images are float tensors in [0, 1], either [H, W, 3] or [B, 3, H, W].

Which SSIM is which (both Wang et al. 2004 with an 11-tap Gaussian window, sigma 1.5, K1 0.01, K2 0.03,
data range 1, population statistics; they differ only at the border):
- `ssim`: the 3D Gaussian Splatting one, shared with the training loss (`ragsplat.ssim`): the window
  runs with zero padding ("same"), and the mean is over the whole map, border included, so it is biased
  by the padding. It is the value 3DGS's own metrics script reports.
- `ssim_standard`: the standard value that scikit-image (`structural_similarity(..., gaussian_weights=True,
  sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1)`) and torchmetrics
  (`structural_similarity_index_measure(..., data_range=1.0)`) give: only the window positions inside the
  image (a (11 - 1) / 2 = 5 pixel border is left out), averaged over pixels, then channels.

LPIPS is the published VGG variant (Zhang et al. 2018, v0.1): torchvision's ImageNet VGG16 `features`
trunk, re-implemented here in plain torch with torchvision's layer indices (so its `vgg16-397923af.pth`
state dict loads as is), plus the learned 1x1 linear heads shipped in `eval/weights/lpips_vgg_v0.1.pth`
(BSD-2-Clause, see `eval/weights/LICENSE-lpips`). The ImageNet weights come from a user-given path or
torch's hub cache; when the cache lacks them they are downloaded as torchvision does (from
download.pytorch.org into the hub cache, the sha256 prefix in the file name checked). Every file is checked
against that checksum before use. Without them (offline, failed download, wrong file) LPIPS is reported as
unavailable with the reason, never computed with another network. `LPIPS.network` records which network
and weights a metric uses.
"""

from __future__ import annotations

import hashlib
import socket
from collections.abc import Callable
from pathlib import Path

import torch
import torch.nn.functional as F

from ragsplat.errors import ConfigError
from ragsplat.ssim import C1, C2, SIGMA, channels_first, gaussian_window, psnr, ssim

__all__ = ["LPIPS", "VGG16_FILE", "VGG16_URL", "load_lpips", "psnr", "ssim", "ssim_standard",
           "vgg16_features_init"]

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
LPIPS_LIN_FILE = WEIGHTS_DIR / "lpips_vgg_v0.1.pth"
LPIPS_LIN_SHA256 = "a78928a0af1e5f0fcb1f3b9e8f8c3a2a5a3de244d830ad5c1feddc79b8432868"
# torchvision names its checkpoints <arch>-<first 8 hex digits of the file's sha256>.pth
VGG16_FILE = "vgg16-397923af.pth"
VGG16_SHA256_PREFIX = "397923af"
# where torchvision's `vgg16(weights=VGG16_Weights.IMAGENET1K_V1)` downloads them from
VGG16_URL = f"https://download.pytorch.org/models/{VGG16_FILE}"
VGG16_NET = f"vgg16 (torchvision ImageNet, {VGG16_FILE})"
LPIPS_LIN = "lpips v0.1"
# seconds a blocking socket step of the download may stall (not the whole download)
DOWNLOAD_TIMEOUT_S = 60

# torchvision vgg16 `features`: conv layer index -> (in, out) channels; a ReLU follows each conv and
# max-pools sit at 4, 9, 16, 23. LPIPS taps relu1_2, relu2_2, relu3_3, relu4_3, relu5_3.
VGG16_CONVS = {0: (3, 64), 2: (64, 64), 5: (64, 128), 7: (128, 128), 10: (128, 256), 12: (256, 256),
               14: (256, 256), 17: (256, 512), 19: (512, 512), 21: (512, 512), 24: (512, 512),
               26: (512, 512), 28: (512, 512)}
VGG16_POOLS = (4, 9, 16, 23)
VGG16_TAPS = (3, 8, 15, 22, 29)
LPIPS_CHANNELS = (64, 128, 256, 512, 512)
# LPIPS ScalingLayer: maps [-1, 1] inputs to ImageNet-normalised ones
LPIPS_SHIFT = (-0.030, -0.088, -0.188)
LPIPS_SCALE = (0.458, 0.448, 0.450)


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def vgg16_features_init(seed: int = 0) -> dict[str, torch.Tensor]:
    """A randomly initialised trunk in the torchvision key layout (for tests: the metric's structure
    without ImageNet weights; never used to report LPIPS)."""
    gen = torch.Generator().manual_seed(seed)
    state = {}
    for idx, (cin, cout) in VGG16_CONVS.items():
        std = (2.0 / (cin * 9)) ** 0.5  # He init keeps activations from vanishing through 13 layers
        state[f"features.{idx}.weight"] = torch.randn(cout, cin, 3, 3, generator=gen) * std
        state[f"features.{idx}.bias"] = torch.zeros(cout)
    return state


class LPIPS:
    """LPIPS-VGG distance. Holds tensors only (no nn.Module): trunk convs keyed like torchvision.

    `network` (a JSON-able dict, also the attribute `.network`) says what the metric is made of:
    {"net": trunk, "lin": linear heads, "source": the trunk's file or None, "downloaded_from": URL or None}.
    `load_lpips` fills it in; built directly, the default says the weights are the caller's, unchecked.
    """

    def __init__(self, trunk: dict[str, torch.Tensor], lins: list[torch.Tensor], network: dict | None = None):
        missing = [f"features.{i}.{p}" for i in VGG16_CONVS for p in ("weight", "bias")
                   if f"features.{i}.{p}" not in trunk]
        if missing:
            raise ValueError(f"VGG16 state dict lacks {missing[0]} (and {len(missing) - 1} more)")
        for i, (cin, cout) in VGG16_CONVS.items():
            if tuple(trunk[f"features.{i}.weight"].shape) != (cout, cin, 3, 3):
                raise ValueError(f"features.{i}.weight has shape "
                                 f"{tuple(trunk[f'features.{i}.weight'].shape)}")
        if [tuple(w.shape) for w in lins] != [(1, c, 1, 1) for c in LPIPS_CHANNELS]:
            raise ValueError(f"LPIPS linear weights have shapes {[tuple(w.shape) for w in lins]}")
        self.trunk = {k: v.detach().float() for k, v in trunk.items() if k.startswith("features.")}
        self.lins = [w.detach().float() for w in lins]
        self.network = {"net": "vgg16 trunk given by the caller (unchecked)", "lin": "given by the caller",
                        "source": None, "downloaded_from": None, **(network or {})}

    def to(self, device) -> LPIPS:
        self.trunk = {k: v.to(device) for k, v in self.trunk.items()}
        self.lins = [w.to(device) for w in self.lins]
        return self

    def _features(self, x: torch.Tensor) -> list[torch.Tensor]:
        taps = []
        for idx in range(VGG16_TAPS[-1] + 1):
            if idx in VGG16_CONVS:
                x = F.conv2d(x, self.trunk[f"features.{idx}.weight"], self.trunk[f"features.{idx}.bias"],
                             padding=1)
            elif idx in VGG16_POOLS:
                x = F.max_pool2d(x, kernel_size=2, stride=2)
            else:
                x = F.relu(x)
            if idx in VGG16_TAPS:
                taps.append(x)
        return taps

    def __call__(self, img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
        """Mean LPIPS over the batch for images in [0, 1] ([H,W,3] or [B,3,H,W]); differentiable."""
        if img1.shape != img2.shape:
            raise ValueError(f"lpips: shapes differ: {tuple(img1.shape)} vs {tuple(img2.shape)}")
        a, b = channels_first(img1).float(), channels_first(img2).float()
        shift = torch.tensor(LPIPS_SHIFT, device=a.device).view(1, 3, 1, 1)
        scale = torch.tensor(LPIPS_SCALE, device=a.device).view(1, 3, 1, 1)
        fa = self._features(((2 * a - 1) - shift) / scale)
        fb = self._features(((2 * b - 1) - shift) / scale)
        total = 0.0
        for xa, xb, w in zip(fa, fb, self.lins):
            # unit-normalise each feature vector along channels (lpips.normalize_tensor, eps 1e-10)
            na = xa / (torch.sqrt((xa**2).sum(1, keepdim=True)) + 1e-10)
            nb = xb / (torch.sqrt((xb**2).sum(1, keepdim=True)) + 1e-10)
            total = total + F.conv2d((na - nb) ** 2, w).mean(dim=(2, 3))  # [B, 1]
        return total.mean()


def load_lin_weights(path: Path = LPIPS_LIN_FILE) -> list[torch.Tensor]:
    digest = sha256(path)
    if digest != LPIPS_LIN_SHA256:
        raise ValueError(f"{path}: sha256 {digest[:12]}... is not the lpips v0.1 VGG head")
    state = torch.load(path, map_location="cpu", weights_only=True)
    return [state[f"lin{i}.model.1.weight"] for i in range(len(LPIPS_CHANNELS))]


def default_vgg16_path() -> Path:
    return Path(torch.hub.get_dir()) / "checkpoints" / VGG16_FILE


def load_vgg16_trunk(path: Path) -> dict[str, torch.Tensor]:
    """torchvision's ImageNet VGG16 state dict, after checking the sha256 prefix of its file name."""
    digest = sha256(path)
    if not digest.startswith(VGG16_SHA256_PREFIX):
        raise ValueError(f"{path}: sha256 starts {digest[:8]}, expected {VGG16_SHA256_PREFIX} "
                         f"(torchvision's {VGG16_FILE}); refusing another network under the LPIPS name")
    return torch.load(path, map_location="cpu", weights_only=True)


def download_vgg16(dst: Path) -> None:
    """torchvision's download of its ImageNet VGG16 to `dst` (torch.hub's `download_url_to_file` with the
    sha256 prefix from the file name, as `load_state_dict_from_url(..., check_hash=True)` runs it: the file
    lands only once whole and matching). Raises on any failure (offline: `URLError`)."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    previous = socket.getdefaulttimeout()  # urlopen waits forever by default: never hang on a dead network
    socket.setdefaulttimeout(previous or DOWNLOAD_TIMEOUT_S)
    try:
        torch.hub.download_url_to_file(VGG16_URL, str(dst), hash_prefix=VGG16_SHA256_PREFIX, progress=False)
    finally:
        socket.setdefaulttimeout(previous)


def vgg16_weights(vgg16_path: str | Path | None = None, download: bool = True,
                  log: Callable[[str], None] | None = None) -> tuple[Path | None, str | None, str]:
    """(the VGG16 weights file, the URL it was just downloaded from or None, "") or (None, None, one-line
    reason), without loading them: see `load_lpips`."""
    path = Path(vgg16_path) if vgg16_path else default_vgg16_path()
    if vgg16_path and not path.is_file():
        raise ConfigError(f"--vgg16 {path}: no such file (torchvision's {VGG16_FILE})")
    if path.is_file():
        return path, None, ""
    missing = f"VGG16 ImageNet weights not found at {path}"
    if not download:
        return None, None, f"{missing} (download off; give --vgg16 PATH to {VGG16_FILE})"
    if log is not None:
        log(f"LPIPS: downloading {VGG16_URL} (528 MB) to {path}")
    try:
        download_vgg16(path)
    except Exception as err:  # noqa: BLE001 (network, disk, checksum: any failure means n/a, no crash)
        detail = (str(err).splitlines() or [""])[0] or type(err).__name__
        return (None, None,
                f"{missing}; downloading {VGG16_URL} failed: {detail} (give --vgg16 PATH to {VGG16_FILE})")
    if not path.is_file():
        return None, None, f"{missing}; downloading {VGG16_URL} left no file there"
    return path, VGG16_URL, ""


def load_lpips(vgg16_path: str | Path | None = None, download: bool = True,
               log: Callable[[str], None] | None = None) -> tuple[LPIPS | None, str]:
    """(metric, "") or (None, one-line reason); `metric.network` records the network and files used.

    `vgg16_path` defaults to torch's hub cache (`<hub dir>/checkpoints/vgg16-397923af.pth`); when the cache
    lacks the file and `download` is true, it is downloaded there from `VGG16_URL` (`log` gets a line before
    the download starts); a download failure makes LPIPS unavailable, with the reason. A path given
    explicitly must exist (ConfigError) and is never downloaded to.
    """
    path, downloaded_from, reason = vgg16_weights(vgg16_path, download, log)
    if path is None:
        return None, reason
    try:
        network = {"net": VGG16_NET, "lin": f"{LPIPS_LIN} ({LPIPS_LIN_FILE.name})", "source": str(path),
                   "downloaded_from": downloaded_from}
        return LPIPS(load_vgg16_trunk(path), load_lin_weights(), network), ""
    except (ValueError, RuntimeError, KeyError, OSError) as err:
        return None, str(err).splitlines()[0]


# scikit-image's window rule for gaussian_weights=True: truncate 3.5 sigma, radius int(3.5 * 1.5 + 0.5) = 5
STANDARD_RADIUS = int(3.5 * SIGMA + 0.5)
STANDARD_WINDOW = 2 * STANDARD_RADIUS + 1  # 11


def ssim_standard(img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
    """The standard mean SSIM (scalar float64 tensor, differentiable) of two images [H,W,3] or [B,3,H,W] in
    [0, 1]: scikit-image's `structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=1.0, channel_axis=-1)` and torchmetrics' SSIM with
    `data_range=1.0`. Only the windows wholly inside the image count (the map is cropped by 5 pixels on
    every side); mean over pixels, channels, and for a batch over the images. Computed in float64.
    """
    if img1.shape != img2.shape:
        raise ValueError(f"ssim_standard: shapes differ: {tuple(img1.shape)} vs {tuple(img2.shape)}")
    a, b = channels_first(img1).double(), channels_first(img2).double()
    if min(a.shape[-2:]) < STANDARD_WINDOW:
        raise ValueError(f"ssim_standard: the image ({a.shape[-2]} x {a.shape[-1]}) is smaller than the "
                         f"{STANDARD_WINDOW}-pixel window")
    ch = a.shape[1]
    x = torch.cat([a, b, a * a, b * b, a * b], dim=1)  # the five local moments in one pass
    g = gaussian_window(STANDARD_WINDOW, SIGMA, dtype=x.dtype, device=x.device)
    c = x.shape[1]
    # no padding: the "valid" map is exactly scikit-image's cropped one (its reflect padding never reaches
    # the windows it keeps), and torchmetrics' (reflect-padded, then cropped)
    x = F.conv2d(x, g.view(1, 1, 1, -1).expand(c, 1, 1, STANDARD_WINDOW), groups=c)
    x = F.conv2d(x, g.view(1, 1, -1, 1).expand(c, 1, STANDARD_WINDOW, 1), groups=c)
    mu1, mu2, e11, e22, e12 = x.split(ch, dim=1)
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    var1, var2, cov = e11 - mu1_sq, e22 - mu2_sq, e12 - mu12
    s = ((2 * mu12 + C1) * (2 * cov + C2)) / ((mu1_sq + mu2_sq + C1) * (var1 + var2 + C2))
    return s.mean()
