"""Antialiasing of a minifying resampling: footprint-adaptive taps over a mip pyramid.

A resampling that reads a source image at the continuous pixels ``pixels (B, h, w, 2)`` (one
per output pixel centre) minifies where an output pixel covers more than one source pixel: a
bilinear point sample there picks one texel of many and aliases (a 1-px line grid seen through
a 180 degree fisheye of a 48 degree frame: 10-12 dB against the area average). Here each output
pixel's footprint is measured from the sampling grid itself: the Jacobian of ``pixels`` by
finite differences to the next output pixel (forward, else backward beside invalid pixels), two
columns ``du, dv`` in source pixels, the longer of length ``rho``. A pixel with ``rho > 1``
(`MINIFIES`) is the mean of `TAPS` x `TAPS` (2 x 2) taps spread over the
parallelogram ``du, dv`` about its centre (at ``+-du / 4 +- dv / 4``: the area average's
quadrature), each a bilinear lookup of the source's mip pyramid (level ``k``: the
``2**k x 2**k`` box average, by 2 x 2 averages) at the level ``floor(log2(rho / TAPS))``: the
image itself up to ``2 TAPS`` source pixels across, the pyramid beyond, so that each tap
averages about its share of the footprint. All taps of a call are one ``grid_sample`` of an
atlas of the pyramid (`_atlas`).

Rules:

* where no output pixel's footprint exceeds one source pixel (``rho <= 1`` everywhere: the
  output magnifies, or keeps the scale) nothing is done here and the caller samples as before,
  bit for bit; per pixel too: a pixel that does not minify keeps its point sample;
* a pixel's value depends on its own footprint only, not on the rest of its batch;
* labels, depth and other nearest-sampled data are never prefiltered: the nearest texel at the
  pixel centre, unchanged (a class id is not blended, a depth edge is not smeared);
* validity is the caller's (the pixel centre's), unchanged.

Used by `sample_camera` (and so ``ot.reproject``) and
`RandomReproject`'s exact path (gradients, other devices). Its
CPU fast path runs the same rule in C++, `mip_image` (16
texels a pixel; on the line grid of ``benchmarks/bench_antialias.py`` 26.7 dB at worst,
``docs/augmentation.md``), so that a module gives the same image on every device and path, to
the rounding of the 8-bit pyramid levels the C++ keeps (a level or two).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


__all__ = ["footprint", "mip_sample", "minified", "TAPS", "MINIFIES"]

#: Taps per axis of a footprint (`mip_sample`): up to ``2 TAPS`` source pixels across, the
#: taps read the image itself; beyond, the mip level ``floor(log2(rho / TAPS))``. 2, the C++
#: rule (``fast.mip_image``): >= 26 dB on the line grid of ``benchmarks/bench_antialias.py``
#: (3 x 3 trilinear taps: 29 dB, at 4.5 times the texels).
TAPS = 2
#: A pixel minifies where a Jacobian column is longer than this many source pixels: 1, with a
#: margin for the rounding of the grid (a pinhole into the same pinhole is 1 +- 1e-6).
MINIFIES = 1.001
#: Pixels are sampled in runs of a multiple of this many (`mip_sample`).
_VECTOR = 64


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


def _atlas(image: Tensor, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """The mip pyramid of ``image (B, C, H, W)`` in one ``dtype`` image, and where each level
    lies: level 0 the image (converted), level ``k + 1`` the 2 x 2 average of level ``k`` (an
    odd last row or column averaged over the texels it holds) down to one texel, level 0 at
    the top left, the others stacked down a column to its right. The layout depends on the
    image's size only, so a pixel reads the same values whatever else its batch holds.

    Returns:
        ``atlas (B, C, Ha, Wa)`` and ``table (levels, 4)``: per level its ``x, y`` offset in
        the atlas and its ``width, height``.
    """
    height, width = image.shape[-2:]
    sizes = [(height, width)]
    while max(sizes[-1]) > 1:
        sizes.append(tuple(-(-n // 2) for n in sizes[-1]))
    rows, y = [[0.0, 0.0, width, height]], 0
    for hk, wk in sizes[1:]:
        rows.append([width, y, wk, hk])
        y += hk
    table = torch.tensor(rows, dtype=dtype, device=image.device)
    if len(sizes) == 1:
        return image.to(dtype), table
    full, column = max(height, y), sizes[1][1]
    if torch.is_grad_enabled() and image.requires_grad:
        # out of place, so that the image's gradient flows through the atlas
        levels = [image.to(dtype)]
        for _ in sizes[1:]:
            levels.append(F.avg_pool2d(levels[-1], 2, ceil_mode=True))
        right = torch.cat([F.pad(m, (0, column - m.shape[-1])) for m in levels[1:]], -2)
        return torch.cat((F.pad(levels[0], (0, 0, 0, full - height)),
                          F.pad(right, (0, 0, 0, full - y))), -1), table
    atlas = torch.zeros(*image.shape[:2], full, width + column, dtype=dtype,
                        device=image.device)
    level = atlas[..., :height, :width]
    level.copy_(image)                       # the one full-size pass: the image converted
    for k, (hk, wk) in enumerate(sizes[1:], 1):
        x0, y0 = int(table[k, 0]), int(table[k, 1])
        level = atlas[..., y0:y0 + hk, x0:x0 + wk].copy_(
            F.avg_pool2d(level, 2, ceil_mode=True))
    return atlas, table


def _offsets(taps: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """``(taps**2, 2)`` tap positions in a footprint's frame: the centres of a ``taps x taps``
    subgrid of ``[-0.5, 0.5]^2``."""
    o = (torch.arange(taps, dtype=dtype, device=device) + 0.5) / taps - 0.5
    return torch.stack(torch.meshgrid(o, o, indexing="ij"), -1).reshape(-1, 2)


def mip_sample(image: Tensor, pixels: Tensor, valid: Tensor, du: Tensor, dv: Tensor, *,
               taps: int = TAPS, dtype: torch.dtype | None = None) -> Tensor:
    """``image`` averaged over each output pixel's footprint (module docstring): ``taps x
    taps`` taps spread over the parallelogram of the Jacobian columns ``du, dv`` about
    ``pixels``, each a bilinear lookup of the mip pyramid at the level
    ``floor(log2(rho / taps))`` of its pixel (0 while ``rho < 2 taps``: the image itself); all
    in one ``grid_sample`` of the pyramid's atlas.

    Args:
        image: ``(B or 1, C, H, W)`` floating, or ``uint8`` read as its levels (0..255); a
            batch of 1 is shared by every sample.
        pixels: ``(B, h, w, 2)`` source pixels (centres at integers).
        valid: ``(B, h, w)`` bool: the pixels to read (the others come back 0).
        du: ``(B, h, w, 2)`` the Jacobian column across (`footprint`).
        dv: ``(B, h, w, 2)`` the Jacobian column down.
        taps: taps per axis.
        dtype: the floating dtype of the work and the result (default: the image's).

    Returns:
        ``(B, C, h, w)`` in ``dtype``; differentiable with respect to ``image`` and ``pixels``
        (the footprint is not: it is a choice of filter).
    """
    batch, h, w = valid.shape
    dtype = image.dtype if dtype is None else dtype
    chans = image.shape[1]
    # the valid pixels of each sample first, padded to the largest count (a padding entry
    # reads a pixel that is not valid, and is dropped at the end)
    flat = valid.reshape(batch, -1)
    count = int(flat.sum(1).max())
    if count == 0:
        return image.new_zeros(batch, chans, h, w, dtype=dtype)
    # a whole number of vectors: every pixel goes through the kernels' vector loops, never a
    # scalar tail that rounds otherwise (a pixel's value must not depend on its batch)
    count = min(-(-count // _VECTOR) * _VECTOR, h * w)
    order = torch.argsort(flat.to(torch.uint8), dim=1, descending=True, stable=True)[:, :count]
    pick = order.unsqueeze(-1).expand(batch, count, 2)
    at = pixels.to(dtype).reshape(batch, -1, 2).gather(1, pick)               # (B, N, 2)
    ju, jv = (d.detach().to(dtype).reshape(batch, -1, 2).gather(1, pick) for d in (du, dv))
    ok = flat.gather(1, order)
    rho = torch.maximum(ju.norm(dim=-1), jv.norm(dim=-1)).clamp_min(1.0)
    rho = torch.where(ok, rho, torch.ones_like(rho))
    n = taps
    atlas, table = _atlas(image, dtype)
    last = len(table) - 1
    k = torch.log2(rho / n).floor().clamp(0, last).long()                      # (B, N)
    o = _offsets(n, dtype, image.device)                                       # (T, 2)
    sizes = (atlas.shape[-1], atlas.shape[-2])
    where = table[k]                                                           # (B, N, 4)
    scale = torch.exp2(-k.to(dtype))                                           # (B, N)
    axes = []   # (B, T, N): the taps' grid_sample coordinates, pixels innermost
    for i in (0, 1):   # x, then y
        centre = ((at[..., i] + 0.5) * scale - 0.5).unsqueeze(1)                # (B, 1, N)
        spots = torch.addcmul(
            torch.addcmul(centre, o[:, 0, None], (ju[..., i] * scale).unsqueeze(1)),
            o[:, 1, None], (jv[..., i] * scale).unsqueeze(1))                   # (B, T, N)
        spots = torch.minimum(spots.clamp_min_(0), (where[..., 2 + i] - 1).unsqueeze(1))
        # atlas pixel x + offset -> grid_sample's (2 (x + offset) + 1) / size - 1
        axes.append((2 * (spots + where[..., i].unsqueeze(1)) + 1) / sizes[i] - 1)
    values = F.grid_sample(atlas.expand(batch, *atlas.shape[1:]), torch.stack(axes, -1),
                           mode="bilinear", padding_mode="border",
                           align_corners=False).mean(2)                        # (B, C, N)
    out = image.new_zeros(batch, chans, h * w, dtype=dtype).scatter(
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
        period: as for `footprint`.

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
    dtype = image.dtype if image.dtype in (torch.float32, torch.float64) else torch.float32
    return mip_sample(image, pixels, mask, du, dv, dtype=dtype), mask.unsqueeze(1)
