"""EG3D, PanoHead and SphereHead tri-plane generators on the project's volume renderer.

What differs between them is read from their rows of :data:`datagen.gans.kinds.GAN_KINDS`. Three
plane layouts (``PLANE_SAMPLERS``) turn the StyleGAN2 backbone's output into features at a 3D
point p (world units, scaled by 2/box_warp into the [-1, 1] cube):

* ``triplane`` (EG3D): 3 planes of 32 channels sampled at (x, y), (x, z) and (z, x). The third
  projection is a known quirk of the released code; its checkpoints were trained with it, so we keep it.
* ``trigrid`` (PanoHead): a tri-grid, 3 planes of 32 channels x D depth slices, sampled in 3D at
  (x, y, z), (x, z, y) and (y, z, x); channel index c*D + d.
* ``spheres`` (SphereHead): two spherical tri-planes A and B (backbone 512 ch -> ConvA / ConvB, 1x1
  convs -> D=3 planes x 32 ch each, depth-major). A samples Ry(pi/2) p (seam at the back), B samples
  Ry(-pi/2) Rz(-pi/2) p (seam at the face); each in spherical coordinates (theta, phi, r) on planes
  (theta, phi), (theta, r), (phi, r); blended by w = (1+cos(pi theta))/2 * (1+cos(pi phi))/2.

The decoder averages the three planes' features. PanoHead and SphereHead zero the density outside
|x|, |z| <= box/2 - 0.1 (``triplane_crop``), composite a generated background behind the render and
turn the feature image into RGB with a ToRGB layer; EG3D takes the first three feature channels.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from ..device import constant
from ..render import RenderSettings, render_rays
from .kinds import GAN_KINDS, GANKind, gan_kind
from .networks import (Conv2dLayer, FullyConnectedLayer, MappingNetwork, StyleGAN2Backbone, Superresolution,
                       SynthesisNetwork, ToRGBLayer)

TRIPLANE_CROP = 0.1


class OSGDecoder(nn.Module):
    """Mean of the per-plane features -> FC -> softplus -> FC -> (density, 32 features)."""

    def __init__(self, n_features, lr_multiplier=1.0, activation="sigmoid", hidden=64, out_features=32):
        super().__init__()
        self.activation = activation
        self.net = nn.Sequential(FullyConnectedLayer(n_features, hidden, lr_multiplier=lr_multiplier), nn.Softplus(),
                                 FullyConnectedLayer(hidden, 1 + out_features, lr_multiplier=lr_multiplier))

    def forward(self, plane_features):
        x = plane_features.mean(1)
        n, m, c = x.shape
        x = self.net(x.view(n * m, c)).view(n, m, -1)
        rgb, sigma = x[..., 1:], x[..., 0:1]
        if self.activation == "sigmoid":
            rgb = torch.sigmoid(rgb) * (1 + 2 * 0.001) - 0.001
        elif self.activation == "lrelu":
            rgb = torch.nn.functional.leaky_relu(rgb, 0.2) * math.sqrt(2)
        return rgb, sigma


def _rot_y(a):
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def _rot_z(a):
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


# SphereHead's row-vector rotations (p @ R) of spheres A and B, (2, 3, 3) rounded to float32 as in the
# originals; nested tuples, so that :func:`constant` makes them once per device.
SPHERE_ROTATIONS = tuple(tuple(map(tuple, r)) for r in np.stack(
    [_rot_y(np.pi / 2.0).T, (_rot_y(-np.pi / 2) @ _rot_z(-np.pi / 2.0)).T]).astype(np.float32).tolist())


def _spherical(p):
    """(theta, phi, r) in [-1, 1] of points (N, M, 3) in the [-1, 1] cube.

    On the polar axis and at the centre the angles are undefined; there the values equal the
    originals' (atan2(0, 0) = 0) and the gradients are finite instead of NaN.
    """
    x, y, z = p.unbind(-1)
    rho2, r2 = x * x + y * y, (p ** 2).sum(dim=-1)
    r = _safe_sqrt(r2) / math.sqrt(3)
    r = 2.0 * r - 1.0
    theta = torch.atan2(_safe_sqrt(rho2), torch.where(r2 > 0, z, torch.ones_like(z))) / math.pi
    theta = 2.0 * theta - 1.0
    phi = torch.atan2(y, torch.where(rho2 > 0, x, torch.ones_like(x))) / math.pi
    return theta, phi, r


def _safe_sqrt(x):
    """sqrt with a zero gradient (not inf) at 0."""
    return torch.sqrt(x.clamp_min(1e-30)) * (x > 0)


def _sample_2d(planes, coords):
    """planes (N, P, C, H, W), coords (N*P, M, 2) -> (N, P, M, C); bilinear, zero padding."""
    n, p, c, h, w = planes.shape
    out = torch.nn.functional.grid_sample(planes.reshape(n * p, c, h, w), coords.unsqueeze(1), mode="bilinear",
                                          padding_mode="zeros", align_corners=False)
    return out.permute(0, 3, 2, 1).reshape(n, p, -1, c)


def _sample_sphere(planes, p):
    """One spherical tri-plane (N, 3, C, H, W) at points p (N, M, 3) -> features (N, 3, M, C), weights."""
    theta, phi, r = _spherical(p)
    n, m = theta.shape
    w = ((1.0 + torch.cos(torch.pi * theta)) / 2.0) * ((1.0 + torch.cos(torch.pi * phi)) / 2.0)
    w = w.view(n, 1, m, 1)
    coords = torch.stack([torch.stack([theta, phi], -1), torch.stack([theta, r], -1), torch.stack([phi, r], -1)], 1)
    return _sample_2d(planes, coords.reshape(n * 3, m, 2)), w


def _sample_triplane(planes, p, depth):
    """EG3D's planes (N, 3, C, H, W) at points p (N, M, 3) in the [-1, 1] cube -> (N, 3, M, C)."""
    x, y, z = p.unbind(-1)
    n, m = x.shape
    coords = torch.stack([torch.stack([x, y], -1), torch.stack([x, z], -1), torch.stack([z, x], -1)], 1)
    return _sample_2d(planes, coords.reshape(n * 3, m, 2))


