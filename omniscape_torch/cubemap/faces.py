"""Cube faces: order, orientation, texel rays, and the ray -> (face, uv) lookup.

Frame and pixel conventions (``DESIGN.md``): OpenCV camera frame (x right, y down,
z forward); pixels ``(u, v)`` = (column, row) with integer coordinates at texel centres, so
a face of ``F`` texels spans ``u, v`` in ``[-0.5, F - 0.5]``.

Every face is a pinhole camera at the cube centre with a 90-degree field of view,
``fx = fy = f = F / 2`` and ``cx = cy = c = (F - 1) / 2``, looking along ``a``, with
image-down ``b`` and image-right ``r = b x a``. Face pixel ``(u, v)`` is the ray::

    ray = r * (u - c) / f + b * (v - c) / f + a

This package (``omniscape_torch.cubemap``) is the only code that knows the face order and
orientation; everything else goes through these functions.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "FACES",
    "face_axes",
    "face_rotations",
    "face_intrinsics",
    "face_pixel_to_ray",
    "face_rays",
    "ray_to_face",
]

FACES = ("front", "back", "left", "right", "up", "down")

# Per face, in FACES order: (a looks along, b image down, r image right = b x a).
# Literally the table of DESIGN.md; plain tuples so that no tensor lives at module level.
_FACE_AXES = (
    ((0, 0, 1), (0, 1, 0), (1, 0, 0)),  # front
    ((0, 0, -1), (0, 1, 0), (-1, 0, 0)),  # back
    ((-1, 0, 0), (0, 1, 0), (0, 0, 1)),  # left
    ((1, 0, 0), (0, 1, 0), (0, 0, -1)),  # right
    ((0, -1, 0), (0, 0, 1), (1, 0, 0)),  # up
    ((0, 1, 0), (0, 0, -1), (1, 0, 0)),  # down
)


def _axis_sign_to_face() -> tuple[int, ...]:
    # Derived from the table, so the face order is written down exactly once:
    # entry 2 * axis + (1 if the axis points negative else 0) is the face looking that way.
    lut = [-1] * 6
    for face, (a, _, _) in enumerate(_FACE_AXES):
        axis = next(i for i, x in enumerate(a) if x != 0)
        lut[2 * axis + (1 if a[axis] < 0 else 0)] = face
    return tuple(lut)


_AXIS_SIGN_TO_FACE = _axis_sign_to_face()


def _signed_axes() -> tuple[tuple[int, ...], ...]:
    """Per face, the (axis, sign) of r and of b: ``r . ray = sign * ray[axis]``. Every face
    vector is a signed coordinate axis, so ``ray_to_face`` selects components instead of
    multiplying 3 x 3 matrices."""
    rows = []
    for _, b, r in _FACE_AXES:
        ir = next(i for i, x in enumerate(r) if x != 0)
        ib = next(i for i, x in enumerate(b) if x != 0)
        rows.append((ir, r[ir], ib, b[ib]))
    return tuple(rows)


_R_B_AXES = _signed_axes()


def _check_int(value: int, name: str, minimum: int) -> int:
    """`value`, an int of at least `minimum`; a `TypeError` or `ValueError` naming `name`."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{name} must be an int, got {type(value).__name__}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")
    return value


def _check_face_size(face_size: int, name: str = "face_size") -> int:
    return _check_int(face_size, name, 1)


def _check_pad(pad: int, name: str = "pad") -> int:
    return _check_int(pad, name, 0)


def _check_float_tensor(x: object, name: str, last: int | None = None) -> Tensor:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise TypeError(f"{name} must be a floating point tensor, got {x.dtype}")
    if last is not None and (x.ndim < 1 or x.shape[-1] != last):
        raise ValueError(f"{name} must have shape (..., {last}), got {tuple(x.shape)}")
    return x


