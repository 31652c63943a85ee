"""The cube texels a camera reads: a cone around its optical axis that holds every texel its
layer reads (`camera_cone`), the texels of the cube within a cone (`cone_texels`), the
texels a layer's taps read for given rays and attitude (`read_texels`, a subset of the cone's),
and texels grown by their neighbours on each face (`grow_texels`).

`omniscape_torch.data.generate` renders only the texels each camera's layer reads
(`read_texels`; the layer's output is the same bit for bit as from whole faces:
tests/test_dataset.py, tests/test_cone.py).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .faces import face_axes
from .padding import border_plan

__all__ = ["camera_cone", "cone_texels", "grow_texels", "read_texels"]

#: `read_texels`: a tap coordinate within this many texels of a texel boundary reads the texels
#: on both sides (the layer computes its taps in float32, `read_texels` in float64: their
#: coordinates differ by about 1e-4 texels at F = 1024), and a ray whose second largest
#: component is within this share of its largest is looked up on both faces (the layer's choice
#: of face at a seam may differ by a rounding).
TAP_MARGIN, SEAM_MARGIN = 1e-3, 1e-5


def camera_cone(camera, face_size: int) -> float:
    """The half-angle (radians) of a cone around a camera's optical axis that holds every cube
    texel its layer reads at ``face_size``: the camera's widest angle (``Camera.max_angle``,
    its model's domain within its ``fov``, an upper bound of its valid pixels'), plus one and a
    half times the largest angle between neighbouring pixels along the image's centre row and
    column (a pixel's footprint, which ``sizing.visible_faces`` counts too, with room for the
    diagonal and the tangential direction) and two and a half texels at a face's centre
    (``2 / F`` radians each, the largest: the bilinear taps, within a texel of the ray, and the
    atlas border, resampled from the next face's texels within a texel and a half of the
    seam)."""
    h, w = camera.image_size
    cu, cv = (w - 1) / 2, (h - 1) / 2
    u = torch.arange(w, dtype=torch.float64)
    v = torch.arange(h, dtype=torch.float64)
    step = 0.0
    params = camera.params.detach().reshape(-1, camera.params.shape[-1])[0].double()
    for pixels in (torch.stack([u, torch.full_like(u, cv)], -1),
                   torch.stack([torch.full_like(v, cu), v], -1)):
        rays, valid = camera.model.unproject(pixels, params)
        rays = rays / rays.norm(dim=-1, keepdim=True)
        both = valid[1:] & valid[:-1]
        if both.any():
            cos = (rays[1:] * rays[:-1]).sum(-1)[both].clamp(-1, 1)
            step = max(step, float(torch.acos(cos).max()))
    widest = float(camera.max_angle().detach().reshape(-1)[0])
    return widest + 1.5 * step + 2.5 * (2.0 / face_size)


def cone_texels(face_size: int, axis: torch.Tensor, half_angle: float) -> torch.Tensor:
    """``(6, F, F)`` bool: the cube texels (cube axes = world) whose ray lies within
    ``half_angle`` radians of the unit vector ``axis (3,)`` (float32: its rounding is far
    below the margins of `camera_cone`)."""
    F = face_size
    if half_angle >= math.pi:
        return torch.ones(6, F, F, dtype=torch.bool)
    f, c = F / 2, (F - 1) / 2
    x = (torch.arange(F, dtype=torch.float32) - c) / f           # texel u (columns), v (rows)
    norm = torch.sqrt(1 + x.view(1, F) ** 2 + x.view(F, 1) ** 2) * math.cos(half_angle)
    axes = face_axes(torch.float64)                                # (6, [a, b, r], 3)
    proj = (axes @ axis.to(torch.float64).reshape(3)).float()     # (6, 3): a.A, b.A, r.A
    out = torch.empty(6, F, F, dtype=torch.bool)
    for k in range(6):   # a face at a time: no (6, F, F) float temporaries
        dot = proj[k, 2] * x.view(1, F) + proj[k, 1] * x.view(F, 1) + proj[k, 0]
        torch.ge(dot, norm, out=out[k])
    return out


def grow_texels(texels: torch.Tensor) -> torch.Tensor:
    """``texels (6, F, F)`` bool and their 8 neighbours on each face (a 3 x 3 dilation)."""
    grown = torch.nn.functional.max_pool2d(texels[:, None].float(), 3, stride=1, padding=1)
    return grown[:, 0] > 0


def read_texels(rays: torch.Tensor, valid: torch.Tensor, rotation: torch.Tensor | None,
                face_size: int, pad: int = 1) -> torch.Tensor:
    """``(6, F, F)`` bool: the cube texels that an ``OmniProjection`` of ``face_size`` and atlas
    border ``pad`` (``layer.pad``; bilinear RGB, nearest depth and labels, the border resampled
    from the next faces) reads for the camera-frame ``rays`` under ``rotation``: a superset of
    every texel the output depends on, so a cube rendered only there gives the layer's output
    bit for bit (the other texels may hold anything finite).

    Per valid ray: its face (both faces within `SEAM_MARGIN` of a seam) and face pixel
    ``(u, v)`` as the layer finds them (in float64), then the bilinear taps ``floor(u)``,
    ``floor(u) + 1`` (and the neighbour across a texel boundary within `TAP_MARGIN`), rows
    likewise; the nearest texel is one of them. A tap on the atlas border reads the texels its
    border texel is resampled from (``padding.border_plan``, bilinear and nearest). Far fewer
    texels than `cone_texels` where the cube is finer than the image (a texel read by no
    pixel's taps is not rendered): 22 % fewer for the rig's fisheyes at 1024 x 1024, 47 % for
    its catadioptric cameras.

    Args:
        rays: ``(..., 3)`` camera-frame directions (``layer.camera_rays()``: the sub-pixel
            rays, and the centre rays where they differ; call once per set and combine).
        valid: ``(...)`` bool, the rays the layer samples.
        rotation: ``(3, 3)`` camera -> cube frame (the layer's ``rotation``), or None.
        face_size: ``F``.
        pad: the layer's atlas border (0: no border).
    """
    F, p = int(face_size), int(pad)
    n = F + 2 * p
    # numpy, one thread: torch's elementwise kernels split over OpenMP threads, which a busy
    # machine makes many times slower (a camera at 1024 x 1024: 0.1 s quiet, 1.5 s at load 6)
    d = rays.detach().reshape(-1, 3)[valid.reshape(-1)].double().numpy()
    x, y, z = (np.ascontiguousarray(d[:, i]) for i in range(3))
    if rotation is not None:   # the rotation's float values, as the layer reads them
        r = torch.as_tensor(rotation).detach().double().reshape(3, 3).tolist()
        x, y, z = (r[i][0] * x + r[i][1] * y + r[i][2] * z for i in range(3))
    comps = (x, y, z)
    top = np.maximum(np.maximum(np.abs(x), np.abs(y)), np.abs(z))
    # the face table's axes are signed coordinate axes: a . p, r . p, b . p are components
    axes = face_axes(torch.float64).numpy()            # (6, [a, b, r], 3)

    def component(axis: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        i = int(np.abs(axis).argmax())
        value = comps[i] if rows is None else comps[i][rows]
        return value if axis[i] > 0 else -value

    # taps into faces padded by one more texel (m = n + 2, offset 1): no clipping
    m = n + 2
    padded = np.zeros(6 * m * m, dtype=bool)
    f, c = F / 2.0, (F - 1) / 2.0 + p + 1
    for k in range(6):
        # the rays of face k, and those within SEAM_MARGIN of it at a seam
        a = component(axes[k, 0])
        rays_k = np.flatnonzero((a >= top * (1 - SEAM_MARGIN)) & (a > 0))
        a = a[rays_k]
        u = c + f * component(axes[k, 2], rays_k) / a   # padded face pixel, offset 1
        v = c + f * component(axes[k, 1], rays_k) / a
        j_lo, i_lo = np.floor(u - TAP_MARGIN), np.floor(v - TAP_MARGIN)
        base = ((k * m + i_lo.astype(np.int64)) * m + j_lo.astype(np.int64))
        for step in (0, 1, m, m + 1):                 # the bilinear taps
            padded[base + step] = True
        # a third column or row where a tap coordinate lies within TAP_MARGIN of a boundary
        wide_j = np.floor(u + TAP_MARGIN) > j_lo
        wide_i = np.floor(v + TAP_MARGIN) > i_lo
        for step, wide in ((2, wide_j), (m + 2, wide_j), (2 * m, wide_i), (2 * m + 1, wide_i),
                           (2 * m + 2, wide_i & wide_j)):
            padded[base[wide] + step] = True
    padded = np.ascontiguousarray(padded.reshape(6, m, m)[:, 1:-1, 1:-1])
    out = padded[:, p:p + F, p:p + F].copy().reshape(-1)
    if p > 0:
        for mode in ("bilinear", "nearest"):
            plan = border_plan(F, p, mode)
            rows = padded.reshape(-1)[plan.dst_index.numpy()]
            src, weight = plan.src_index.numpy()[rows], plan.weight.numpy()[rows]
            out[src[weight != 0]] = True
    return torch.from_numpy(out.reshape(6, F, F))