def _sample_trigrid(planes, p, depth):
    """PanoHead's tri-grid (N, 3, C*D, H, W) at points p (N, M, 3) -> (N, 3, M, C); trilinear."""
    x, y, z = p.unbind(-1)
    n, m = x.shape
    c = planes.shape[2] // depth
    grid = planes.reshape(n * 3, c, depth, planes.shape[-2], planes.shape[-1])
    coords = torch.stack([torch.stack([x, y, z], -1), torch.stack([x, z, y], -1), torch.stack([y, z, x], -1)], 1)
    out = torch.nn.functional.grid_sample(grid, coords.reshape(n * 3, 1, 1, m, 3), mode="bilinear",
                                          padding_mode="zeros", align_corners=False)
    return out.permute(0, 4, 3, 2, 1).reshape(n, 3, m, c)


def _sample_spheres(planes, p, depth):
    """SphereHead's spheres (N, 2, 3, C, H, W) at points p (N, M, 3) -> (N, 3, M, C), blended."""
    rot_a, rot_b = constant(SPHERE_ROTATIONS, p.device).to(p.dtype)
    fa, wa = _sample_sphere(planes[:, 0], p @ rot_a)
    fb, wb = _sample_sphere(planes[:, 1], p @ rot_b)
    return (fa * wa + fb * wb) / (wa + wb + 1.0e-8)


# plane layout (GANKind.layout) -> its sampler (planes, points in the [-1, 1] cube, depth D)
PLANE_SAMPLERS = {"triplane": _sample_triplane, "trigrid": _sample_trigrid, "spheres": _sample_spheres}


def sample_planes(kind: str, planes: torch.Tensor, points: torch.Tensor, box_warp: float, depth: int = 3):
    """Per-plane features (N, 3, M, 32) at world points (N, M, 3), for a generator ``kind``."""
    sampler = PLANE_SAMPLERS[gan_kind(kind).layout]
    return sampler(planes, (2 / box_warp) * points, depth)


def crop_outside(points: torch.Tensor, box_warp: float) -> torch.Tensor:
    """PanoHead's crop: True where |x| or |z| exceeds box/2 - 0.1 (density is set to -1e3 there)."""
    inside = (points[..., [0, 2]].abs() <= (box_warp / 2 - TRIPLANE_CROP)).all(dim=-1, keepdim=True)
    return ~inside


