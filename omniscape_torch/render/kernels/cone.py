"""The cube texels a layer reads (`read_texels`): the texels its bilinear taps touch, the C++ op
``cone_taps`` with its schema, fake implementation and NumPy reference twin side by side, and
the texels of the atlas border those taps read through.

Per ray (float64, as the layer would find its texel to within a rounding): its face (both faces
where its second largest component is within ``seam_margin`` of its largest), its padded face
pixel ``(u, v)``, then the taps ``floor(u - tap_margin)`` and the next column (and a third where
``u + tap_margin`` crosses a texel boundary), rows likewise. The texels are marked in faces
padded by the atlas border ``pad`` and one texel more (``(6, F + 2 pad + 2, F + 2 pad + 2)``),
so no tap needs clipping.

The twin is the NumPy code the op replaced; the two mark the same texels (the same float64
operations in the same order: ``-ffp-contract=off``), tests/test_cone.py. A ray with a
component that is not finite, or the zero ray, touches nothing on either route.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ...cubemap.cone import SEAM_MARGIN, TAP_MARGIN
from ...cubemap.faces import face_axes
from ...cubemap.padding import border_plan
from . import build
from ._backend import choose

__all__ = ["OPS", "cone_taps", "read_texels"]

#: The op's schema, defined here in the package's namespace (implemented in C++ for the CPU):
#: ``faces (6, 3)`` int64 the signed coordinate axes ``a, b, r`` of each face (``i + 1`` for
#: ``+e_i``, ``-(i + 1)`` for ``-e_i``); ``near`` is ``1 - seam_margin``.
OPS = {
    "cone_taps": "(Tensor rays, Tensor? valid, Tensor? rotation, Tensor faces, int face_size, "
                 "int pad, float tap_margin, float near, Tensor(a!) padded) -> ()",
}


def _fake_cone_taps(rays, valid, rotation, faces, face_size, pad, tap_margin, near,
                    padded) -> None:
    m = face_size + 2 * pad + 2
    torch._check(rays.dim() == 2 and rays.shape[1] == 3 and padded.shape == (6, m, m),
                 lambda: f"{build.NAMESPACE}: cone_taps: expected rays (n, 3), padded "
                         f"(6, {m}, {m})")


#: The op's fake implementation (for ``torch.compile``), registered with its schema.
_FAKES = {"cone_taps": _fake_cone_taps}
_LIBRARY = build.define(OPS, _FAKES)   # the registration's handle: the op lives while it does


def read_texels(rays: Tensor, valid: Tensor, rotation: Tensor | None, face_size: int,
                pad: int = 1, *, backend: str = "auto") -> Tensor:
    """``(6, F, F)`` bool: the cube texels that an ``OmniProjection`` of ``face_size`` and atlas
    border ``pad`` (``layer.pad``; bilinear RGB, nearest depth and labels, the border resampled
    from the next faces) reads for the camera-frame ``rays`` under ``rotation``: a superset of
    every texel the output depends on, so a cube rendered only there gives the layer's output
    bit for bit (the other texels may hold anything finite).

    Per valid ray: its face (both faces within ``cubemap.cone.SEAM_MARGIN`` of a seam) and face
    pixel ``(u, v)`` as the layer finds them (in float64), then the bilinear taps
    ``floor(u)``, ``floor(u) + 1`` (and the neighbour across a texel boundary within
    ``cubemap.cone.TAP_MARGIN``), rows likewise (`cone_taps`); the nearest texel is one of
    them. A tap on the atlas border reads the texels its border texel is resampled from
    (``padding.border_plan``, bilinear and nearest). Far fewer texels than
    ``cubemap.cone.cone_texels`` where the cube is finer than the image (a texel read by no
    pixel's taps is not rendered): 22 % fewer for the rig's fisheyes at 1024 x 1024, 47 % for
    its catadioptric cameras.

    Args:
        rays: ``(..., 3)`` camera-frame directions (``layer.camera_rays()``: the sub-pixel
            rays, and the centre rays where they differ; call once per set and combine).
        valid: ``(...)`` bool, the rays the layer samples.
        rotation: ``(3, 3)`` camera -> cube frame (the layer's ``rotation``), or None.
        face_size: ``F``.
        pad: the layer's atlas border (0: no border).
        backend: ``"auto"`` (default), ``"cpp"`` or ``"torch"``: the taps' C++ op or its
            NumPy twin (the same texels).
    """
    F, p = int(face_size), int(pad)
    padded = cone_taps(rays, valid, rotation, F, p, TAP_MARGIN, SEAM_MARGIN, backend=backend)
    padded = np.ascontiguousarray(padded[:, 1:-1, 1:-1])
    out = padded[:, p:p + F, p:p + F].copy().reshape(-1)
    if p > 0:
        for mode in ("bilinear", "nearest"):
            plan = border_plan(F, p, mode)
            rows = padded.reshape(-1)[plan.dst_index.numpy()]
            src, weight = plan.src_index.numpy()[rows], plan.weight.numpy()[rows]
            out[src[weight != 0]] = True
    return torch.from_numpy(out.reshape(6, F, F))


def _signed_axes(axes: np.ndarray) -> np.ndarray:
    """``(6, 3)`` int64 codes of the face table's signed coordinate axes ``a, b, r``."""
    index = np.abs(axes).argmax(-1)                                  # (6, 3)
    sign = np.take_along_axis(axes, index[..., None], -1)[..., 0]
    return np.where(sign > 0, index + 1, -(index + 1)).astype(np.int64)


def cone_taps(rays: Tensor, valid: Tensor | None, rotation: Tensor | None, face_size: int,
              pad: int, tap_margin: float, seam_margin: float, *,
              backend: str = "auto") -> np.ndarray:
    """``(6, F + 2 pad + 2, F + 2 pad + 2)`` bool NumPy array: the texels that the bilinear taps
    of ``rays`` touch, in faces padded by ``pad`` and one texel more (module docstring).

    Args:
        rays: ``(..., 3)`` float32 or float64 camera-frame directions (need not be unit).
        valid: ``(...)`` bool, the rays to look up (None: every ray).
        rotation: ``(3, 3)`` camera -> cube frame, applied in float64, or None.
        face_size: ``F``, a positive integer.
        pad: the atlas border, a non-negative integer.
        tap_margin: a tap coordinate within this many texels of a texel boundary reads both
            sides.
        seam_margin: a ray whose second largest component is within this share of its largest
            is looked up on both faces.
        backend: ``"auto"``, ``"cpp"`` or ``"torch"`` (the NumPy twin).
    """
    if not isinstance(rays, Tensor) or rays.dtype not in (torch.float32, torch.float64) or \
            rays.shape[-1:] != (3,):
        raise ValueError(f"rays: expected a (..., 3) float32 or float64 tensor, got "
                         f"{getattr(rays, 'dtype', type(rays).__name__)} "
                         f"{tuple(getattr(rays, 'shape', ()))}")
    if valid is not None and (not isinstance(valid, Tensor) or valid.dtype != torch.bool
                              or valid.shape != rays.shape[:-1]):
        raise ValueError(f"valid: expected a bool tensor of shape {tuple(rays.shape[:-1])}, "
                         f"got {getattr(valid, 'dtype', type(valid).__name__)} "
                         f"{tuple(getattr(valid, 'shape', ()))}")
    if rotation is not None:
        rotation = torch.as_tensor(rotation).detach()
        if rotation.shape != (3, 3) or not rotation.is_floating_point():
            raise ValueError(f"rotation: expected a (3, 3) floating tensor or None, got "
                             f"{rotation.dtype} {tuple(rotation.shape)}")
        rotation = rotation.double().cpu()
    for name, value, low in (("face_size", face_size, 1), ("pad", pad, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name}: expected an integer >= {low}, got {value!r}")
    for name, value in (("tap_margin", tap_margin), ("seam_margin", seam_margin)):
        if not 0 <= float(value) < 0.5:
            raise ValueError(f"{name}: expected a value in [0, 0.5), got {value!r}")
    axes = face_axes(torch.float64).numpy()            # (6, [a, b, r], 3)
    rays = rays.detach().reshape(-1, 3).cpu()
    valid = None if valid is None else valid.detach().reshape(-1).cpu()
    m = face_size + 2 * pad + 2
    ops = choose(backend, rays, what="cone taps")
    if ops is None:
        return _cone_taps_numpy(rays, valid, rotation, axes, face_size, pad, float(tap_margin),
                                float(seam_margin))
    padded = torch.zeros(6, m, m, dtype=torch.bool)
    ops.cone_taps(rays.contiguous(), None if valid is None else valid.contiguous(), rotation,
                  torch.from_numpy(_signed_axes(axes)), face_size, pad, float(tap_margin),
                  1.0 - float(seam_margin), padded)
    return padded.numpy()


def _cone_taps_numpy(rays: Tensor, valid: Tensor | None, rotation: Tensor | None,
                     axes: np.ndarray, F: int, p: int, tap_margin: float,
                     seam_margin: float) -> np.ndarray:
    """`cone_taps` in NumPy, on one thread."""
    with np.errstate(invalid="ignore"):   # rays that are not finite: masked out below
        return _taps_numpy(rays, valid, rotation, axes, F, p, tap_margin, seam_margin)


def _taps_numpy(rays: Tensor, valid: Tensor | None, rotation: Tensor | None, axes: np.ndarray,
                F: int, p: int, tap_margin: float, seam_margin: float) -> np.ndarray:
    d = (rays if valid is None else rays[valid]).double().numpy()
    x, y, z = (np.ascontiguousarray(d[:, i]) for i in range(3))
    if rotation is not None:   # the rotation's float values, as the layer reads them
        r = rotation.tolist()
        x, y, z = (r[i][0] * x + r[i][1] * y + r[i][2] * z for i in range(3))
    comps = (x, y, z)
    finite = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
    top = np.maximum(np.maximum(np.abs(x), np.abs(y)), np.abs(z))

    def component(axis: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        i = int(np.abs(axis).argmax())
        value = comps[i] if rows is None else comps[i][rows]
        return value if axis[i] > 0 else -value

    m = F + 2 * p + 2
    padded = np.zeros(6 * m * m, dtype=bool)
    f, c = F / 2.0, (F - 1) / 2.0 + p + 1
    for k in range(6):
        # the rays of face k, and those within seam_margin of it at a seam
        a = component(axes[k, 0])
        rays_k = np.flatnonzero((a >= top * (1 - seam_margin)) & (a > 0) & finite)
        a = a[rays_k]
        u = c + f * component(axes[k, 2], rays_k) / a   # padded face pixel, offset 1
        v = c + f * component(axes[k, 1], rays_k) / a
        j_lo, i_lo = np.floor(u - tap_margin), np.floor(v - tap_margin)
        base = ((k * m + i_lo.astype(np.int64)) * m + j_lo.astype(np.int64))
        for step in (0, 1, m, m + 1):                 # the bilinear taps
            padded[base + step] = True
        # a third column or row where a tap coordinate lies within tap_margin of a boundary
        wide_j = np.floor(u + tap_margin) > j_lo
        wide_i = np.floor(v + tap_margin) > i_lo
        for step, wide in ((2, wide_j), (m + 2, wide_j), (2 * m, wide_i), (2 * m + 1, wide_i),
                           (2 * m + 2, wide_i & wide_j)):
            padded[base[wide] + step] = True
    return padded.reshape(6, m, m)