def _check_face(face: object, name: str = "face") -> int | Tensor:
    if isinstance(face, bool):
        raise TypeError(f"{name} must be an int or an integer tensor, got bool")
    if isinstance(face, int):
        if not 0 <= face < 6:
            raise ValueError(f"{name} must be in [0, 6) (an index into FACES), got {face}")
        return face
    if isinstance(face, Tensor):
        if face.is_floating_point() or face.is_complex() or face.dtype == torch.bool:
            raise TypeError(f"{name} must be an integer tensor, got {face.dtype}")
        return face
    raise TypeError(f"{name} must be an int or an integer tensor, got {type(face).__name__}")


def face_intrinsics(face_size: int) -> tuple[float, float]:
    """Pinhole intrinsics shared by all faces.

    Args:
        face_size: ``F``, texels per face side.

    Returns:
        ``(f, c)``: focal length ``F / 2`` and principal point ``(F - 1) / 2`` (same on both
        axes), in pixels, as Python floats.
    """
    _check_face_size(face_size)
    return face_size / 2.0, (face_size - 1) / 2.0


def face_axes(dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> Tensor:
    """The face table of ``DESIGN.md`` as a tensor.

    Args:
        dtype: floating dtype of the result (default: torch's default dtype).
        device: device of the result.

    Returns:
        ``(6, 3, 3)`` tensor, faces in ``FACES`` order; ``axes[k, 0]`` is ``a`` (viewing axis),
        ``axes[k, 1]`` is ``b`` (image down), ``axes[k, 2]`` is ``r = b x a`` (image right).
    """
    return torch.tensor(_FACE_AXES, dtype=dtype or torch.get_default_dtype(), device=device)


def face_rotations(
    dtype: torch.dtype | None = None, device: torch.device | str | None = None
) -> Tensor:
    """Rotations from each face camera's frame to the cube frame.

    ``R[k]`` has columns ``(r, b, a)``, so ``R[k] @ (x, y, z)_face = x r + y b + z a``: the face
    camera's OpenCV axes (right, down, forward) expressed in the cube frame. These are the rig
    rotations of six simulator cameras (front: none, back: yaw 180 deg, left: yaw -90 deg,
    right: yaw +90 deg, up: pitch +90 deg, down: pitch -90 deg).

    Args:
        dtype: floating dtype of the result (default: torch's default dtype).
        device: device of the result.

    Returns:
        ``(6, 3, 3)`` rotation matrices, faces in ``FACES`` order.
    """
    axes = face_axes(dtype, device)  # [6, (a, b, r), 3]
    return axes.flip(1).transpose(1, 2)  # columns (r, b, a)


def face_pixel_to_ray(
    face: int | Tensor, uv: Tensor, face_size: int, *, normalize: bool = False
) -> Tensor:
    """Ray of a (continuous) face pixel.

    ``ray = r (u - c) / f + b (v - c) / f + a`` with ``f = F / 2``, ``c = (F - 1) / 2``; the
    component along the face axis ``a`` is 1 unless ``normalize``. Any ``uv`` is accepted,
    including outside the face (the face's pinhole extended beyond its edges).

    Args:
        face: face index (into ``FACES``), an int or an integer tensor broadcastable with
            ``uv.shape[:-1]``.
        uv: ``(..., 2)`` face pixel coordinates ``(u, v)`` = (column, row), floating.
        face_size: ``F``, texels per face side.
        normalize: return unit rays.

    Returns:
        ``(..., 3)`` rays in the cube frame, dtype and device of ``uv``. Differentiable with
        respect to ``uv``.
    """
    _check_float_tensor(uv, "uv", last=2)
    face = _check_face(face)
    f, c = face_intrinsics(face_size)
    axes = face_axes(uv.dtype, uv.device)[face]  # [..., 3, 3]
    x = ((uv[..., 0] - c) / f).unsqueeze(-1)
    y = ((uv[..., 1] - c) / f).unsqueeze(-1)
    ray = axes[..., 2, :] * x + axes[..., 1, :] * y + axes[..., 0, :]  # [..., 3]
    if normalize:
        ray = ray / ray.norm(dim=-1, keepdim=True)  # norm >= 1: never zero
    return ray


def face_rays(
    face_size: int,
    *,
    pad: int = 0,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
    normalize: bool = False,
) -> Tensor:
    """Rays of every texel centre of every face, optionally of a padded face.

    Texel ``[k, i, j]`` is face ``k`` pixel ``(u, v) = (j - pad, i - pad)``: with ``pad > 0``
    the border texels are the face's own pinhole extended beyond its edge (as in
    `pad_faces`).

    Args:
        face_size: ``F``, texels per face side.
        pad: border width in texels.
        dtype: floating dtype (default: torch's default dtype).
        device: device of the result.
        normalize: return unit rays (otherwise the component along the face axis is 1).

    Returns:
        ``(6, F + 2 pad, F + 2 pad, 3)`` rays, faces in ``FACES`` order, indexed ``[face, v, u]``.
    """
    _check_face_size(face_size)
    _check_pad(pad)
    dtype = dtype or torch.get_default_dtype()
    n = face_size + 2 * pad
    t = torch.arange(n, dtype=dtype, device=device) - pad
    v, u = torch.meshgrid(t, t, indexing="ij")
    uv = torch.stack([u, v], dim=-1)  # [n, n, 2]
    face = torch.arange(6, device=device).view(6, 1, 1)
    return face_pixel_to_ray(face, uv, face_size, normalize=normalize)


def ray_to_face(rays: Tensor, face_size: int) -> tuple[Tensor, Tensor]:
    """Face hit by a ray and the continuous face pixel where it hits.

    The face is the one whose axis ``a`` is the ray's dominant signed axis. Ties (rays exactly
    on an edge or a corner of the cube) go to the x axis, then y, then z; both candidate faces
    see such a ray on their common edge (``u`` or ``v`` = ``-0.5`` or ``F - 0.5``), so the choice
    only matters for determinism. Then ``u = c + f (r . ray) / (a . ray)``,
    ``v = c + f (b . ray) / (a . ray)``, which lies in ``[-0.5, F - 0.5]``.

    Rays need not be unit. A zero ray gets face 0 (``FACES[0]``) and the face centre, with
    finite values and gradients; the caller masks it.

    Args:
        rays: ``(..., 3)`` directions in the cube frame, floating.
        face_size: ``F``, texels per face side.

    Returns:
        ``(face, uv)``: ``face`` ``(...)`` int64 index into ``FACES``; ``uv`` ``(..., 2)`` face
        pixel coordinates, dtype of ``rays``, differentiable with respect to ``rays`` (piecewise:
        the face is constant between seams).

    Examples:
        >>> face, uv = ray_to_face(torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]]), 4)
        >>> [FACES[k] for k in face.tolist()], uv.tolist()
        (['front', 'right'], [[1.5, 1.5], [-0.5, 1.5]])
    """
    _check_float_tensor(rays, "rays", last=3)
    f, c = face_intrinsics(face_size)
    mag = rays.detach().abs()
    ax, ay, az = mag.unbind(-1)
    use_x = (ax >= ay) & (ax >= az)
    use_y = ~use_x & (ay >= az)
    axis = torch.where(use_x, 0, torch.where(use_y, 1, 2))  # [...]
    comp = rays.detach().gather(-1, axis.unsqueeze(-1)).squeeze(-1)  # dominant component
    lut = torch.tensor(_AXIS_SIGN_TO_FACE, device=rays.device)
    face = lut[2 * axis + (comp < 0).long()]
    # The dominant component is zero only for the zero ray.
    face = torch.where(comp == 0, torch.zeros_like(face), face)

    # r, b and a are signed coordinate axes: select components instead of matrix products.
    lut = torch.tensor(_R_B_AXES, device=rays.device)[face]  # [..., 4]: ir, sr, ib, sb
    num = rays.gather(-1, lut[..., 0::2]) * lut[..., 1::2].to(rays.dtype)  # [..., 2]: r., b.
    # a . ray = |dominant component| (> 0 except for the zero ray: made safe before dividing)
    sign = torch.where(comp < 0, -1.0, 1.0).to(rays.dtype)
    depth = rays.gather(-1, axis.unsqueeze(-1)).squeeze(-1) * sign
    depth = torch.where(comp != 0, depth, torch.ones_like(depth))
    uv = c + f * num / depth.unsqueeze(-1)
    return face, uv
