"""Antialiasing of a minifying resampling: a mip pyramid of the source, trilinear lookups.

A resampling that reads a source image at the continuous pixels ``pixels (B, h, w, 2)`` (one
per output pixel centre) minifies where an output pixel covers more than one source pixel: a
bilinear point sample there picks one texel of many and aliases (a 1-px line grid seen through
a 180 degree fisheye of a 48 degree frame: 10-12 dB against the area average). Here each output
pixel's footprint is measured from the sampling grid itself: the Jacobian of ``pixels`` by
finite differences to the next output pixel (one-sided at the edges and beside invalid pixels),
its longer column ``rho`` in source pixels. The source is prefiltered by a mip pyramid (level
``k`` the ``2**k x 2**k`` box average, built by 2 x 2 averages: ``avg_pool2d``, odd edges
averaged over the texels they hold), and the pixel is read by trilinear lookup: bilinear in
the levels ``floor(L)`` and ``floor(L) + 1`` around ``L = log2(rho / n)``, blended linearly.
Anisotropic footprints (the rim of a fisheye squeezes one direction many times more than the
other) take ``n = ceil(rho / rho_minor)`` such lookups (at most :data:`MAX_ANISOTROPY`) spread
along the longer column, as GPUs' anisotropic filtering does, instead of blurring both
directions to the longer one.

Rules:

* where no output pixel's footprint exceeds one source pixel (``rho <= 1`` everywhere: the
  output magnifies, or keeps the scale) nothing is done here and the caller samples as before,
  bit for bit;
* labels, depth and other nearest-sampled data are never prefiltered: the nearest texel at the
  pixel centre, unchanged (a class id is not blended, a depth edge is not smeared);
* validity is the caller's (the pixel centre's), unchanged.

Module functions, used by :func:`~omniscape_torch.render.reproject.sample_camera` (and so
``ot.reproject``), :class:`~omniscape_torch.augment.RandomReproject` and the cubemap layer.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from .reference import grid_sample

__all__ = ["footprint_level", "mip_sample"]


def _step(pixels: Tensor, ok: Tensor, dim: int) -> Tensor:
    """Squared length of ``d pixels / d (output pixel)`` along ``dim`` (1: rows, 2: columns),
    ``(B, h, w)``: the forward difference where both pixels are ``ok``, else the backward
    one, else 0."""
    n = pixels.shape[dim]
    if n < 2:
        return torch.zeros_like(pixels[..., 0])
    diff = (pixels.narrow(dim, 1, n - 1) - pixels.narrow(dim, 0, n - 1)).square().sum(-1)
    diff = diff * (ok.narrow(dim, 1, n - 1) & ok.narrow(dim, 0, n - 1))
    zero = torch.zeros_like(diff.narrow(dim, 0, 1))
    # forward where it is known, else backward (max: an unknown difference is 0)
    return torch.maximum(torch.cat((diff, zero), dim), torch.cat((zero, diff), dim)) \
        if n > 2 else torch.cat((diff, diff), dim)


def footprint_level(pixels: Tensor, valid: Tensor) -> Tensor:
    """The mip level ``L = log2(rho)`` of each output pixel, ``rho`` the longer Jacobian
    column of the sampling grid in source pixels (how far the source position moves to the
    next output pixel, across or down), by finite differences to the neighbours (the longer
    of the forward and backward ones where both are valid; 0 where none is).

    Args:
        pixels: ``(B, h, w, 2)`` source pixel ``(u, v)`` of each output pixel centre.
        valid: ``(B, h, w)`` bool: the pixels whose position is meaningful.

    Returns:
        ``(B, h, w)`` float32 levels, ``-inf`` where ``rho = 0``; ``L <= 0`` everywhere valid
        means the grid does not minify (:func:`mip_sample` is then plain bilinear).
    """
    pixels = pixels.detach()
    longer = torch.maximum(_step(pixels, valid, 2), _step(pixels, valid, 1))
    return 0.5 * torch.log2(longer.float())


def _pyramid(image: Tensor, first: int, last: int) -> list[Tensor | None]:
    """Mip levels ``0..last`` of ``image (B, C, H, W)`` (floating), those below ``first``
    None: level ``k`` the ``2**k x 2**k`` box average (``first`` in one ``avg_pool2d`` from
    the image, the next ones by 2 x 2 averages; an odd last row or column averaged over the
    texels it holds)."""
    out: list[Tensor | None] = [None] * first
    level = image if first == 0 else F.avg_pool2d(image, 2 ** first, ceil_mode=True)
    out.append(level)
    for _ in range(first, last):
        level = F.avg_pool2d(level, 2, ceil_mode=True) if min(level.shape[-2:]) > 1 else level
        out.append(level)
    return out


def _bilinear(level: Tensor, batch: Tensor, x: Tensor, y: Tensor) -> Tensor:
    """``level (B, C, H, W)`` at the pixels ``(x, y) (n,)`` of the samples ``batch (n,)``,
    bilinear with border clamping (``grid_sample``'s ``padding_mode="border"``): ``(n, C)``."""
    chans, height, width = level.shape[1:]
    x = x.clamp(0, width - 1)
    y = y.clamp(0, height - 1)
    x0 = x.detach().floor().clamp(max=max(width - 2, 0))
    y0 = y.detach().floor().clamp(max=max(height - 2, 0))
    fx, fy = (x - x0).unsqueeze(1), (y - y0).unsqueeze(1)
    x0, y0 = x0.long(), y0.long()
    x1 = (x0 + 1).clamp(max=width - 1) - x0
    y1 = ((y0 + 1).clamp(max=height - 1) - y0) * width
    plane = height * width
    base = (batch * (chans * plane) + y0 * width + x0).unsqueeze(1) + \
        torch.arange(chans, device=x.device) * plane
    flat = level.contiguous().reshape(-1)
    x1, y1 = x1.unsqueeze(1), y1.unsqueeze(1)
    top = flat.take(base) * (1 - fx) + flat.take(base + x1) * fx
    bottom = flat.take(base + y1) * (1 - fx) + flat.take(base + y1 + x1) * fx
    return top * (1 - fy) + bottom * fy


def mip_sample(image: Tensor, pixels: Tensor, valid: Tensor, level: Tensor) -> Tensor:
    """``image`` read at ``pixels`` through its mip pyramid, each output pixel prefiltered to
    its footprint (module docstring): trilinear, bilinear in the levels ``floor(L)`` and
    ``floor(L) + 1`` blended linearly (``L`` clamped to ``[0, top]``).

    Args:
        image: ``(B or 1, C, H, W)`` floating; a batch of 1 is shared by every sample.
        pixels: ``(B, h, w, 2)`` source pixels (centres at integers).
        valid: ``(B, h, w)`` bool: the pixels to read (the others come back 0).
        level: ``(B, h, w)`` from :func:`footprint_level`.

    Returns:
        ``(B, C, h, w)`` in ``image``'s dtype; differentiable with respect to ``image`` and
        ``pixels`` (the level is not: it is a choice of filter).
    """
    batch, h, w = valid.shape
    chans, height, width = image.shape[1:]
    index = valid.reshape(-1).nonzero().squeeze(1)
    sample = index // (h * w) if image.shape[0] > 1 else torch.zeros_like(index)
    at = pixels.reshape(-1, 2)[index].to(image.dtype)
    top = int(math.floor(math.log2(max(height, width))))
    lv = level.reshape(-1)[index].nan_to_num(0.0).clamp(0, top)
    first, last = (int(math.floor(float(lv.min()))), int(math.ceil(float(lv.max())))) \
        if len(index) else (0, 0)
    out = image.new_zeros(len(index), chans)
    for k, mip in enumerate(_pyramid(image, first, last)):
        if mip is None:
            continue
        weight = (1 - (lv - k).abs()).clamp_min(0)
        sel = (weight > 0).nonzero().squeeze(1)
        if len(sel) == 0:
            continue
        scale = 0.5 ** k
        x = (at[sel, 0] + 0.5) * scale - 0.5
        y = (at[sel, 1] + 0.5) * scale - 0.5
        values = _bilinear(mip, sample[sel], x, y) * weight[sel].to(image.dtype).unsqueeze(1)
        out = out.index_add(0, sel, values)
    full = image.new_zeros(batch * h * w, chans).index_copy(0, index, out)
    return full.reshape(batch, h, w, chans).permute(0, 3, 1, 2)
