"""Scaramuzza's polynomial model (OCamCalib), any degree.

Scaramuzza, Martinelli and Siegwart, "A toolbox for easily calibrating omnidirectional cameras",
IROS 2006. Parameters ``cx, cy, c, d, e, a0, a1, ..., aN``: the centre in (u, v) = (column, row)
order, OCamCalib's affine ``c, d, e`` and its direct polynomial ``f(rho) = a0 + a1 rho + ...``
exactly as ``calib_results.txt`` stores them (a0 < 0).

In OpenCV axes a sensor point ``(pu, pv)`` at radius ``rho = |(pu, pv)|`` pixels sees the ray
``(pu, pv, -f(rho))``; OCamCalib's own frame is (row, column, f) = (pv, pu, -z), so
``cam2world`` here is OCamCalib's with the axes renamed. The affine part maps the sensor to the
image: ``u = pu + e pv + cx``, ``v = d pu + c pv + cy`` (OCamCalib's ``row = c x + d y + xc``,
``col = e x + y + yc`` with x along rows).

``theta(rho) = atan2(rho, -f(rho))`` is the angle of the ray to the optical axis; the model is
valid while it grows: ``rho < rho_max``, the first zero of ``-f + rho f'``. Projection inverts
``theta(rho)`` by safeguarded Newton (no ``invpol`` needed), or, when OCamCalib's inverse
polynomial is given, evaluates it as OCamCalib's ``world2cam`` does.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ._base import (CameraModel, check_inputs, implicit_step, invert_monotone, polar, polyder,
                    polyval, safe_div, safe_sqrt, smallest_positive_root)

_NAMES = ("cx", "cy", "c", "d", "e", "a0")

#: Default maximum number of Newton iterations of the exact projection (safeguarded Newton).
SCARAMUZZA_ITERATIONS = 60


def _theta_of_rho(rho: Tensor, poly: Tensor) -> tuple[Tensor, Tensor]:
    """theta(rho) = atan2(rho, g), g = -f(rho), and d theta / d rho = (g - rho g') / (rho^2 + g^2)."""
    g = -polyval(poly, rho)
    dg = -polyval(polyder(poly), rho)
    return torch.atan2(rho, g), (g - rho * dg) / (rho * rho + g * g)


def scaramuzza_rho_max(params: Tensor) -> Tensor:
    """Sensor radius (pixels) where theta(rho) stops growing: the smallest positive root of
    ``-a0 + sum_i (i - 1) a_i rho^i``; inf when it never does."""
    poly = params[..., 5:]
    k = torch.arange(poly.shape[-1], dtype=poly.dtype, device=poly.device)
    coeffs = (k - 1) * poly
    coeffs = torch.cat((-poly[..., :1], coeffs[..., 1:]), dim=-1)
    return smallest_positive_root(coeffs, scale=poly[..., 0].detach().abs())


def _bracket(params: Tensor) -> tuple[Tensor, Tensor]:
    """(rho_max, theta_max); without a fold the bracket stops at 100 |a0| (170 degrees off a
    unit-slope lens' axis would need rho ~ 60 |a0|)."""
    poly = params[..., 5:].detach()
    rho_max = scaramuzza_rho_max(params)
    rho_max = torch.where(torch.isfinite(rho_max), rho_max, 100 * poly[..., 0].abs())
    return rho_max, _theta_of_rho(rho_max, poly)[0]


def scaramuzza_rho_limit(params: Tensor) -> Tensor:
    """The radius (pixels, after the affine map) where the unprojection's domain ends: valid
    pixels lie at ``rho < limit``."""
    return _bracket(params)[0]


def scaramuzza_max_angle(params: Tensor) -> Tensor:
    """theta(rho_max)."""
    return _bracket(params)[1]


def _affine(pu: Tensor, pv: Tensor, params: Tensor) -> Tensor:
    cx, cy, c, d, e = params[..., :5].unbind(-1)
    return torch.stack((pu + e * pv + cx, d * pu + c * pv + cy), dim=-1)


def scaramuzza_project(points: Tensor, params: Tensor, *, invpol: Tensor | None = None,
                       iterations: int = SCARAMUZZA_ITERATIONS) -> tuple[Tensor, Tensor]:
    """Project with the polynomial model.

    Args:
        points: ``(..., 3)`` points in the camera frame (OpenCV axes).
        params: ``(..., 6 + N)`` cx, cy, c, d, e, a0, ..., aN.
        invpol: optional ``(..., M)`` OCamCalib inverse polynomial (ascending, in
            ``t = atan(-z / rho)``); when given, ``rho = invpol(t)`` as OCamCalib's ``world2cam``,
            fast but only as exact as the fit (about 0.01 px); otherwise Newton, exact.
        iterations: maximum Newton iterations (fixed; see ``SCARAMUZZA_ITERATIONS``).

    Returns:
        ``pixels (..., 2)`` and ``valid (...)``: ``theta < theta(rho_max)`` and, without
        ``invpol``, Newton converged.
    """
    check_inputs("scaramuzza", points, params, 3, 6, "points", variadic=True)
    x, y, z = points.unbind(-1)
    rho, theta, axis = polar(points)
    rho_max, theta_max = _bracket(params)
    valid = theta < theta_max
    if invpol is not None:
        check_inputs("scaramuzza", points, invpol, 3, 1, "points", variadic=True)
        # OCamCalib's elevation: t = atan(z_ocam / rho) with z_ocam = -z.
        t = torch.atan(safe_div(-z, rho, ~axis))
        r = polyval(invpol, t)
        scale = safe_div(r, rho, ~axis)
    else:
        poly = params[..., 5:]
        target = torch.where(valid, theta, torch.zeros_like(theta))
        tol = 4 * torch.finfo(points.dtype).eps
        r, converged = invert_monotone(lambda q: _theta_of_rho(q, poly.detach()),
                                       target.detach(), rho_max, iterations, tol)
        # one more Newton step, with gradient (polish + implicit-function derivative)
        value, slope = _theta_of_rho(r, poly)
        r = implicit_step(r, value - target, slope)
        valid = valid & converged
        # rho / |(x, y)| -> -a0 / z on the axis (theta ~ rho / g(0) with g(0) = -a0).
        scale = torch.where(axis, safe_div(-poly[..., 0].expand_as(z), z, axis & valid),
                            safe_div(r, rho, ~axis))
    return _affine(x * scale, y * scale, params), valid


def scaramuzza_unproject(pixels: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """Unproject with the polynomial model (OCamCalib's ``cam2world``, OpenCV axes).

    Args:
        pixels: ``(..., 2)`` pixel coordinates (u, v).
        params: ``(..., 6 + N)`` cx, cy, c, d, e, a0, ..., aN.

    Returns:
        ``rays (..., 3)`` unit norm and ``valid (...)``: ``rho < rho_max``.
    """
    check_inputs("scaramuzza", pixels, params, 2, 6, "pixels", variadic=True)
    cx, cy, c, d, e = params[..., :5].unbind(-1)
    du, dv = pixels[..., 0] - cx, pixels[..., 1] - cy
    det = c - d * e
    pu = (c * du - e * dv) / det
    pv = (dv - d * du) / det
    rho2 = pu * pu + pv * pv
    rho = safe_sqrt(rho2, rho2 > torch.finfo(rho2.dtype).tiny)
    valid = rho < scaramuzza_rho_limit(params)
    g = -polyval(params[..., 5:], rho)
    rays = torch.stack((pu, pv, g), dim=-1)
    n2 = rho2 + g * g
    ok = n2 > 0
    rays = rays * torch.rsqrt(torch.where(ok, n2, torch.ones_like(n2))).unsqueeze(-1)
    return rays, valid & ok


def _check_values(params: Tensor) -> None:
    if bool((params[..., 5] >= 0).any()):
        raise ValueError(f"params: a0 of the scaramuzza model must be < 0 (OCamCalib's sign: the "
                         f"scene is at -z in its frame), got {params[..., 5].cpu().tolist()}")
    det = params[..., 2] - params[..., 3] * params[..., 4]
    if bool((det <= 0).any()):
        raise ValueError(f"params: the affine matrix of the scaramuzza model must have "
                         f"c - d * e > 0, got {det.cpu().tolist()}")


SCARAMUZZA = CameraModel(
    "scaramuzza", _NAMES, scaramuzza_project, scaramuzza_unproject, scaramuzza_max_angle,
    {"center": (0, 1), "affine": (2, 3, 4)}, variadic=True, check_values=_check_values,
    domain_end=scaramuzza_rho_limit, radial=True)
