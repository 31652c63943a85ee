"""Equirectangular (longitude-latitude) panorama: ``u = cx + fx lon``, ``v = cy + fy lat``.

``lon = atan2(x, z)`` (0 straight ahead, positive to the right), ``lat = atan2(y, |(x, z)|)``
(positive downwards, since y points down). A full 360 x 180 panorama of W x H pixels has
``fx = W / (2 pi)``, ``fy = H / pi``, ``cx = (W - 1) / 2``, ``cy = (H - 1) / 2``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ._base import CameraModel, check_inputs, check_positive, near_zero_radius, safe_sqrt

_NAMES = ("fx", "fy", "cx", "cy")


def equirectangular_project(points: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """Longitude and latitude of ``points``, scaled and shifted.

    Args:
        points: ``(..., 3)``.
        params: ``(..., 4)`` fx, fy, cx, cy.

    Returns:
        ``pixels (..., 2)`` and ``valid (...)``: every direction except the zero vector. At the
        poles, where longitude is undefined, ``lon = 0``.
    """
    check_inputs("equirectangular", points, params, 3, 4, "points")
    x, y, z = points.unbind(-1)
    h2 = x * x + z * z
    pole = near_zero_radius(h2, y * y)
    valid = (h2 + y * y) > torch.finfo(points.dtype).tiny
    zeros, ones = torch.zeros_like(x), torch.ones_like(x)
    lon = torch.where(pole, zeros, torch.atan2(torch.where(pole, zeros, x), torch.where(pole, ones, z)))
    lat = torch.atan2(torch.where(valid, y, ones), safe_sqrt(h2, ~pole))
    pixels = torch.stack((params[..., 0] * lon + params[..., 2],
                          params[..., 1] * lat + params[..., 3]), dim=-1)
    return pixels, valid


def equirectangular_unproject(pixels: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """Ray of longitude ``(u - cx) / fx`` and latitude ``(v - cy) / fy``.

    Returns:
        ``rays (..., 3)`` unit norm and ``valid (...)``: ``|lon| <= pi`` and ``|lat| <= pi / 2``.
    """
    check_inputs("equirectangular", pixels, params, 2, 4, "pixels")
    lon = (pixels[..., 0] - params[..., 2]) / params[..., 0]
    lat = (pixels[..., 1] - params[..., 3]) / params[..., 1]
    valid = (lon.abs() <= math.pi) & (lat.abs() <= math.pi / 2)
    c = torch.cos(lat)
    rays = torch.stack((c * torch.sin(lon), torch.sin(lat), c * torch.cos(lon)), dim=-1)
    return rays, valid


EQUIRECTANGULAR = CameraModel(
    "equirectangular", _NAMES, equirectangular_project, equirectangular_unproject,
    lambda p: torch.full(p.shape[:-1], math.pi, dtype=p.dtype, device=p.device),
    {"focal": (0, 1), "center": (2, 3)},
    check_values=lambda p: check_positive(p, (0, 1), _NAMES, "equirectangular"))
