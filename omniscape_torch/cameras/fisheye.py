"""Fisheyes with radial, tangential and thin-prism distortion: ``thin_prism_fisheye`` and
``fisheye624``.

A point at angle ``theta = atan2(|(x, y)|, z)`` from the optical axis goes to the equidistant
plane, ``(a, b) = theta (x, y) / |(x, y)|`` (``atan2``: past 90 degrees, as ``kannala_brandt``),
is distorted there, then scaled by ``(fx, fy)`` and shifted by ``(cx, cy)``. With ``t = a^2 +
b^2 = theta^2``:

* ``thin_prism_fisheye`` (fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1, sy1), COLMAP
  ``THIN_PRISM_FISHEYE`` (Weng, Cohen and Herniou, "Camera calibration with distortion models
  and accuracy evaluation", TPAMI 1992)::

      R  = 1 + k1 t + k2 t^2 + k3 t^3 + k4 t^4
      xd = a R + 2 p1 a b + p2 (t + 2 a^2) + sx1 t
      yd = b R + 2 p2 a b + p1 (t + 2 b^2) + sy1 t

  With p = s = 0 it is ``kannala_brandt`` with (k1, k2, k3, k4).
* ``fisheye624`` (fx, fy, cx, cy, k0, ..., k5, p0, p1, s0, s1, s2, s3), Project Aria's
  ``FisheyeRadTanThinPrism`` (projectaria_tools ``FisheyeRadTanThinPrism.h``; with fx = fy),
  COLMAP ``RAD_TAN_THIN_PRISM_FISHEYE``, nerfstudio ``FISHEYE624``: the radial part first,
  then tangential and thin prism on the *distorted* point::

      (x, y) = (a, b) (1 + k0 t + k1 t^2 + ... + k5 t^6),  r2 = x^2 + y^2
      xd = x + 2 p1 x y + p0 (r2 + 2 x^2) + s0 r2 + s1 r2^2
      yd = y + 2 p0 x y + p1 (r2 + 2 y^2) + s2 r2 + s3 r2^2

  With p = s = 0 and k4 = k5 = 0 it is ``kannala_brandt`` with (k1, k2, k3, k4) = (k0, k1, k2,
  k3).

Valid set: ``theta < min(pi, fold)``, the fold being the first zero of the radial part's
``d(theta R) / d theta`` (as Kannala-Brandt's), so ``max_angle`` is that limit. Unprojection:
2-D Newton on the distortion of the equidistant plane with its 2 x 2 Jacobian
(``_base.undistort_2d``, as COLMAP's ``IterativeUndistortion``), started from the radial
inverse, at most ``FISHEYE_ITERATIONS`` steps, invalid where it did not converge; then
``ray = (a sin(theta) / theta, b sin(theta) / theta, cos(theta))``, ``theta = |(a, b)|``.
COLMAP's own fisheye models take ``theta = atan(r / z)`` and so stop at 90 degrees.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ._base import (CameraModel, check_inputs, check_positive, near_zero_radius, polar,
                    polyder, polyval, safe_div, safe_sqrt, series_or, smallest_positive_root,
                    undistort_2d)

#: Default maximum number of 2-D Newton iterations of the undistortion: started from the radial
#: inverse, it converges quadratically away from the fold (fewer than 10 steps to float64
#: precision in tests/test_cameras.py); 50 leave room near the fold, where it slows down.
FISHEYE_ITERATIONS = 50

_GROUPS = {"focal": (0, 1), "center": (2, 3)}
_TPF_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "sx1", "sy1")
_F624_NAMES = ("fx", "fy", "cx", "cy", "k0", "k1", "k2", "k3", "k4", "k5", "p0", "p1",
               "s0", "s1", "s2", "s3")


def _radial_coeffs(model: str, c: Tensor) -> Tensor:
    """Ascending coefficients ``(1, k...)`` of ``R(t)``, ``r(theta) = theta R(theta^2)``, from
    the distortion coefficients ``c`` (params[..., 4:])."""
    ks = c[..., [0, 1, 4, 5]] if model == "thin_prism_fisheye" else c[..., 0:6]
    return torch.cat((torch.ones_like(ks[..., :1]), ks), -1)


def _tpf_distort(a: Tensor, b: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
    k1, k2, p1, p2, k3, k4, sx1, sy1 = c.unbind(-1)
    t = a * a + b * b
    radial = 1 + t * (k1 + t * (k2 + t * (k3 + t * k4)))
    ab = a * b
    return (a * radial + 2 * p1 * ab + p2 * (t + 2 * a * a) + sx1 * t,
            b * radial + 2 * p2 * ab + p1 * (t + 2 * b * b) + sy1 * t)


def _f624_distort(a: Tensor, b: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
    k0, k1, k2, k3, k4, k5, p0, p1, s0, s1, s2, s3 = c.unbind(-1)
    t = a * a + b * b
    radial = 1 + t * (k0 + t * (k1 + t * (k2 + t * (k3 + t * (k4 + t * k5)))))
    x, y = a * radial, b * radial
    r2 = x * x + y * y
    xy = x * y
    return (x + 2 * p1 * xy + p0 * (r2 + 2 * x * x) + r2 * (s0 + s1 * r2),
            y + 2 * p0 * xy + p1 * (r2 + 2 * y * y) + r2 * (s2 + s3 * r2))


def _tpf_jacobian(a: Tensor, b: Tensor, c: Tensor):
    """`_tpf_distort` and its Jacobian ``d(xd, yd) / d(a, b)``, written out."""
    k1, k2, p1, p2, k3, k4, sx1, sy1 = c.unbind(-1)
    t = a * a + b * b
    radial = 1 + t * (k1 + t * (k2 + t * (k3 + t * k4)))
    radial_t = k1 + t * (2 * k2 + t * (3 * k3 + 4 * t * k4))
    ab = a * b
    cross = 2 * ab * radial_t
    return (a * radial + 2 * p1 * ab + p2 * (t + 2 * a * a) + sx1 * t,
            b * radial + 2 * p2 * ab + p1 * (t + 2 * b * b) + sy1 * t,
            radial + 2 * a * a * radial_t + 2 * p1 * b + 6 * p2 * a + 2 * sx1 * a,
            cross + 2 * p1 * a + 2 * p2 * b + 2 * sx1 * b,
            cross + 2 * p2 * b + 2 * p1 * a + 2 * sy1 * a,
            radial + 2 * b * b * radial_t + 2 * p2 * a + 6 * p1 * b + 2 * sy1 * b)


def _f624_jacobian(a: Tensor, b: Tensor, c: Tensor):
    """`_f624_distort` and its Jacobian ``d(xd, yd) / d(a, b)``: the tangential and
    thin-prism map's Jacobian times the radial map's."""
    k0, k1, k2, k3, k4, k5, p0, p1, s0, s1, s2, s3 = c.unbind(-1)
    t = a * a + b * b
    radial = 1 + t * (k0 + t * (k1 + t * (k2 + t * (k3 + t * (k4 + t * k5)))))
    radial_t = k0 + t * (2 * k1 + t * (3 * k2 + t * (4 * k3 + t * (5 * k4 + 6 * t * k5))))
    x, y = a * radial, b * radial
    # d(x, y) / d(a, b)
    r11, r12 = radial + 2 * a * a * radial_t, 2 * a * b * radial_t
    r22 = radial + 2 * b * b * radial_t
    r2 = x * x + y * y
    xy = x * y
    gx, gy = s0 + 2 * s1 * r2, s2 + 2 * s3 * r2
    # d(xd, yd) / d(x, y)
    t11 = 1 + 2 * p1 * y + 6 * p0 * x + 2 * gx * x
    t12 = 2 * p1 * x + 2 * p0 * y + 2 * gx * y
    t21 = 2 * p0 * y + 2 * p1 * x + 2 * gy * x
    t22 = 1 + 2 * p0 * x + 6 * p1 * y + 2 * gy * y
    return (x + 2 * p1 * xy + p0 * (r2 + 2 * x * x) + r2 * (s0 + s1 * r2),
            y + 2 * p0 * xy + p1 * (r2 + 2 * y * y) + r2 * (s2 + s3 * r2),
            t11 * r11 + t12 * r12, t11 * r12 + t12 * r22,
            t21 * r11 + t22 * r12, t21 * r12 + t22 * r22)


_JACOBIANS = {"thin_prism_fisheye": _tpf_jacobian, "fisheye624": _f624_jacobian}


def _radial_fn(model: str):
    def radial(theta: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
        coeffs = _radial_coeffs(model, c)
        t = theta * theta
        p = polyval(coeffs, t)
        return theta * p, p + 2 * t * polyval(polyder(coeffs), t)
    return radial


def _max_angle(model: str, params: Tensor) -> Tensor:
    """min(pi, fold): the first theta > 0 where ``d(theta R(theta^2)) / d theta = 0``, i.e. the
    smallest positive root of ``sum (2 i + 1) c_i t^i`` at ``t = theta^2``."""
    coeffs = _radial_coeffs(model, params[..., 4:].detach())
    odd = torch.arange(coeffs.shape[-1], dtype=params.dtype, device=params.device) * 2 + 1
    return torch.sqrt(smallest_positive_root(coeffs * odd)).clamp(max=math.pi)


def _project(model: str, distort, points: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    x, y, z = points.unbind(-1)
    rho, theta, axis = polar(points)
    valid = theta < _max_angle(model, params)
    theta = torch.where(valid, theta, torch.zeros_like(theta))
    ones = torch.ones_like(rho)
    # theta / rho, whose limit on the axis is 1 / z
    scale = torch.where(axis, safe_div(ones, z, axis & valid), safe_div(theta, rho, ~axis))
    xd, yd = distort(x * scale, y * scale, params[..., 4:])
    u = params[..., 0] * xd + params[..., 2]
    v = params[..., 1] * yd + params[..., 3]
    return torch.stack((u, v), -1), valid


def _unproject(model: str, distort, pixels: Tensor, params: Tensor, iterations: int
               ) -> tuple[Tensor, Tensor]:
    xd = (pixels[..., 0] - params[..., 2]) / params[..., 0]
    yd = (pixels[..., 1] - params[..., 3]) / params[..., 1]
    limit = _max_angle(model, params)
    a, b, valid = undistort_2d(xd, yd, params[..., 4:], distort, _radial_fn(model),
                               limit * limit, iterations, _JACOBIANS[model])
    t = a * a + b * b
    valid = valid & (t < limit * limit)
    small = near_zero_radius(t, 1.0)
    theta = safe_sqrt(t, ~small)
    sinc = series_or(theta, small | (theta < 1e-3), lambda s: torch.sin(s) / s,
                     lambda s: 1 - s * s / 6 + s ** 4 / 120)
    zero = torch.zeros_like(a)
    rays = torch.stack((torch.where(valid, a * sinc, zero), torch.where(valid, b * sinc, zero),
                        torch.where(valid, torch.cos(theta), zero + 1)), -1)
    return rays, valid


def thin_prism_fisheye_project(points: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """Thin-prism fisheye projection (COLMAP ``THIN_PRISM_FISHEYE``, with ``atan2``).

    Args:
        points: ``(..., 3)`` points in the camera frame.
        params: ``(..., 12)`` fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1, sy1.

    Returns:
        ``pixels (..., 2)`` and ``valid (...)``: ``theta < min(pi, fold)``.
    """
    check_inputs("thin_prism_fisheye", points, params, 3, 12, "points")
    return _project("thin_prism_fisheye", _tpf_distort, points, params)


def thin_prism_fisheye_unproject(pixels: Tensor, params: Tensor, *,
                                 iterations: int = FISHEYE_ITERATIONS) -> tuple[Tensor, Tensor]:
    """Thin-prism fisheye unprojection: 2-D Newton on the distortion, then the ray.

    Args:
        pixels: ``(..., 2)``.
        params: ``(..., 12)`` fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1, sy1.
        iterations: maximum Newton iterations (see ``FISHEYE_ITERATIONS``).

    Returns:
        ``rays (..., 3)`` unit norm and ``valid (...)``: converged, ``theta < min(pi, fold)``.
    """
    check_inputs("thin_prism_fisheye", pixels, params, 2, 12, "pixels")
    return _unproject("thin_prism_fisheye", _tpf_distort, pixels, params, iterations)


def fisheye624_project(points: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """Fisheye624 projection (Project Aria ``FisheyeRadTanThinPrism``, COLMAP
    ``RAD_TAN_THIN_PRISM_FISHEYE``), valid past 90 degrees.

    Args:
        points: ``(..., 3)``.
        params: ``(..., 16)`` fx, fy, cx, cy, k0, k1, k2, k3, k4, k5, p0, p1, s0, s1, s2, s3.

    Returns:
        ``pixels (..., 2)`` and ``valid (...)``: ``theta < min(pi, fold)``.
    """
    check_inputs("fisheye624", points, params, 3, 16, "points")
    return _project("fisheye624", _f624_distort, points, params)


def fisheye624_unproject(pixels: Tensor, params: Tensor, *,
                         iterations: int = FISHEYE_ITERATIONS) -> tuple[Tensor, Tensor]:
    """Fisheye624 unprojection: 2-D Newton on the distortion, then the ray.

    Args:
        pixels: ``(..., 2)``.
        params: ``(..., 16)`` fx, fy, cx, cy, k0, k1, k2, k3, k4, k5, p0, p1, s0, s1, s2, s3.
        iterations: maximum Newton iterations (see ``FISHEYE_ITERATIONS``).

    Returns:
        ``rays (..., 3)`` unit norm and ``valid (...)``: converged, ``theta < min(pi, fold)``.
    """
    check_inputs("fisheye624", pixels, params, 2, 16, "pixels")
    return _unproject("fisheye624", _f624_distort, pixels, params, iterations)


THIN_PRISM_FISHEYE = CameraModel(
    "thin_prism_fisheye", _TPF_NAMES, thin_prism_fisheye_project, thin_prism_fisheye_unproject,
    lambda p: _max_angle("thin_prism_fisheye", p), {**_GROUPS, "distortion": tuple(range(4, 12))},
    check_values=lambda p: check_positive(p, (0, 1), _TPF_NAMES, "thin_prism_fisheye"))
FISHEYE624 = CameraModel(
    "fisheye624", _F624_NAMES, fisheye624_project, fisheye624_unproject,
    lambda p: _max_angle("fisheye624", p), {**_GROUPS, "distortion": tuple(range(4, 16))},
    check_values=lambda p: check_positive(p, (0, 1), _F624_NAMES, "fisheye624"))
