"""The atlas: padded faces stacked vertically into one image, and the one map to its grid.

Atlas of border ``p``: ``(B, C, 6 n, n)`` with ``n = F + 2p``; face ``k`` (in ``FACES`` order)
occupies rows ``[k n, (k + 1) n)``, and face pixel ``(u, v)`` is atlas pixel
``(x, y) = (u + p, v + p + k n)``. `face_uv_to_grid` defines how face coordinates become
``grid_sample`` coordinates; ``cubemap.grid`` computes the same map from rays.

Because every face carries its resampled border (`pad_faces`),
bilinear sampling (``p >= 1``) or bicubic sampling (``p >= 2``) at any ``uv`` in
``[-0.5, F - 0.5]`` reads texels of one padded face only, and is continuous across seams.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .faces import _check_face, _check_face_size, _check_float_tensor, _check_pad
from .padding import BorderPlan, _pad_flat, check_cubemap

__all__ = [
    "faces_to_atlas",
    "atlas_to_faces",
    "cubemap_to_atlas",
    "face_uv_to_grid",
]


def faces_to_atlas(faces: Tensor) -> Tensor:
    """Stack (padded) faces vertically into one image.

    Args:
        faces: ``(B, 6, C, n, n)``, faces in ``FACES`` order (e.g. from ``pad_faces``).

    Returns:
        ``(B, C, 6 n, n)`` atlas; face ``k`` in rows ``[k n, (k + 1) n)``.
    """
    check_cubemap(faces, "faces")
    batch, _, channels, n, _ = faces.shape
    return faces.transpose(1, 2).reshape(batch, channels, 6 * n, n)


def atlas_to_faces(atlas: Tensor) -> Tensor:
    """Inverse of `faces_to_atlas`.

    Args:
        atlas: ``(B, C, 6 n, n)``.

    Returns:
        ``(B, 6, C, n, n)`` faces (a view when possible).
    """
    if not isinstance(atlas, Tensor):
        raise TypeError(f"atlas must be a torch.Tensor, got {type(atlas).__name__}")
    if atlas.ndim != 4 or atlas.shape[2] != 6 * atlas.shape[3]:
        raise ValueError(f"atlas must have shape (B, C, 6 n, n), got {tuple(atlas.shape)}")
    batch, channels, _, n = atlas.shape
    return atlas.reshape(batch, channels, 6, n, n).transpose(1, 2)


def cubemap_to_atlas(
    cubemap: Tensor, pad: int, mode: str = "bilinear", *, plan: BorderPlan | None = None
) -> Tensor:
    """Pad a cube (``pad_faces``) and lay it out as an atlas (``faces_to_atlas``).

    Args:
        cubemap: ``(B, 6, C, F, F)``; floating for ``"bilinear"``, any dtype for ``"nearest"``.
        pad: border width ``p`` (``>= 1`` for bilinear sampling, ``>= 2`` for bicubic).
        mode: border resampling, ``"bilinear"`` or ``"nearest"`` (labels).
        plan: optional precomputed ``border_plan(F, pad, mode)``.

    Returns:
        ``(B, C, 6 (F + 2p), F + 2p)`` atlas, differentiable with respect to ``cubemap``.
    """
    check_cubemap(cubemap)
    _check_pad(pad)
    batch, _, channels, face_size, _ = cubemap.shape
    n = face_size + 2 * pad
    return _pad_flat(cubemap, pad, mode, plan).reshape(batch, channels, 6 * n, n)


def face_uv_to_grid(face: int | Tensor, uv: Tensor, face_size: int, pad: int) -> Tensor:
    """``grid_sample`` coordinates of face pixels in the atlas, for ``align_corners=False``.

    Atlas pixel ``(x, y) = (u + p, v + p + face n)``, ``n = F + 2p``, normalised as
    ``gx = (2 x + 1) / n - 1``, ``gy = (2 y + 1) / (6 n) - 1`` (the atlas edge, pixel ``-0.5``
    or ``size - 0.5``, maps to -1 or 1).

    Args:
        face: int or integer tensor broadcastable with ``uv.shape[:-1]``, index into ``FACES``.
        uv: ``(..., 2)`` face pixel coordinates, floating.
        face_size: ``F``.
        pad: atlas border ``p``.

    Returns:
        ``(..., 2)`` grid ``(gx, gy)`` in ``[-1, 1]`` for ``uv`` within the padded face, dtype of
        ``uv``; differentiable with respect to ``uv``.

    Examples:
        >>> cube = torch.rand(1, 6, 1, 4, 4, dtype=torch.float64)
        >>> atlas = cubemap_to_atlas(cube, 1)
        >>> grid = face_uv_to_grid(2, torch.tensor([[3.0, 1.0]], dtype=torch.float64), 4, 1)
        >>> out = torch.nn.functional.grid_sample(atlas, grid.view(1, 1, 1, 2), align_corners=False)
        >>> torch.allclose(out.flatten(), cube[0, 2, 0, 1, 3])
        True
    """
    _check_float_tensor(uv, "uv", last=2)
    face = _check_face(face)
    _check_face_size(face_size)
    _check_pad(pad)
    n = face_size + 2 * pad
    if isinstance(face, Tensor):
        row0 = (face * n).to(uv.dtype)  # an index, converted once to the grid's dtype
    else:
        row0 = float(face * n)
    x = uv[..., 0] + pad
    y = uv[..., 1] + pad + row0
    return torch.stack([(2 * x + 1) / n - 1, (2 * y + 1) / (6 * n) - 1], dim=-1)