class TriPlaneGenerator(nn.Module):
    """A generator of ``kind`` (a GAN_KINDS name), built from the constructor kwargs stored in its checkpoint."""

    def __init__(self, kind, z_dim, c_dim, w_dim, img_resolution, img_channels=3, sr_num_fp16_res=0,
                 mapping_kwargs=None, rendering_kwargs=None, sr_kwargs=None, channel_base=32768, channel_max=512,
                 conv_clamp=None, num_fp16_res=0, **_ignored):
        super().__init__()
        spec = gan_kind(kind)
        rk = dict(rendering_kwargs or {})
        self.kind, self.rendering_kwargs = kind, rk
        self.z_dim, self.c_dim, self.w_dim, self.img_resolution = z_dim, c_dim, w_dim, img_resolution
        self.depth = int(rk.get("triplane_depth", 1))
        synthesis = dict(channel_base=channel_base, channel_max=channel_max, conv_clamp=conv_clamp,
                         num_fp16_res=num_fp16_res)
        backbone_res = spec.backbone_resolution or rk["triplane_size"]
        backbone_ch = spec.backbone_channels(self.depth)
        self.backbone = StyleGAN2Backbone(z_dim, c_dim, w_dim, backbone_res, backbone_ch, mapping_kwargs, **synthesis)
        projected_ch = math.prod(spec.plane_shape(self.depth))
        for name in spec.projections:
            self.add_module(name, nn.Sequential(Conv2dLayer(backbone_ch, 256, 1, bias=False),
                                                Conv2dLayer(256, projected_ch, 1, bias=False)))
        sr_name = rk["superresolution_module"].rsplit(".", 1)[-1]
        self.superresolution = Superresolution(sr_name, 32, img_resolution, sr_num_fp16_res, rk.get("sr_antialias", True),
                                               **(sr_kwargs or {}))
        activation = spec.decoder_activation or rk.get("decoder_activation", "sigmoid")
        self.decoder = OSGDecoder(32, rk.get("decoder_lr_mul", 1.0), activation)
        if spec.panohead_modules:
            self.torgb = ToRGBLayer(32, 3, w_dim) if rk.get("use_torgb_raw", False) else None
            self.bcg_synthesis = None
            if rk.get("use_background", False):
                self.bcg_synthesis = SynthesisNetwork(w_dim, self.superresolution.input_resolution, 32,
                                                      **{**synthesis, "channel_base": channel_base // 2})
            self.t_mapping = MappingNetwork(z_dim, c_dim, 3, num_ws=1, last_activation="linear", lr_multiplier=1.0,
                                            **(mapping_kwargs or {}))
        self.neural_rendering_resolution = 64
        self.precision = "auto"

    @property
    def spec(self) -> GANKind:
        """This generator's row of the GAN kinds table (looked up: the table is not pickled with it)."""
        return GAN_KINDS[self.kind]

    def fp16(self, t: torch.Tensor) -> bool:
        """Whether the float16-capable blocks run in float16 for tensors on ``t``'s device."""
        return self.precision == "fp16" or (self.precision == "auto" and t.device.type == "cuda")

    # -- latent side ------------------------------------------------------------------------------
    def _c(self, c):
        if self.rendering_kwargs.get("c_gen_conditioning_zero", False):
            c = torch.zeros_like(c)
        return c * self.rendering_kwargs.get("c_scale", 0)

    def mapping(self, z, c, truncation_psi=1.0, truncation_cutoff=None):
        return self.backbone.mapping(z, self._c(c), truncation_psi, truncation_cutoff)

    def delta_c(self, z, c, truncation_psi=1.0, truncation_cutoff=None):
        """PanoHead's learned camera translation offset (3,) per sample (used only in training)."""
        return self.t_mapping(z, self._c(c), truncation_psi, truncation_cutoff).squeeze(1)

    # -- per-subject work ---------------------------------------------------------------------------
    def planes(self, ws, noise_mode="const", generator=None):
        """Backbone output shaped for :func:`sample_planes`."""
        raw = self.backbone.synthesis(ws, noise_mode=noise_mode, generator=generator, fp16=self.fp16(ws))
        n, _, h, w = raw.shape
        shape = self.spec.plane_shape(self.depth)
        if not self.spec.projections:
            return raw.view(n, *shape, h, w)
        return torch.cat([getattr(self, name)(raw).view(n, 1, *shape, h, w) for name in self.spec.projections], 1)

    def background(self, ws, noise_mode="const", generator=None):
        """PanoHead/SphereHead's background feature image (N, 32, R, R), or None."""
        bcg = getattr(self, "bcg_synthesis", None)
        if bcg is None:
            return None
        wb = ws[:, :bcg.num_ws]
        if wb.size(1) < bcg.num_ws:
            wb = torch.cat([wb, wb[:, -1:].repeat(1, bcg.num_ws - wb.size(1), 1)], 1)
        return bcg(wb, noise_mode=noise_mode, generator=generator, fp16=self.fp16(ws))

    # -- querying and rendering ---------------------------------------------------------------------
    def plane_features(self, planes, points):
        return sample_planes(self.kind, planes, points, self.rendering_kwargs["box_warp"], self.depth)

    def decode(self, planes, points):
        """Decoder output at world points (N, M, 3): features (N, M, 32), raw density (N, M, 1)."""
        return self.decoder(self.plane_features(planes, points))

    def field(self, planes):
        """The renderer's field for these planes (density cropped for kinds that crop it)."""
        box = self.rendering_kwargs["box_warp"]

        def query(points, _dirs):
            rgb, sigma = self.decode(planes, points)
            if self.spec.crops_density:
                sigma = torch.where(crop_outside(points, box), torch.full_like(sigma, -1e3), sigma)
            return rgb, sigma
        return query

    def content_box(self) -> tuple:
        """Half extents (x, y, z), world units, of the box the planes cover (``box_warp``); kinds that
        crop the density (PanoHead, SphereHead) crop it 0.1 inside it in x and z. Outside, the planes
        are zero-padded and only the decoder's response to zero features (EG3D) remains."""
        h = self.rendering_kwargs["box_warp"] / 2
        return (h - TRIPLANE_CROP, h, h - TRIPLANE_CROP) if self.spec.crops_density else (h, h, h)

    def render_settings(self, deterministic: bool) -> RenderSettings:
        rk = self.rendering_kwargs
        return RenderSettings(rk["depth_resolution"], rk["depth_resolution_importance"], rk.get("clamp_mode", "softplus"),
                              deterministic)

    def synthesis(self, ws, origins, dirs, resolution, ray_start=None, ray_end=None, planes=None, background=None,
                  noise_mode="const", deterministic=False, generator=None):
        """Render rays (N, R*R, 3) of N images in one pass; returns the originals' output dict.

        ``planes``/``background`` may be passed precomputed (the per-subject work). ray_start/ray_end
        default to the checkpoint's range.
        """
        rk = self.rendering_kwargs
        if planes is None:
            planes = self.planes(ws, noise_mode, generator)
        start = rk["ray_start"] if ray_start is None else ray_start
        end = rk["ray_end"] if ray_end is None else ray_end
        feats, depth, weights = render_rays(self.field(planes), origins, dirs, start, end,
                                            self.render_settings(deterministic), generator)
        return self.compose(ws, feats, depth, weights, resolution, background, noise_mode, generator)

    def raw_rgb(self, feature_image, w):
        """Feature image (N, C, H, W), signed as the decoder's features are after compose's scaling ->
        raw RGB (N, 3, H, W): ToRGB (a 1x1 convolution modulated by ``w``, (N, 512)) where the
        generator has one (PanoHead, SphereHead), else the first 3 channels (EG3D)."""
        if getattr(self, "torgb", None) is not None:
            return self.torgb(feature_image, w, fused_modconv=False)
        return feature_image[:, :3]

    def compose(self, ws, feats, depth, weights, resolution, background=None, noise_mode="const", generator=None):
        """Rendered rays (..., C) / (..., 1) of n = numel / R^2 images -> raw image, mask, depth, final image.

        ``ws`` has one row per image or one per subject (repeated over its images).
        """
        rk = self.rendering_kwargs
        n = feats.shape[:-1].numel() // resolution ** 2

        def image(t):
            return t.reshape(n, resolution * resolution, -1).permute(0, 2, 1).reshape(n, -1, resolution, resolution)

        feature_image = image(feats).contiguous()
        depth_image, weights_image = image(depth), image(weights)
        if ws.shape[0] != n:
            ws = ws.repeat_interleave(n // ws.shape[0], dim=0)
        if self.decoder.activation == "sigmoid":
            feature_image = feature_image * 2 - 1
        out = {"image_depth": depth_image, "weights_sum": weights_image}
        if self.spec.panohead_modules:
            if background is None:
                background = self.background(ws, noise_mode, generator)
            if background is not None:
                bcg = torch.nn.functional.interpolate(background, size=feature_image.shape[2:], mode="bilinear",
                                                      align_corners=False, antialias=rk.get("sr_antialias", True))
                if bcg.shape[0] != n:
                    bcg = bcg.repeat_interleave(n // bcg.shape[0], dim=0)
                feature_image = feature_image + (1 - weights_image) * bcg
            out["image_mask"] = weights_image * (1 + 2 * 0.001) - 0.001
        rgb = self.raw_rgb(feature_image, ws[:, -1])
        out["feature_image"] = feature_image
        out["image_raw"] = rgb
        out["image"] = self.superresolution(rgb, feature_image, ws, noise_mode=rk.get("superresolution_noise_mode", "none"),
                                            generator=generator, fp16=self.fp16(ws))
        return out
