"""Low-level StyleGAN2 operations, in plain PyTorch (no compiled extensions).

FIR up/down-sampling (``upfirdn2d``), convolution with resampling, bias + activation with gain and
clamp, and modulated convolution, with the same arithmetic as the released generators so that
their checkpoints reproduce within float32 rounding. Tensors are NCHW, float32 or (in the blocks the
originals run in half precision on CUDA) float16; float16 follows the originals' fp16 arithmetic:
weights and styles are pre-normalized before a demodulated convolution, and bias + activation are
computed in float32 and stored in float16, as their fused CUDA kernel does.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

# Activation -> (function, default gain)
ACTIVATIONS = {
    "linear": (lambda x: x, 1.0),
    "relu": (F.relu, math.sqrt(2)),
    "lrelu": (lambda x: F.leaky_relu(x, 0.2), math.sqrt(2)),
    "softplus": (F.softplus, 1.0),
    "sigmoid": (torch.sigmoid, 1.0),
}


# In-place forms (for tensors the caller owns); gradients flow through them as through the others.
INPLACE_ACTIVATIONS = {
    "linear": lambda x: x,
    "relu": F.relu_,
    "lrelu": lambda x: F.leaky_relu_(x, 0.2),
}


def default_gain(activation: str) -> float:
    return ACTIVATIONS[activation][1]


def bias_act(x, b=None, act="linear", gain=None, clamp=None, dim=1, inplace=False):
    """x + b (broadcast along ``dim``), activation, times gain (default: the activation's), clamp.

    A float16 ``x`` is computed in float32 and returned in float16. ``inplace``: ``x`` may be
    overwritten when there is no bias (with a bias the sum is a new tensor anyway).
    """
    if x.dtype == torch.float16:
        return bias_act(x.float(), None if b is None else b.float(), act, gain, clamp, dim).half()
    fn, g = ACTIVATIONS[act]
    gain = g if gain is None else float(gain)
    if b is not None:
        x = x + b.reshape([-1 if i == dim else 1 for i in range(x.ndim)])
    elif not inplace:
        x = x.clone()
    # From here x is a fresh tensor: the remaining steps overwrite it (same values, no new buffers).
    x = INPLACE_ACTIVATIONS[act](x) if act in INPLACE_ACTIVATIONS else fn(x)
    if gain != 1:
        x = x.mul_(gain)
    if clamp is not None and clamp >= 0:
        x = x.clamp_(-clamp, clamp)
    return x


def normalize_2nd_moment(x, dim=1, eps=1e-8):
    return x * (x.square().mean(dim=dim, keepdim=True) + eps).rsqrt()


def setup_filter(f=(1, 3, 3, 1)) -> torch.Tensor:
    """Normalized 2D FIR filter from 1D taps (outer product)."""
    f = torch.as_tensor(f, dtype=torch.float32)
    f = torch.outer(f, f)
    return f / f.sum()


def upfirdn2d(x, f, up=1, down=1, padding=(0, 0, 0, 0), gain=1.0):
    """Upsample by zero insertion, pad (x0, x1, y0, y1; negative crops), FIR filter, downsample."""
    n, c, h, w = x.shape
    px0, px1, py0, py1 = padding
    if up > 1:
        x = x.reshape(n, c, h, 1, w, 1)
        x = F.pad(x, [0, up - 1, 0, 0, 0, up - 1])
        x = x.reshape(n, c, h * up, w * up)
    x = F.pad(x, [max(px0, 0), max(px1, 0), max(py0, 0), max(py1, 0)])
    x = x[:, :, max(-py0, 0): x.shape[2] - max(-py1, 0), max(-px0, 0): x.shape[3] - max(-px1, 0)]
    f = (f * (gain ** (f.ndim / 2))).to(x.dtype).flip([0, 1])
    x = _conv(x, f[None, None].repeat(c, 1, 1, 1), groups=c)
    return x[:, :, ::down, ::down]


def upsample2d(x, f, up=2):
    fw = f.shape[-1]
    p = ((fw + up - 1) // 2, (fw - up) // 2, (fw + up - 1) // 2, (fw - up) // 2)
    return upfirdn2d(x, f, up=up, padding=p, gain=up * up)


def _conv(x, w, stride=1, padding=0, groups=1, transpose=False, flip_weight=True):
    if x.dtype == torch.float16 and x.device.type == "cpu":
        # A CPU without fp16 arithmetic (AVX2) runs fp16 convolutions on a reference path, minutes
        # for one 512 px layer; sum in fp32 and round to fp16 instead, as CUDA's tensor cores do.
        return _conv(x.float(), w.float(), stride, padding, groups, transpose, flip_weight).half()
    kh, kw = w.shape[2:]
    if not flip_weight and (kw > 1 or kh > 1):
        w = w.flip([2, 3])
    if transpose:
        return F.conv_transpose2d(x, w, stride=stride, padding=padding, groups=groups)
    return F.conv2d(x, w, stride=stride, padding=padding, groups=groups)


def conv2d_resample(x, w, f=None, up=1, padding=0, groups=1, flip_weight=True):
    """2D convolution with optional FIR upsampling (the only cases the generators use)."""
    out_ch, in_per_group, kh, kw = w.shape
    px0 = px1 = py0 = py1 = padding
    if up > 1:
        fw = f.shape[-1]
        px0 += (fw + up - 1) // 2
        px1 += (fw - up) // 2
        py0 += (fw + up - 1) // 2
        py1 += (fw - up) // 2
        if kw == 1 and kh == 1:
            x = _conv(x, w, groups=groups, flip_weight=flip_weight)
            return upfirdn2d(x, f, up=up, padding=(px0, px1, py0, py1), gain=up ** 2)
        if groups == 1:
            w = w.transpose(0, 1)
        else:
            w = w.reshape(groups, out_ch // groups, in_per_group, kh, kw).transpose(1, 2)
            w = w.reshape(groups * in_per_group, out_ch // groups, kh, kw)
        px0 -= kw - 1
        px1 -= kw - up
        py0 -= kh - 1
        py1 -= kh - up
        pxt = max(min(-px0, -px1), 0)
        pyt = max(min(-py0, -py1), 0)
        x = _conv(x, w, stride=up, padding=[pyt, pxt], groups=groups, transpose=True, flip_weight=not flip_weight)
        return upfirdn2d(x, f, padding=(px0 + pxt, px1 + pxt, py0 + pyt, py1 + pyt), gain=up ** 2)
    if px0 >= 0:
        return _conv(x, w, padding=[py0, px0], groups=groups, flip_weight=flip_weight)
    raise ValueError("negative padding is not supported")


def modulated_conv2d(x, weight, styles, noise=None, up=1, padding=0, resample_filter=None, demodulate=True,
                     flip_weight=True, fused_modconv=True):
    """StyleGAN2 modulated convolution; styles (N, in_channels) scale the input channels.

    ``weight`` and ``styles`` are float32; the convolution runs in ``x``'s dtype.
    """
    n = x.shape[0]
    out_ch, in_ch, kh, kw = weight.shape
    if x.dtype == torch.float16 and demodulate:
        # The originals' guard against fp16 overflow; demodulation cancels both scales.
        weight = weight * (1 / math.sqrt(in_ch * kh * kw) / weight.norm(float("inf"), dim=[1, 2, 3], keepdim=True))
        styles = styles / styles.norm(float("inf"), dim=1, keepdim=True)
    w = None
    dcoefs = None
    if demodulate or fused_modconv:
        w = weight.unsqueeze(0) * styles.reshape(n, 1, -1, 1, 1)
    if demodulate:
        dcoefs = (w.square().sum(dim=[2, 3, 4]) + 1e-8).rsqrt()
    if demodulate and fused_modconv:
        w = w * dcoefs.reshape(n, -1, 1, 1, 1)
    dt = x.dtype
    if noise is not None:
        noise = noise.to(dt)
    if not fused_modconv:
        x = x * styles.to(dt).reshape(n, -1, 1, 1)
        x = conv2d_resample(x, weight.to(dt), f=resample_filter, up=up, padding=padding, flip_weight=flip_weight)
        if demodulate and noise is not None:
            return torch.addcmul(noise, x, dcoefs.to(dt).reshape(n, -1, 1, 1))
        if demodulate:
            return x * dcoefs.to(dt).reshape(n, -1, 1, 1)
        if noise is not None:
            return x + noise
        return x
    x = x.reshape(1, -1, *x.shape[2:])
    w = w.reshape(-1, in_ch, kh, kw).to(dt)
    x = conv2d_resample(x, w, f=resample_filter, up=up, padding=padding, groups=n, flip_weight=flip_weight)
    x = x.reshape(n, -1, *x.shape[2:])
    if noise is not None:
        x = x + noise
    return x
