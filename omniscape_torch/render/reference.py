"""Sampling an image at continuous pixel positions: the ``grid_sample`` conventions, written once.

Pixel ``(u, v)`` of an image W wide and H tall (integer coordinates at pixel centres) is
``grid_sample`` coordinate ``((2 u + 1) / W - 1, (2 v + 1) / H - 1)`` with
``align_corners=False``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def pixels_to_grid(pixels: Tensor, width: int, height: int) -> Tensor:
    """``grid_sample`` coordinates (``align_corners=False``) of ``pixels (..., 2)``."""
    return torch.stack(((2 * pixels[..., 0] + 1) / width - 1,
                        (2 * pixels[..., 1] + 1) / height - 1), dim=-1)


def unnormalize(coord: Tensor, size: int) -> Tensor:
    """Pixel coordinate ``((g + 1) size - 1) / 2`` of grid coordinates, as ``grid_sample``'s CPU
    kernel computes it (``align_corners=False``): one fused multiply-add,
    ``fma(g + 1, size / 2, -0.5)``, reproduced for float32 by computing in float64 and rounding
    once (exact). Nearest and bilinear taps computed from it are ``grid_sample``'s own."""
    if coord.dtype == torch.float64:
        return (coord + 1) * (size / 2) - 0.5
    return ((coord + 1).double() * (size / 2) - 0.5).to(coord.dtype)


