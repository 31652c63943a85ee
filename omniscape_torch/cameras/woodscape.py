"""WoodScape's fisheye model, ``radial_poly``: a polynomial in the angle, in pixels.

WoodScape (Yogamani et al., ICCV 2019; ``valeoai/WoodScape``, MIT licence), its
``scripts/calibration/calibration_readme.txt`` and ``projection.py``: a point ``(x, y, z)`` of the
camera frame (OpenCV axes) at angle ``theta = atan2(chi, z)`` from the optical axis,
``chi = sqrt(x^2 + y^2)``, lands at the distance

    rho(theta) = k1 theta + k2 theta^2 + k3 theta^3 + k4 theta^4      (pixels)

from the principal point, in the direction of its ``(x, y)``:

    u = cx + rho x / chi,        v = cy + aspect_ratio rho y / chi.

Every power of ``theta`` appears (Kannala-Brandt has the odd ones only), and the coefficients are
in pixels (``k1`` is the focal length, pixels per radian at the axis). WoodScape's files give the
principal point as an offset from the image centre: ``cx = W / 2 - 0.5 + cx_offset``,
``cy = H / 2 - 0.5 + cy_offset``, the top-left pixel's centre at (0, 0) as in this package
(``ot.cameras.read_woodscape`` converts). ``theta`` comes from ``atan2``, so points behind the
camera keep their angle; the model is valid for ``theta < min(pi, fold)``, the fold the first
``theta > 0`` where ``d rho / d theta = k1 + 2 k2 theta + 3 k3 theta^2 + 4 k4 theta^3`` vanishes
(beyond it ``rho`` shrinks and two angles would share a pixel). ``k1 > 0`` and
``aspect_ratio > 0``.

The inverse is safeguarded Newton on the polynomial (``_base.invert_monotone``: a step that
leaves the bracket ``[0, limit]`` is a bisection), at most ``WOODSCAPE_ITERATIONS`` steps; a
pixel whose solve has not converged is invalid. WoodScape's own ``projection.py`` takes the
smallest real root of the quartic with ``numpy.roots`` instead (``tests/test_woodscape.py``
compares the two).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ._base import (CameraModel, check_inputs, check_positive, implicit_step, invert_monotone,
                    near_zero_radius, polar, safe_div, safe_sqrt, smallest_positive_root)

_NAMES = ("cx", "cy", "aspect_ratio", "k1", "k2", "k3", "k4")

#: Maximum Newton iterations of the inverse. Safeguarded Newton converges quadratically away
#: from the fold and at least halves its bracket near it: 60 steps reach the float64
#: tolerance wherever the inverse is defined (tests/test_cameras.py, the registry battery).
WOODSCAPE_ITERATIONS = 60


def _rho(theta: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """``rho(theta)`` and ``d rho / d theta`` (pixels, pixels per radian), Horner's scheme."""
    k1, k2, k3, k4 = (params[..., i] for i in range(3, 7))
    rho = theta * (k1 + theta * (k2 + theta * (k3 + theta * k4)))
    slope = k1 + theta * (2.0 * k2 + theta * (3.0 * k3 + theta * (4.0 * k4)))
    return rho, slope


def woodscape_max_angle(params: Tensor) -> Tensor:
    """``min(pi, fold)``, the fold the smallest positive root of ``d rho / d theta`` (0 where
    ``k1 <= 0``: no angle is imaged); no gradient."""
    with torch.no_grad():
        p = params.detach()
        k1 = p[..., 3]
        good = k1 > 0
        ones = torch.ones_like(k1)
        derivative = torch.stack((torch.where(good, k1, ones), 2.0 * p[..., 4], 3.0 * p[..., 5],
                                  4.0 * p[..., 6]), -1)
        fold = smallest_positive_root(derivative)
        return torch.where(good, fold.clamp(max=math.pi), torch.zeros_like(k1))


def woodscape_domain_end(params: Tensor) -> Tensor:
    """``rho(max_angle)`` in pixels: valid pixels lie at ``|(u - cx, (v - cy) / aspect_ratio)|``
    below it (the radius ``render.kernels.radial_table`` tabulates in)."""
    with torch.no_grad():
        return _rho(woodscape_max_angle(params), params.detach())[0]


