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


__all__ = ["footprint", "mip_sample", "minified", "MAX_TAPS", "MINIFIES"]

#: Most taps per axis of a footprint (:func:`mip_sample`): up to ``MAX_TAPS`` source pixels
#: across, the taps read the image itself; beyond, the mip level ``log2(rho / MAX_TAPS)``.
MAX_TAPS = 3
#: A pixel minifies where a Jacobian column is longer than this many source pixels: 1, with a
#: margin for the rounding of the grid (a pinhole into the same pinhole is 1 +- 1e-6).
MINIFIES = 1.001


def _derivative(pixels: Tensor, ok: Tensor, dim: int, period: float | None) -> Tensor:
    """``d pixels / d (output pixel)`` along ``dim`` (1: rows, 2: columns), ``(B, h, w, 2)``:
    the forward difference where both pixels are ``ok``, else the backward one, else 0; ``u``
    differences taken modulo ``period`` (a panorama's width) into ``[-period / 2, period / 2)``
    ."""
    n = pixels.shape[dim]
    if n < 2:
        return torch.zeros_like(pixels)
    diff = pixels.narrow(dim, 1, n - 1) - pixels.narrow(dim, 0, n - 1)
    if period is not None:
        du = torch.remainder(diff[..., 0] + period / 2, period) - period / 2
        diff = torch.stack((du, diff[..., 1]), -1)
    both = (ok.narrow(dim, 1, n - 1) & ok.narrow(dim, 0, n - 1)).unsqueeze(-1)
    diff = torch.where(both, diff, torch.zeros_like(diff))   # invalid positions may be inf
    fwd = torch.cat((diff, diff.narrow(dim, 0, 1)), dim)
    fwd_ok = torch.cat((both, torch.zeros_like(both.narrow(dim, 0, 1))), dim)
    bwd = torch.cat((diff.narrow(dim, 0, 1), diff), dim)
    return torch.where(fwd_ok, fwd, bwd)


def footprint(pixels: Tensor, valid: Tensor, period: float | None = None
              ) -> tuple[Tensor, Tensor]:
    """The Jacobian columns of a sampling grid: how far the source position moves to the next
    output pixel across (``du``) and down (``dv``), in source pixels, by finite differences
    (forward where both pixels are valid, else backward, else 0).

    Args:
        pixels: ``(B, h, w, 2)`` source pixel ``(u, v)`` of each output pixel centre.
        valid: ``(B, h, w)`` bool: the pixels whose position is meaningful.
        period: the source's width where its columns wrap around (a full panorama): ``u``
            moves the short way round.

    Returns:
        ``du, dv``, each ``(B, h, w, 2)`` (no gradient).
    """
    pixels = pixels.detach()
    return _derivative(pixels, valid, 2, period), _derivative(pixels, valid, 1, period)


def _atlas(image: Tensor, first: int, last: int) -> tuple[Tensor, Tensor]:
    """Mip levels ``first..last`` of ``image (B, C, H, W)`` (floating) in one image, and where
    each lies: level ``k`` the ``2**k x 2**k`` box average (``first`` in one ``avg_pool2d``,
    the next ones by 2 x 2 averages; an odd last row or column averaged over the texels it
    holds), level ``first`` at the top left, the others stacked down a column to its right.

    Returns:
        ``atlas (B, C, Ha, Wa)`` and ``table (last + 1, 4)`` float: per level its ``x, y``
        offset in the atlas and its ``width, height`` (rows below ``first`` unused).
    """
    level = image if first == 0 else F.avg_pool2d(image, 2 ** first, ceil_mode=True)
    levels = [level]
    for _ in range(first, last):
        if min(levels[-1].shape[-2:]) > 1:
            levels.append(F.avg_pool2d(levels[-1], 2, ceil_mode=True))
        else:
            levels.append(levels[-1])
    table = torch.zeros(last + 1, 4, dtype=image.dtype)
    height, width = level.shape[-2:]
    table[first] = torch.tensor([0.0, 0.0, width, height])
    if len(levels) == 1:
        return level, table
    column = levels[1].shape[-1]
    atlas = image.new_zeros(*level.shape[:2], max(height, sum(m.shape[-2] for m in levels[1:])),
                            width + column)
    atlas[..., :height, :width] = level
    y = 0
    for k, mip in enumerate(levels[1:], first + 1):
        hk, wk = mip.shape[-2:]
        atlas[..., y:y + hk, width:width + wk] = mip
        table[k] = torch.tensor([float(width), float(y), wk, hk])
        y += hk
    return atlas, table


def _offsets(taps: int, dtype: torch.dtype) -> Tensor:
    """``(taps**2, 2)`` tap positions in a footprint's frame: the centres of a ``taps x taps``
    subgrid of ``[-0.5, 0.5]^2``."""
    o = (torch.arange(taps, dtype=dtype) + 0.5) / taps - 0.5
    return torch.stack(torch.meshgrid(o, o, indexing="ij"), -1).reshape(-1, 2)