def grid_sample(image: Tensor, grid: Tensor, mode: str, padding_mode: str = "border") -> Tensor:
    """``F.grid_sample(align_corners=False)``, split into row blocks on the CPU when the batch is
    smaller than the thread count.

    PyTorch's CPU kernel parallelises over the batch only; the output rows become a
    pseudo-batch over a stride-0 expanded image (no copy), and the result is identical.

    Args:
        image: ``(B, C, Hi, Wi)``; grid ``(B, H, W, 2)``.
    """
    batch, height = grid.shape[0], grid.shape[1]
    threads = torch.get_num_threads()
    plain = (grid.device.type != "cpu" or batch >= threads or height < 2 * threads)
    k = 1 if plain else max(d for d in range(1, threads // batch + 1) if height % d == 0)
    if k == 1:
        return F.grid_sample(image, grid, mode=mode, padding_mode=padding_mode,
                             align_corners=False)
    outs = []
    for b in range(batch):  # per sample: expanding (1, ...) to (k, ...) is a view
        img = image[b:b + 1].expand(k, *image.shape[1:])
        g = grid[b].reshape(k, height // k, *grid.shape[2:])
        out = F.grid_sample(img, g, mode=mode, padding_mode=padding_mode, align_corners=False)
        outs.append(out.permute(1, 0, 2, 3).reshape(1, image.shape[1], height, -1))
    return torch.cat(outs)


def nearest_gather(image: Tensor, grid: Tensor) -> Tensor:
    """``grid_sample(mode="nearest", align_corners=False, padding_mode="border")`` as a gather,
    exact for any dtype (integer labels of any size): ``x = ((gx + 1) W - 1) / 2``
    (`unnormalize`) rounded half to even, as ``grid_sample`` rounds.

    Args:
        image: ``(B, C, Hi, Wi)``; grid ``(B' in {1, B}, H, W, 2)``.

    Returns:
        ``(B, C, H, W)`` in the dtype of ``image``.
    """
    b, c, hi, wi = image.shape
    x = torch.round(unnormalize(grid[..., 0].detach(), wi)).clamp(0, wi - 1).long()
    y = torch.round(unnormalize(grid[..., 1].detach(), hi)).clamp(0, hi - 1).long()
    idx = (y * wi + x).reshape(grid.shape[0], 1, -1).expand(b, c, -1)
    return image.reshape(b, c, hi * wi).gather(-1, idx).reshape(b, c, *grid.shape[1:3])


def check_out_dtype(dtype: torch.dtype, out_dtype: object) -> torch.dtype:
    """The dtype an image of ``dtype`` is sampled into: ``out_dtype`` (None: ``dtype``), which
    must be ``dtype`` or floating (a ``uint8`` image is then scaled to [0, 1]: `from_float`)."""
    if out_dtype is None:
        return dtype
    if not isinstance(out_dtype, torch.dtype) or not (
            out_dtype == dtype or out_dtype.is_floating_point):
        raise TypeError(f"out_dtype: expected None, {dtype} or a floating dtype, got "
                        f"{out_dtype!r}")
    return out_dtype


def from_float(image: Tensor, dtype: torch.dtype, out_dtype: torch.dtype) -> Tensor:
    """An image sampled in floats from an image of ``dtype`` as ``out_dtype``: a ``uint8``
    image's levels (0..255) into floats scaled to [0, 1]; into ``uint8`` rounded to nearest
    (half up, as the fast sampler and OpenCV's ``remap`` round) and saturated, from levels or
    from [0, 1]; floats cast."""
    levels = dtype == torch.uint8
    if out_dtype == torch.uint8:
        image = image if levels else image * 255
        return torch.floor(image.clamp(0, 255) + 0.5).to(torch.uint8)
    return (image / 255 if levels else image).to(out_dtype)


class LabelMapWarning(UserWarning):
    """A ``uint8`` image given to a rendering as its image looks like a label map: it would be
    blended (bilinear or bicubic), which mixes class ids into ids of other classes."""


#: At most this many distinct values (and at least 2) in a one-channel (or grey) ``uint8``
#: image make it look like a label map (`warn_if_label_map`).
LABEL_MAP_MAX_VALUES = 32
#: Rows of the first images that `warn_if_label_map` reads.
_SAMPLED_ROWS = 8

_LABEL_MAP_MESSAGE = (
    "a uint8 image with one channel (or three equal ones) and few distinct values was given "
    "as the image to render: it looks like a label map, and an image is blended across class "
    "boundaries. Pass class ids as labels: labels=... (OmniProjection.render, "
    "ot.reproject(..., labels=True)) or the 'labels' key of RandomOmniCamera's and "
    "RandomReproject's input dict; pass labels=False to ot.reproject to silence this for an "
    "image")


def warn_if_label_map(image: Tensor, channel_dim: int) -> None:
    """Warn (`LabelMapWarning`, once: one message from one place) when ``image``, a
    ``uint8`` image whose channels are on ``channel_dim``, looks like a label map: one channel,
    or three channels equal to each other, with 2 to `LABEL_MAP_MAX_VALUES` distinct
    values, not only 0 and 255 (a mask). Cheap: a few rows of the first images are read. CPU
    images only: off the CPU, reading them back would wait for the device on every call."""
    if image.dtype != torch.uint8 or image.dim() < 3 or image.shape[channel_dim] not in (1, 3) \
            or image.device.type != "cpu":
        return
    x = image.movedim(channel_dim, -1)
    x = x.reshape(-1, *x.shape[-3:])[:6]      # the first images (a cube's six faces)
    rows = torch.linspace(0, x.shape[1] - 1, min(_SAMPLED_ROWS, x.shape[1]),
                          device=x.device).round().long()
    x = x[:, rows]
    if x.shape[-1] == 3 and not bool(((x[..., 0] == x[..., 1]) & (x[..., 1] == x[..., 2]))
                                     .all()):
        return
    counts = torch.bincount(x[..., 0].flatten().long(), minlength=256)
    distinct = int(counts.count_nonzero())
    # a 0 / 255 mask is an image to blend (a soft mask comes out), not class ids
    mask = distinct == int(counts[0] > 0) + int(counts[255] > 0)
    if 2 <= distinct <= LABEL_MAP_MAX_VALUES and not mask:
        import warnings
        warnings.warn(_LABEL_MAP_MESSAGE, LabelMapWarning, stacklevel=2)
