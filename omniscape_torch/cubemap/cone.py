"""The cube texels a camera reads: a cone around its optical axis that holds every texel its
layer reads (`camera_cone`), the texels of the cube within a cone (`cone_texels`) and texels
grown by their neighbours on each face (`grow_texels`); the margins (`TAP_MARGIN`,
`SEAM_MARGIN`) of the texels a layer's taps read for given rays and attitude
(`omniscape_torch.render.kernels.cone.read_texels`, a subset of the cone's).

`omniscape_torch.data.generate` renders only the texels each camera's layer reads (the layer's
output is the same bit for bit as from whole faces: tests/test_dataset.py, tests/test_cone.py).
"""

from __future__ import annotations

import math

import torch

from .faces import face_axes

__all__ = ["SEAM_MARGIN", "TAP_MARGIN", "camera_cone", "cone_texels", "grow_texels"]

#: ``render.kernels.cone.read_texels``: a tap coordinate within this many texels of a texel
#: boundary reads the texels on both sides (the layer computes its taps in float32,
#: ``read_texels`` in float64: their coordinates differ by about 1e-4 texels at F = 1024), and
#: a ray whose second largest component is within this share of its largest is looked up on
#: both faces (the layer's choice of face at a seam may differ by a rounding).
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