def mip_sample(image: Tensor, pixels: Tensor, valid: Tensor, du: Tensor, dv: Tensor, *,
               max_taps: int = MAX_TAPS) -> Tensor:
    """``image`` averaged over each output pixel's footprint (module docstring): ``n x n``
    taps spread over the parallelogram of the Jacobian columns ``du, dv`` about ``pixels``
    (``n = ceil(rho)`` of the call's largest footprint, up to ``max_taps``), each a trilinear
    lookup of the mip pyramid at the level ``log2(rho / n)`` of its pixel (0 while
    ``rho <= n``: bilinear taps of the image itself); all in one ``grid_sample`` of the
    pyramid's atlas.

    Args:
        image: ``(B or 1, C, H, W)`` floating; a batch of 1 is shared by every sample.
        pixels: ``(B, h, w, 2)`` source pixels (centres at integers).
        valid: ``(B, h, w)`` bool: the pixels to read (the others come back 0).
        du, dv: ``(B, h, w, 2)`` the Jacobian columns (:func:`footprint`).
        max_taps: most taps per axis.

    Returns:
        ``(B, C, h, w)`` in ``image``'s dtype; differentiable with respect to ``image`` and
        ``pixels`` (the footprint is not: it is a choice of filter).
    """
    batch, h, w = valid.shape
    dtype = image.dtype
    height, width = image.shape[-2:]
    chans = image.shape[1]
    # the valid pixels of each sample first, padded to the largest count (a padding entry
    # reads a pixel that is not valid, and is dropped at the end)
    flat = valid.reshape(batch, -1)
    count = int(flat.sum(1).max())
    if count == 0:
        return image.new_zeros(batch, chans, h, w)
    order = torch.argsort(flat.to(torch.uint8), dim=1, descending=True, stable=True)[:, :count]
    pick = order.unsqueeze(-1).expand(batch, count, 2)
    at = pixels.to(dtype).reshape(batch, -1, 2).gather(1, pick)               # (B, N, 2)
    ju, jv = (d.detach().to(dtype).reshape(batch, -1, 2).gather(1, pick) for d in (du, dv))
    ok = flat.gather(1, order)
    rho = torch.maximum(ju.norm(dim=-1), jv.norm(dim=-1)).clamp_min(1.0)
    rho = torch.where(ok, rho, torch.ones_like(rho))
    n = min(int(math.ceil(float(rho.max()))), max_taps)
    top = int(math.floor(math.log2(max(height, width))))
    level = torch.log2(rho / n).clamp(0, top)
    first = int(level[ok].min())
    last = int(math.ceil(float(level.max())))
    level = level.clamp_min(first)
    atlas, table = _atlas(image, first, last)
    below = level.floor()
    lower = below.long()
    o = _offsets(n, dtype)                                                     # (T, 2)
    sizes = (atlas.shape[-1], atlas.shape[-2])
    grids = []   # per level (B, T, N, 2): the taps' grid_sample coordinates, pixels innermost
    for k in ((lower,) if last == first else (lower, (lower + 1).clamp(max=last))):
        where = table[k]                                                       # (B, N, 4)
        scale = torch.exp2(-k.to(dtype))                                       # (B, N)
        axes = []
        for i in (0, 1):   # x, then y
            centre = ((at[..., i] + 0.5) * scale - 0.5).unsqueeze(1)            # (B, 1, N)
            spots = torch.addcmul(
                torch.addcmul(centre, o[:, 0, None], (ju[..., i] * scale).unsqueeze(1)),
                o[:, 1, None], (jv[..., i] * scale).unsqueeze(1))               # (B, T, N)
            spots = torch.minimum(spots.clamp_min_(0), (where[..., 2 + i] - 1).unsqueeze(1))
            # atlas pixel x + offset -> grid_sample's (2 (x + offset) + 1) / size - 1
            axes.append((2 * (spots + where[..., i].unsqueeze(1)) + 1) / sizes[i] - 1)
        grids.append(torch.stack(axes, -1))
    grid = torch.cat(grids, 1)                                                 # (B, L T, N, 2)
    values = F.grid_sample(atlas.expand(batch, *atlas.shape[1:]), grid, mode="bilinear",
                           padding_mode="border", align_corners=False)       # (B, C, L T, N)
    values = values.reshape(batch, chans, len(grids), len(o), count).mean(3)
    values = values[:, :, 0] if len(grids) == 1 else torch.lerp(
        values[:, :, 0], values[:, :, 1], (level - below).unsqueeze(1))      # (B, C, N)
    out = image.new_zeros(batch, chans, h * w).scatter(
        2, order.unsqueeze(1).expand(batch, chans, count), values)
    out = out.reshape(batch, chans, h, w)
    return torch.where(valid.unsqueeze(1), out, torch.zeros_like(out))


def minified(image: Tensor, pixels: Tensor, valid: Tensor, period: float | None = None
             ) -> tuple[Tensor, Tensor] | None:
    """The pixels of a resampling that minify, averaged over their footprints: what a sampler
    writes over its point samples (module docstring's rules).

    Args:
        image: ``(B or 1, C, H, W)`` floating or ``uint8`` (read as float32 levels).
        pixels: ``(B, h, w, 2)`` source pixels of the output pixel centres.
        valid: ``(B, h, w)`` bool.
        period: as for :func:`footprint`.

    Returns:
        None where no valid pixel's footprint exceeds one source pixel (nothing to change),
        else ``values (B, C, h, w)`` (float; a ``uint8`` image's levels 0..255) and
        ``mask (B, 1, h, w)``: the valid pixels whose footprint exceeds one source pixel
        (a Jacobian column longer than 1), where ``values`` replace the point samples
        (elsewhere ``values`` is 0).
    """
    du, dv = footprint(pixels, valid, period)
    limit = MINIFIES ** 2
    mask = valid & ((du.square().sum(-1) > limit) | (dv.square().sum(-1) > limit))
    if not bool(mask.any()):
        return None
    work = image if image.dtype in (torch.float32, torch.float64) else image.float()
    return mip_sample(work, pixels, mask, du, dv), mask.unsqueeze(1)
