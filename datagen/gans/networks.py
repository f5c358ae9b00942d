"""StyleGAN2 networks as the 3D-GAN generators use them (mapping, synthesis, super-resolution).

Parameter names and shapes match the released EG3D / PanoHead / SphereHead state dicts. Weights are
stored unscaled and the equalized-learning-rate gains are applied at run time (FC: lr_mul/sqrt(in),
bias * lr_mul; conv: 1/sqrt(in*k*k); ToRGB styles: 1/sqrt(in)), as in the originals.
Noise modes: 'const' (stored noise * strength), 'none', or 'random' (drawn from a CPU torch.Generator).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from .ops import bias_act, conv2d_resample, default_gain, modulated_conv2d, normalize_2nd_moment, setup_filter, \
    upsample2d


class FullyConnectedLayer(nn.Module):
    def __init__(self, in_features, out_features, bias=True, activation="linear", lr_multiplier=1.0, bias_init=0.0):
        super().__init__()
        self.in_features, self.out_features = in_features, out_features
        self.activation = activation
        self.weight = nn.Parameter(torch.randn([out_features, in_features]) / lr_multiplier)
        self.bias = nn.Parameter(torch.full([out_features], float(bias_init))) if bias else None
        self.weight_gain = lr_multiplier / math.sqrt(in_features)
        self.bias_gain = lr_multiplier

    def forward(self, x):
        w = self.weight * self.weight_gain
        b = self.bias
        if b is not None and self.bias_gain != 1:
            b = b * self.bias_gain
        if self.activation == "linear" and b is not None:
            return torch.addmm(b.unsqueeze(0), x, w.t())
        return bias_act(x.matmul(w.t()), b, act=self.activation)


class MappingNetwork(nn.Module):
    """z (+ embedded c) -> w, broadcast to num_ws copies, with truncation toward ``w_avg``."""

    def __init__(self, z_dim, c_dim, w_dim, num_ws, num_layers=8, embed_features=None, layer_features=None,
                 activation="lrelu", lr_multiplier=0.01, last_activation=None):
        super().__init__()
        self.z_dim, self.c_dim, self.w_dim, self.num_ws, self.num_layers = z_dim, c_dim, w_dim, num_ws, num_layers
        embed_features = w_dim if embed_features is None else embed_features
        if c_dim == 0:
            embed_features = 0
        layer_features = w_dim if layer_features is None else layer_features
        features = [z_dim + embed_features] + [layer_features] * (num_layers - 1) + [w_dim]
        if c_dim > 0:
            self.embed = FullyConnectedLayer(c_dim, embed_features)
        for i in range(num_layers):
            act = last_activation if (i == num_layers - 1 and last_activation) else activation
            setattr(self, f"fc{i}", FullyConnectedLayer(features[i], features[i + 1], activation=act,
                                                        lr_multiplier=lr_multiplier))
        self.register_buffer("w_avg", torch.zeros([w_dim]))

    def forward(self, z, c, truncation_psi=1.0, truncation_cutoff=None):
        x = None
        if self.z_dim > 0:
            x = normalize_2nd_moment(z.to(torch.float32))
        if self.c_dim > 0:
            y = normalize_2nd_moment(self.embed(c.to(torch.float32)))
            x = torch.cat([x, y], dim=1) if x is not None else y
        for i in range(self.num_layers):
            x = getattr(self, f"fc{i}")(x)
        x = x.unsqueeze(1).repeat([1, self.num_ws, 1])
        if truncation_psi != 1:
            if truncation_cutoff is None:
                x = self.w_avg.lerp(x, truncation_psi)
            else:
                x[:, :truncation_cutoff] = self.w_avg.lerp(x[:, :truncation_cutoff], truncation_psi)
        return x


class Conv2dLayer(nn.Module):
    """Plain equalized-lr convolution (SphereHead's ConvA/ConvB use it as 1x1 projections)."""

    def __init__(self, in_channels, out_channels, kernel_size, bias=True, activation="linear", conv_clamp=None):
        super().__init__()
        self.activation, self.conv_clamp = activation, conv_clamp
        self.register_buffer("resample_filter", setup_filter())
        self.padding = kernel_size // 2
        self.weight_gain = 1 / math.sqrt(in_channels * kernel_size ** 2)
        self.act_gain = default_gain(activation)
        self.weight = nn.Parameter(torch.randn([out_channels, in_channels, kernel_size, kernel_size]))
        self.bias = nn.Parameter(torch.zeros([out_channels])) if bias else None

    def forward(self, x):
        x = conv2d_resample(x, self.weight * self.weight_gain, f=self.resample_filter, padding=self.padding)
        return bias_act(x, self.bias, act=self.activation, gain=self.act_gain, clamp=self.conv_clamp)


def _noise(layer, x, noise_mode, generator):
    if not layer.use_noise or noise_mode == "none":
        return None
    if noise_mode == "const":
        return layer.noise_const * layer.noise_strength
    if noise_mode == "random":
        shape = [x.shape[0], 1, layer.resolution, layer.resolution]
        # drawn on the CPU from the subject's generator, so the noise does not depend on the device
        return torch.randn(shape, generator=generator).to(x.device) * layer.noise_strength
    raise ValueError(f"unknown noise mode {noise_mode!r}")


class SynthesisLayer(nn.Module):
    def __init__(self, in_channels, out_channels, w_dim, resolution, kernel_size=3, up=1, use_noise=True,
                 activation="lrelu", conv_clamp=None):
        super().__init__()
        self.resolution, self.up, self.use_noise, self.activation = resolution, up, use_noise, activation
        self.conv_clamp = conv_clamp
        self.register_buffer("resample_filter", setup_filter())
        self.padding = kernel_size // 2
        self.act_gain = default_gain(activation)
        self.affine = FullyConnectedLayer(w_dim, in_channels, bias_init=1)
        self.weight = nn.Parameter(torch.randn([out_channels, in_channels, kernel_size, kernel_size]))
        if use_noise:
            self.register_buffer("noise_const", torch.randn([resolution, resolution]))
            self.noise_strength = nn.Parameter(torch.zeros([]))
        self.bias = nn.Parameter(torch.zeros([out_channels]))

    def forward(self, x, w, noise_mode="const", fused_modconv=True, generator=None):
        styles = self.affine(w)
        x = modulated_conv2d(x, self.weight, styles, noise=_noise(self, x, noise_mode, generator), up=self.up,
                             padding=self.padding, resample_filter=self.resample_filter, flip_weight=(self.up == 1),
                             fused_modconv=fused_modconv)
        return bias_act(x, self.bias, act=self.activation, gain=self.act_gain, clamp=self.conv_clamp)


class ToRGBLayer(nn.Module):
    def __init__(self, in_channels, out_channels, w_dim, kernel_size=1, conv_clamp=None):
        super().__init__()
        self.conv_clamp = conv_clamp
        self.affine = FullyConnectedLayer(w_dim, in_channels, bias_init=1)
        self.weight = nn.Parameter(torch.randn([out_channels, in_channels, kernel_size, kernel_size]))
        self.bias = nn.Parameter(torch.zeros([out_channels]))
        self.weight_gain = 1 / math.sqrt(in_channels * kernel_size ** 2)

    def forward(self, x, w, fused_modconv=True):
        styles = self.affine(w) * self.weight_gain
        x = modulated_conv2d(x, self.weight, styles, demodulate=False, fused_modconv=fused_modconv)
        return bias_act(x, self.bias, clamp=self.conv_clamp)


class SynthesisBlock(nn.Module):
    """Two modulated convs (the first upsamples 2x unless ``upsample=False``) and a skip ToRGB.

    ``use_fp16``: the block runs in float16 when its caller allows it (``fp16=True``; the originals
    do so on CUDA only); the image skip path stays float32. Without upsampling (the originals'
    ``SynthesisBlockNoUp``) the ToRGB output is added to ``img`` in place, as there, so a caller's
    ``image_raw`` (and, for EG3D, the feature image it is a view of) changes with it.
    """

    def __init__(self, in_channels, out_channels, w_dim, resolution, img_channels, is_last, conv_clamp=None,
                 upsample=True, use_fp16=False):
        super().__init__()
        self.in_channels, self.upsample, self.use_fp16 = in_channels, upsample, use_fp16
        self.register_buffer("resample_filter", setup_filter())
        self.num_conv = 0
        if in_channels == 0:
            self.const = nn.Parameter(torch.randn([out_channels, resolution, resolution]))
        else:
            self.conv0 = SynthesisLayer(in_channels, out_channels, w_dim, resolution, up=2 if upsample else 1,
                                        conv_clamp=conv_clamp)
            self.num_conv += 1
        self.conv1 = SynthesisLayer(out_channels, out_channels, w_dim, resolution, conv_clamp=conv_clamp)
        self.num_conv += 1
        self.torgb = ToRGBLayer(out_channels, img_channels, w_dim, conv_clamp=conv_clamp)
        self.num_torgb = 1

    def forward(self, x, img, ws, noise_mode="const", fused_modconv=True, generator=None, fp16=False):
        w_iter = iter(ws.unbind(dim=1))
        kw = dict(noise_mode=noise_mode, fused_modconv=fused_modconv, generator=generator)
        dtype = torch.float16 if (self.use_fp16 and fp16) else torch.float32
        if self.in_channels == 0:
            x = self.const.to(dtype).unsqueeze(0).repeat([ws.shape[0], 1, 1, 1])
            x = self.conv1(x, next(w_iter), **kw)
        else:
            x = self.conv0(x.to(dtype), next(w_iter), **kw)
            x = self.conv1(x, next(w_iter), **kw)
        y = self.torgb(x, next(w_iter), fused_modconv=fused_modconv).float()
        if img is None:
            return x, y
        if self.upsample:
            return x, upsample2d(img, self.resample_filter) + y
        return x, img.add_(y)


class SynthesisNetwork(nn.Module):
    """Skip-architecture StyleGAN2 synthesis from 4x4 to ``img_resolution``.

    The top ``num_fp16_res`` resolutions (at least 8x8) are the blocks the originals run in float16.
    """

    def __init__(self, w_dim, img_resolution, img_channels, channel_base=32768, channel_max=512, conv_clamp=None,
                 num_fp16_res=0, **_ignored):
        super().__init__()
        self.w_dim, self.img_resolution, self.img_channels = w_dim, img_resolution, img_channels
        log2 = int(math.log2(img_resolution))
        self.block_resolutions = [2 ** i for i in range(2, log2 + 1)]
        channels = {r: min(channel_base // r, channel_max) for r in self.block_resolutions}
        fp16_resolution = max(2 ** (log2 + 1 - num_fp16_res), 8)
        self.num_ws = 0
        for res in self.block_resolutions:
            in_ch = channels[res // 2] if res > 4 else 0
            block = SynthesisBlock(in_ch, channels[res], w_dim, res, img_channels, res == img_resolution, conv_clamp,
                                   use_fp16=res >= fp16_resolution)
            self.num_ws += block.num_conv
            setattr(self, f"b{res}", block)
        self.num_ws += 1  # the last ToRGB

    def forward(self, ws, noise_mode="const", fused_modconv=True, generator=None, fp16=False):
        ws = ws.to(torch.float32)
        x = img = None
        w_idx = 0
        for res in self.block_resolutions:
            block = getattr(self, f"b{res}")
            cur = ws.narrow(1, w_idx, block.num_conv + block.num_torgb)
            w_idx += block.num_conv
            x, img = block(x, img, cur, noise_mode=noise_mode, fused_modconv=fused_modconv, generator=generator,
                           fp16=fp16)
        return img


class StyleGAN2Backbone(nn.Module):
    """Mapping + synthesis; the 3D GANs use its output image as plane features."""

    def __init__(self, z_dim, c_dim, w_dim, img_resolution, img_channels, mapping_kwargs=None, **synthesis_kwargs):
        super().__init__()
        self.synthesis = SynthesisNetwork(w_dim, img_resolution, img_channels, **synthesis_kwargs)
        self.num_ws = self.synthesis.num_ws
        self.mapping = MappingNetwork(z_dim, c_dim, w_dim, self.num_ws, **(mapping_kwargs or {}))


@dataclass(frozen=True)
class SRVariant:
    """One of the originals' super-resolution classes (EG3D's ``training/superresolution.py``).

    block0 upsamples 2x except in the NoUp variants; ``filter_buffer``: the module registers its
    own ``resample_filter`` (all but 8XDC); ``resize_if``: the input is resized to
    ``input_resolution`` when its size differs ('!=') or only when it is smaller ('<');
    ``antialias``: that resize honours ``sr_antialias`` (the deep fp32 variant never antialiases).
    """

    input_resolution: int
    output_resolution: int
    channels: tuple
    block0_upsamples: bool
    filter_buffer: bool = True
    resize_if: str = "!="
    antialias: bool = True


SUPERRESOLUTION = {
    "SuperresolutionHybrid2X": SRVariant(64, 128, (128, 64), False),
    "SuperresolutionHybrid4X": SRVariant(128, 256, (128, 64), False, resize_if="<"),
    "SuperresolutionHybrid8X": SRVariant(128, 512, (128, 64), True),
    "SuperresolutionHybrid8XDC": SRVariant(128, 512, (256, 128), True, filter_buffer=False),
    "SuperresolutionHybridDeepfp32": SRVariant(128, 256, (128, 64), False, resize_if="<", antialias=False),
}


class Superresolution(nn.Module):
    """EG3D's hybrid super-resolution: resize the neural render, then two synthesis blocks.

    Both blocks use ``ws[:, -1]`` three times. With ``sr_num_fp16_res > 0`` the blocks are the
    originals' fp16 blocks: ``conv_clamp`` 256 always (in float32 too), float16 arithmetic only
    when the caller passes ``fp16=True``.
    """

    def __init__(self, kind, channels, img_resolution, sr_num_fp16_res=0, sr_antialias=True, **_ignored):
        super().__init__()
        if kind not in SUPERRESOLUTION:
            raise ValueError(f"unknown superresolution module {kind!r}")
        v = SUPERRESOLUTION[kind]
        if img_resolution != v.output_resolution:
            raise ValueError(f"{kind} makes {v.output_resolution}x{v.output_resolution} images, not {img_resolution}")
        self.variant = v
        self.input_resolution, self.sr_antialias = v.input_resolution, sr_antialias and v.antialias
        use_fp16 = sr_num_fp16_res > 0
        clamp = 256 if use_fp16 else None
        ch0, ch1 = v.channels
        res0 = v.input_resolution * 2 if v.block0_upsamples else v.input_resolution
        self.block0 = SynthesisBlock(channels, ch0, 512, res0, 3, False, clamp, upsample=v.block0_upsamples,
                                     use_fp16=use_fp16)
        self.block1 = SynthesisBlock(ch0, ch1, 512, v.output_resolution, 3, True, clamp, use_fp16=use_fp16)
        if v.filter_buffer:
            self.register_buffer("resample_filter", setup_filter())

    def forward(self, rgb, x, ws, noise_mode="none", fused_modconv=True, generator=None, fp16=False):
        ws = ws[:, -1:, :].repeat(1, 3, 1)
        size = x.shape[-1]
        if size < self.input_resolution or (size != self.input_resolution and self.variant.resize_if == "!="):
            size = (self.input_resolution, self.input_resolution)
            x = torch.nn.functional.interpolate(x, size=size, mode="bilinear", align_corners=False,
                                                antialias=self.sr_antialias)
            rgb = torch.nn.functional.interpolate(rgb, size=size, mode="bilinear", align_corners=False,
                                                  antialias=self.sr_antialias)
        kw = dict(noise_mode=noise_mode, fused_modconv=fused_modconv, generator=generator, fp16=fp16)
        x, rgb = self.block0(x, rgb, ws, **kw)
        x, rgb = self.block1(x, rgb, ws, **kw)
        return rgb
