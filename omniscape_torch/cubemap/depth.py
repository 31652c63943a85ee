"""Planar depth <-> range on cube faces.

A simulator's depth camera gives planar depth: the distance along the face axis ``a``. The
point seen by face pixel ``(u, v)`` at depth ``d`` is ``d * ray`` with the ray's ``a``-component
equal to 1, so its range (Euclidean distance from the cube centre along the ray) is::

    range = depth * sqrt(1 + ((u - c) / f)^2 + ((v - c) / f)^2)

The factor is the same on every face (all faces share the intrinsics). Range is
view-independent, so it is what gets padded and sampled across faces; planar depth is not.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .faces import _check_face_size, _check_float_tensor, _check_pad, face_intrinsics

__all__ = ["range_factor", "depth_to_range", "range_to_depth"]


def range_factor(
    face_size: int,
    *,
    pad: int = 0,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """Range per unit of planar depth at every texel centre of a (padded) face.

    Args:
        face_size: ``F``.
        pad: border width of a padded face (texel ``[i, j]`` is pixel ``(j - pad, i - pad)``).
        dtype: floating dtype (default: torch's default dtype).
        device: device of the result.

    Returns:
        ``(n, n)`` factor ``sqrt(1 + x^2 + y^2) >= 1``, ``n = F + 2 pad``, indexed ``[v, u]``.
    """
    _check_face_size(face_size)
    _check_pad(pad)
    f, c = face_intrinsics(face_size)
    dtype = dtype or torch.get_default_dtype()
    t = (torch.arange(face_size + 2 * pad, dtype=dtype, device=device) - pad - c) / f
    return torch.sqrt(1 + t[:, None] ** 2 + t[None, :] ** 2)


def _check_square(x: Tensor, name: str) -> int:
    if x.ndim < 2 or x.shape[-1] != x.shape[-2]:
        raise ValueError(f"{name} must have shape (..., F, F), got {tuple(x.shape)}")
    return x.shape[-1]


def depth_to_range(depth: Tensor, *, pad: int = 0) -> Tensor:
    """Planar depth on face texels to range along each texel's ray.

    Args:
        depth: ``(..., n, n)`` planar depth in metres (e.g. a depth cube ``(B, 6, 1, F, F)``), any
            face; ``n = F + 2 pad``. ``inf`` (sky) stays ``inf``.
        pad: border width if the faces are padded.

    Returns:
        ``(..., n, n)`` range in metres, dtype and device of ``depth``; differentiable.
    """
    _check_float_tensor(depth, "depth")
    n = _check_square(depth, "depth")
    _check_pad(pad)
    if n - 2 * pad < 1:
        raise ValueError(f"depth of size {n} cannot hold a face with pad {pad}")
    return depth * range_factor(n - 2 * pad, pad=pad, dtype=depth.dtype, device=depth.device)


def range_to_depth(range_: Tensor, *, pad: int = 0) -> Tensor:
    """Range along each texel's ray to planar depth along the face axis.

    Args:
        range_: ``(..., n, n)`` range in metres; ``n = F + 2 pad``.
        pad: border width if the faces are padded.

    Returns:
        ``(..., n, n)`` planar depth in metres, dtype and device of ``range_``; differentiable.
    """
    _check_float_tensor(range_, "range_")
    n = _check_square(range_, "range_")
    _check_pad(pad)
    if n - 2 * pad < 1:
        raise ValueError(f"range_ of size {n} cannot hold a face with pad {pad}")
    return range_ / range_factor(n - 2 * pad, pad=pad, dtype=range_.dtype, device=range_.device)
