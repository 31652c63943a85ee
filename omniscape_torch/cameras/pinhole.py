"""Pinhole camera: ``u = fx x / z + cx``, ``v = fy y / z + cy``, valid for z > 0.

The cube faces are pinhole cameras (DESIGN.md); so are rectified views.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ._base import CameraModel, check_inputs, check_positive, safe_div

_NAMES = ("fx", "fy", "cx", "cy")


def pinhole_project(points: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """Pinhole projection.

    Args:
        points: ``(..., 3)`` points in the camera frame (x right, y down, z forward).
        params: ``(..., 4)`` fx, fy, cx, cy.

    Returns:
        ``pixels (..., 2)`` and ``valid (...)``: z > 0. Invalid lanes sit at the principal point.
    """
    check_inputs("pinhole", points, params, 3, 4, "points")
    x, y, z = points.unbind(-1)
    valid = z > 0
    u = params[..., 0] * safe_div(x, z, valid) + params[..., 2]
    v = params[..., 1] * safe_div(y, z, valid) + params[..., 3]
    return torch.stack((u, v), dim=-1), valid


def pinhole_unproject(pixels: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """Pinhole unprojection: the unit ray through ``((u - cx) / fx, (v - cy) / fy, 1)``.

    Args:
        pixels: ``(..., 2)`` pixel coordinates (u, v).
        params: ``(..., 4)`` fx, fy, cx, cy.

    Returns:
        ``rays (..., 3)`` unit norm and ``valid (...)`` (always True).
    """
    check_inputs("pinhole", pixels, params, 2, 4, "pixels")
    mx = (pixels[..., 0] - params[..., 2]) / params[..., 0]
    my = (pixels[..., 1] - params[..., 3]) / params[..., 1]
    rays = torch.stack((mx, my, torch.ones_like(mx)), dim=-1)
    rays = rays * torch.rsqrt(1.0 + mx * mx + my * my).unsqueeze(-1)
    return rays, torch.ones_like(mx, dtype=torch.bool)


PINHOLE = CameraModel(
    "pinhole", _NAMES, pinhole_project, pinhole_unproject,
    lambda p: torch.full(p.shape[:-1], math.pi / 2, dtype=p.dtype, device=p.device),
    {"focal": (0, 1), "center": (2, 3)},
    check_values=lambda p: check_positive(p, (0, 1), _NAMES, "pinhole"), radial=True)
