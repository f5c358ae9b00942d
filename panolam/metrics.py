"""Image metrics for evaluation and training: PSNR, SSIM (and the D-SSIM loss) and LPIPS.

Every function takes float tensors laid out (B, C, H, W) with values in [0, 1] (LPIPS needs C = 3)
and returns one value per image, shape (B,), unless said otherwise. Images are compared as given:
composite them on the same background first (the datasets' background, :data:`panolam.data.BACKGROUND`).
PSNR and SSIM are written here in torch, not taken from scikit-image: batched on the model's device,
and SSIM differentiable for the D-SSIM loss; the tests check both against scikit-image's.

SSIM is Wang et al.'s: an 11x11 Gaussian window with sigma 1.5 px, C1 = 0.01^2, C2 = 0.03^2
(data range 1), population (not sample) covariances, averaged over the *valid* region only (the
5 px border, where the window would leave the image, is left out). That equals
``skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1)`` (skimage pads, then crops the same border before the
mean; its default is a 7x7 uniform window) and pytorch-msssim's valid convolution; Inria's 3DGS
``ssim`` zero-pads instead and so differs near the border.

LPIPS is richzhang/PerceptualSimilarity v0.1 (``lpips.LPIPS(net=..., normalize=True)``) rebuilt
here without torchvision: the ImageNet backbone (AlexNet or VGG-16 ``features``, with torchvision's
layer indices so its state-dict keys load as they are), the input scaling layer, unit-normalized
features of five ReLU layers, squared differences weighted by the per-channel "lin" 1x1 convs and
averaged over space, summed over layers. The weights are read from local files only
(``load_lpips``).
"""
from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from datagen.errors import UserError

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2
PSNR_MAX_DB = 100.0  # returned for identical images (MSE below 1e-10)

# torchvision's `features` of each backbone: ("conv", in, out, kernel, stride, padding), "relu" or
# ("pool", kernel, stride), in index order; LPIPS taps the outputs of the ReLUs at TAPS.
_ALEX = [("conv", 3, 64, 11, 4, 2), "relu", ("pool", 3, 2), ("conv", 64, 192, 5, 1, 2), "relu",
         ("pool", 3, 2), ("conv", 192, 384, 3, 1, 1), "relu", ("conv", 384, 256, 3, 1, 1), "relu",
         ("conv", 256, 256, 3, 1, 1), "relu"]


def _vgg16() -> list:
    layers = []
    for stage, (cin, cout, n) in enumerate([(3, 64, 2), (64, 128, 2), (128, 256, 3), (256, 512, 3), (512, 512, 3)]):
        if stage:
            layers.append(("pool", 2, 2))
        for i in range(n):
            layers += [("conv", cin if i == 0 else cout, cout, 3, 1, 1), "relu"]
    return layers


ARCHS = {"alex": _ALEX, "vgg": _vgg16()}
TAPS = {"alex": (1, 4, 7, 9, 11), "vgg": (3, 8, 15, 22, 29)}
BACKBONE_FILES = {"alex": "alexnet-owt-7be5be79.pth", "vgg": "vgg16-397923af.pth"}
_SHIFT = (-0.030, -0.088, -0.188)  # LPIPS ScalingLayer, applied to inputs in [-1, 1]
_SCALE = (0.458, 0.448, 0.450)


class MetricError(UserError, RuntimeError):
    """A metric cannot be computed as asked (missing or mismatched weight files)."""


def _check_pair(pred: torch.Tensor, target: torch.Tensor) -> None:
    if pred.shape != target.shape or pred.dim() != 4:
        raise ValueError(f"expected two (B, C, H, W) tensors of one shape, "
                         f"got {tuple(pred.shape)} and {tuple(target.shape)}")