def woodscape_project(points: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """WoodScape projection: ``u = cx + rho(theta) x / chi``, ``v = cy + aspect_ratio
    rho(theta) y / chi``, ``rho(theta) = k1 theta + k2 theta^2 + k3 theta^3 + k4 theta^4``
    (module docstring).

    Args:
        points: ``(..., 3)`` points in the camera frame (OpenCV: x right, y down, z forward).
        params: ``(..., 7)`` cx, cy, aspect_ratio, k1, k2, k3, k4 (pixels; aspect_ratio
            unitless).

    Returns:
        ``pixels (..., 2)`` and ``valid (...)``: ``theta < min(pi, fold)``.
    """
    check_inputs("woodscape", points, params, 3, 7, "points")
    cx, cy, aspect, k1 = params[..., 0], params[..., 1], params[..., 2], params[..., 3]
    x, y, z = points.unbind(-1)
    chi, theta, axis = polar(points)
    valid = theta < woodscape_max_angle(params)
    rho = _rho(torch.where(valid, theta, torch.zeros_like(theta)), params)[0]
    # rho / chi, whose limit on the axis is rho'(0) / z = k1 / z
    scale = torch.where(axis, safe_div(k1 * torch.ones_like(z), z, axis & valid),
                        safe_div(rho, chi, ~axis))
    pixels = torch.stack((cx + x * scale, cy + aspect * y * scale), dim=-1)
    return pixels, valid


def woodscape_unproject(pixels: Tensor, params: Tensor, *,
                        iterations: int = WOODSCAPE_ITERATIONS) -> tuple[Tensor, Tensor]:
    """WoodScape unprojection: ``rho(theta) = |(u - cx, (v - cy) / aspect_ratio)|`` solved by
    safeguarded Newton on ``[0, min(pi, fold)]`` (module docstring), then one Newton step with
    gradient (the implicit function theorem's derivative to the pixels and parameters).

    Args:
        pixels: ``(..., 2)`` pixel coordinates (u, v).
        params: ``(..., 7)`` cx, cy, aspect_ratio, k1, k2, k3, k4.
        iterations: maximum Newton iterations (fixed; see ``WOODSCAPE_ITERATIONS``).

    Returns:
        ``rays (..., 3)`` unit norm and ``valid (...)``: the radius below ``rho(limit)`` and
        Newton converged.
    """
    check_inputs("woodscape", pixels, params, 2, 7, "pixels")
    cx, cy, aspect, k1 = params[..., 0], params[..., 1], params[..., 2], params[..., 3]
    mx = pixels[..., 0] - cx
    my = (pixels[..., 1] - cy) / aspect
    r2 = mx * mx + my * my
    axis = near_zero_radius(r2, (k1 * k1).detach())
    r = safe_sqrt(r2, ~axis)
    limit = woodscape_max_angle(params)
    inside = r < woodscape_domain_end(params)
    target = torch.where(inside, r, torch.zeros_like(r))
    theta, converged = invert_monotone(lambda th: _rho(th, params.detach()), target.detach(),
                                       limit, iterations, 8 * torch.finfo(params.dtype).eps)
    value, slope = _rho(theta, params)
    theta = implicit_step(theta, value - target, slope)
    valid = inside & converged
    theta = torch.where(valid, theta, torch.zeros_like(theta))
    # sin(theta) / r -> theta'(0) = 1 / k1 on the axis
    ones = torch.ones_like(r)
    sin_over_r = torch.where(axis, safe_div(ones, k1 * ones, k1 * ones > 0),
                             safe_div(torch.sin(theta), r, ~axis))
    rays = torch.stack((mx * sin_over_r, my * sin_over_r, torch.cos(theta)), dim=-1)
    return rays, valid


def _check(params: Tensor) -> None:
    check_positive(params, (2, 3), _NAMES, "woodscape")


WOODSCAPE = CameraModel(
    "woodscape", _NAMES, woodscape_project, woodscape_unproject, woodscape_max_angle,
    {"center": (0, 1), "focal": (2, 3), "distortion": (4, 5, 6)}, check_values=_check,
    domain_end=woodscape_domain_end, radial=True)
