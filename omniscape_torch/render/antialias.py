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


def _offsets(taps: int, dtype: torch.dtype) -> Tensor:
    """``(taps**2, 2)`` tap positions in a footprint's frame: the centres of a ``taps x taps``
    subgrid of ``[-0.5, 0.5]^2``."""
    o = (torch.arange(taps, dtype=dtype) + 0.5) / taps - 0.5
    return torch.stack(torch.meshgrid(o, o, indexing="ij"), -1).reshape(-1, 2)


def mip_sample(image: Tensor, pixels: Tensor, valid: Tensor, du: Tensor, dv: Tensor, *,
               max_taps: int = MAX_TAPS) -> Tensor:
    """``image`` averaged over each output pixel's footprint (module docstring): ``n x n``
    taps spread over the parallelogram of the Jacobian columns ``du, dv`` about ``pixels``
    (``n = ceil(rho)`` up to ``max_taps``, ``rho`` the longer column), each a trilinear
    lookup of the mip pyramid at the level ``log2(rho / n)`` (0 while ``rho <= max_taps``:
    bilinear taps of the image itself).

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
    chans, height, width = image.shape[1:]
    dtype = image.dtype
    out = image.new_zeros(batch, h * w, chans)
    top = int(math.floor(math.log2(max(height, width))))
    ok = valid.reshape(batch, -1)
    for b in range(batch):   # each sample reads its own image (grid_sample: one per call)
        index = ok[b].nonzero().squeeze(1)
        if len(index) == 0:
            continue
        at = pixels[b].reshape(-1, 2)[index].to(dtype)
        ju, jv = (d[b].detach().reshape(-1, 2)[index].to(dtype) for d in (du, dv))
        rho = torch.maximum(ju.norm(dim=-1), jv.norm(dim=-1)).clamp_min(1.0)
        taps = torch.ceil(rho).clamp(max=max_taps)
        level = torch.log2(rho / taps).clamp(0, top)
        mips = _pyramid(image[b if image.shape[0] > 1 else 0][None],
                        int(level.min()), int(math.ceil(float(level.max()))))
        for n in taps.unique().long().tolist():
            group = None if bool((taps == n).all()) else (taps == n).nonzero().squeeze(1)
            pick = (lambda t: t) if group is None else (lambda t: t[group])
            lv = pick(level)
            below = lv.floor()
            spread = _offsets(n, dtype)                                     # (taps, 2)
            for k in range(int(below.min()), min(int(below.max()) + 1, len(mips) - 1) + 1):
                weight = torch.where(below == k, 1 - (lv - below), (lv - below) * (below + 1 == k))
                # tap positions in grid_sample's coordinates of level k:
                # g = (2 (p + 0.5) 2^-k) / W_k - 1, p = centre + o_u du + o_v dv
                mip = mips[k]
                scale = torch.tensor([2 * 0.5 ** k / mip.shape[-1], 2 * 0.5 ** k / mip.shape[-2]],
                                     dtype=dtype)
                c, u, v = ((pick(t) * scale).T for t in (at + 0.5, ju, jv))   # (2, m) each
                grid = torch.stack([torch.addcmul(torch.addcmul(
                    (c[i] - 1).unsqueeze(1), u[i].unsqueeze(1), spread[:, 0]),
                    v[i].unsqueeze(1), spread[:, 1]) for i in (0, 1)], -1)   # (m, taps, 2)
                values = F.grid_sample(mip, grid.unsqueeze(0), mode="bilinear",
                                       padding_mode="border", align_corners=False)[0]
                values = values.mean(-1).T * weight.unsqueeze(1)           # (m, C)
                rows = index if group is None else index[group]
                out[b].index_add_(0, rows, values)
    return out.reshape(batch, h, w, chans).permute(0, 3, 1, 2)


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