def psnr(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """PSNR in dB of images in [0, 1], shape (B,), capped at PSNR_MAX_DB.

    mask: optional (B, 1, H, W) or (B, H, W) weights (bool or float); the MSE is then averaged over
    the masked pixels (and all channels) only. An image whose mask is empty gets nan.
    """
    _check_pair(pred, target)
    err = (pred - target).square()
    mse = err.mean(dim=(1, 2, 3)) if mask is None else _masked_mean(err, mask)
    return -10.0 * torch.log10(mse.clamp_min(10.0 ** (-PSNR_MAX_DB / 10)))


def _gaussian_window(channels: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    x = torch.arange(SSIM_WINDOW, dtype=dtype, device=device) - SSIM_WINDOW // 2
    g = torch.exp(-0.5 * (x / SSIM_SIGMA) ** 2)
    g = g / g.sum()
    return (g[:, None] * g[None, :]).expand(channels, 1, SSIM_WINDOW, SSIM_WINDOW)


def _weights(mask: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """A (B, 1, H, W) or (B, H, W) mask as float weights broadcast to ``like`` (B, C, H, W)."""
    return (mask if mask.dim() == 4 else mask.unsqueeze(1)).to(like.dtype).expand_as(like)


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``values`` (B, C, H, W) per image, weighted by ``mask``; nan where the mask is empty."""
    m = _weights(mask, values)
    total = m.sum(dim=(1, 2, 3))
    mean = (values * m).sum(dim=(1, 2, 3)) / total.clamp_min(1e-12)
    return torch.where(total > 0, mean, torch.full_like(mean, math.nan))


def ssim(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """SSIM of images in [0, 1], shape (B,); differentiable. Needs H, W >= 11 (see module docstring).

    mask: optional (B, 1, H, W) or (B, H, W) weights; the SSIM map (valid region) is then averaged
    over the masked pixels only (the mask is cropped like the map). An empty mask gives nan.
    """
    _check_pair(pred, target)
    b, c, h, w = pred.shape
    if min(h, w) < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} px, got {h}x{w}")
    win = _gaussian_window(c, pred.dtype, pred.device)
    stats = F.conv2d(torch.cat([pred, target, pred * pred, target * target, pred * target], dim=1),
                     win.repeat(5, 1, 1, 1), groups=5 * c)
    mu_x, mu_y, xx, yy, xy = stats.split(c, dim=1)
    var_x, var_y, cov = xx - mu_x ** 2, yy - mu_y ** 2, xy - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * cov + SSIM_C2)
    den = (mu_x ** 2 + mu_y ** 2 + SSIM_C1) * (var_x + var_y + SSIM_C2)
    value = num / den
    if mask is None:
        return value.mean(dim=(1, 2, 3))
    r = SSIM_WINDOW // 2
    m = mask if mask.dim() == 4 else mask.unsqueeze(1)
    return _masked_mean(value, m[..., r:h - r, r:w - r])


def dssim_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """D-SSIM training loss ``(1 - ssim) / 2``, averaged over the batch (a scalar in [0, 1])."""
    return ((1 - ssim(pred, target)) / 2).mean()


def _backbone(net: str) -> nn.Sequential:
    layers = []
    for spec in ARCHS[net]:
        if spec == "relu":
            layers.append(nn.ReLU())
        elif spec[0] == "pool":
            layers.append(nn.MaxPool2d(spec[1], spec[2]))
        else:
            layers.append(nn.Conv2d(*spec[1:]))
    return nn.Sequential(*layers)


class LPIPS(nn.Module):
    """LPIPS v0.1 distance (``net`` 'alex' or 'vgg'); ``forward(pred, target)`` on [0, 1] images -> (B,).

    Built with random weights: use ``load_lpips`` for the real ones. Weights are frozen; gradients
    reach the inputs.
    """

    def __init__(self, net: str = "alex"):
        super().__init__()
        if net not in ARCHS:
            raise ValueError(f"LPIPS net must be one of {sorted(ARCHS)}, got {net!r}")
        self.net = net
        self.features = _backbone(net)
        channels = [self.features[i - 1].out_channels for i in TAPS[net]]
        self.lins = nn.ModuleList(nn.Conv2d(ch, 1, 1, bias=False) for ch in channels)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = (2 * x - 1 - self.shift) / self.scale
        out, taps = [], set(TAPS[self.net])
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in taps:
                out.append(x / (x.square().sum(dim=1, keepdim=True).sqrt() + 1e-10))
        return out

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        _check_pair(pred, target)
        if pred.shape[1] != 3:
            raise ValueError(f"LPIPS needs RGB images (B, 3, H, W), got {tuple(pred.shape)}")
        total = 0
        for lin, f0, f1 in zip(self.lins, self._taps(pred), self._taps(target)):
            total = total + lin((f0 - f1).square()).mean(dim=(1, 2, 3))
        return total


def _where_from(net: str) -> str:
    return (f"the backbone is torchvision's ImageNet {BACKBONE_FILES[net]} (the file torchvision's "
            f"{'AlexNet' if net == 'alex' else 'VGG16'}_Weights.IMAGENET1K_V1 downloads); the lin weights are "
            f"lpips/weights/v0.1/{net}.pth of richzhang/PerceptualSimilarity (also inside the `lpips` "
            f"package from PyPI)")


def _read_state(path, what: str, net: str) -> dict:
    if path is None:
        raise MetricError(f"LPIPS needs {what} weights too: {_where_from(net)}")
    path = Path(path)
    if not path.is_file():
        raise MetricError(f"LPIPS {what} weights not found at {path}: {_where_from(net)}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many kinds for a corrupt or foreign file
        raise MetricError(f"cannot read LPIPS {what} weights {path} ({type(e).__name__}: {e}); "
                          f"{_where_from(net)}") from None
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise MetricError(f"{path} is not a state dict of tensors; {_where_from(net)}")
    return state


def _copy_into(module: nn.Module, state: dict, rename, path, net: str) -> None:
    for key, param in module.state_dict().items():
        src = rename(key)
        if src not in state:
            raise MetricError(f"{path} has no {src!r}: not the {net} weights? {_where_from(net)}")
        if state[src].shape != param.shape:
            raise MetricError(f"{path}: {src!r} has shape {tuple(state[src].shape)}, LPIPS-{net} needs "
                              f"{tuple(param.shape)}: not the {net} weights? {_where_from(net)}")
        param.copy_(state[src])


@torch.no_grad()
def load_lpips(backbone_path, lin_path, net: str = "alex") -> LPIPS:
    """LPIPS with the backbone (torchvision ``features.N.*`` keys) and lin (``linK.model.1.weight``)
    weights read from local files; raises MetricError when a file is missing or does not fit."""
    model = LPIPS(net)
    _copy_into(model.features, _read_state(backbone_path, "backbone", net),
               lambda k: f"features.{k}", backbone_path, net)
    _copy_into(model.lins, _read_state(lin_path, "lin", net),
               lambda k: f"lin{k.split('.')[0]}.model.1.weight", lin_path, net)
    return model
