"""Pinhole cameras with lens distortion: ``fov``, ``division`` and ``opencv``.

Each maps a point to the normalised plane of a pinhole camera, distorts it there, then scales
by ``(fx, fy)`` and shifts by ``(cx, cy)``: ``u = fx xd + cx``, ``v = fy yd + cy``. With
``(mx, my) = (x / z, y / z)``, ``r = |(mx, my)|``, ``(xd, yd)`` the distorted point and
``rd = |(xd, yd)|``:

========= ============================================================== =======================
model     distortion                                                     valid
========= ============================================================== =======================
fov       ``rd = atan(2 r tan(omega / 2)) / omega``                      z > 0; unprojection:
          (Devernay and Faugeras 2001; Kalibr ``pinhole-fov``, COLMAP     ``omega rd < pi / 2``
          ``FOV``, TUM monoVO); omega -> 0 is the pinhole
division  the ray of ``(xd, yd)`` is ``(xd, yd, 1 + k rd^2)`` (Fitzgibbon  ``theta < max_angle``:
          2001; COLMAP ``DIVISION``): its projection solves               ``atan(1 / (2 sqrt k))``
          ``k r^2 t^2 - z t + 1 = 0``, ``(xd, yd) = t (x, y)`` (closed    for k > 0 (the fold
          form), ``t = 2 / (z + sqrt(z^2 - 4 k r^2))`` with ``r`` now      ``rd^2 = 1 / k``), pi
          ``|(x, y)|``                                                    for k < 0 (past 90
                                                                          deg), pi / 2 for k = 0
opencv    ``xd = mx R + 2 p1 mx my + p2 (r^2 + 2 mx^2) + s1 r^2 + s2 r^4``, z > 0 and ``r^2``
          ``yd = my R + p1 (r^2 + 2 my^2) + 2 p2 mx my + s3 r^2 + s4 r^4``, below the radial
          ``R = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 +    fold (first zero of
          k6 r^6)`` (OpenCV's ``projectPoints`` with 12 coefficients;     ``d(r R) / dr``) and
          COLMAP ``OPENCV`` is k3..s4 = 0, ``FULL_OPENCV`` s = 0; kornia's the pole of R
          Brown-Conrady)
========= ============================================================== =======================

Unprojection: ``fov`` and ``division`` in closed form; ``opencv`` by 2-D Newton on the
distortion of the plane with its 2 x 2 Jacobian (``_base.undistort_2d``, as OpenCV's
``undistortPoints`` and COLMAP's ``IterativeUndistortion``), at most ``OPENCV_ITERATIONS``
steps, invalid where it did not converge. Its valid set is the radial one: tangential and
thin-prism terms can fold the plane a little before the radial fold, or, for a rational lens
with k5, k6 and a thin prism (the r^4 prism terms outgrowing ``r R``), short of 90 degrees far
outside the image; there Newton does not converge and the pixels are invalid.

COLMAP's FOV model switches to a series for ``omega^2 < 1e-4``; its projection's series there
(``1 - omega^2 / 12 + omega^2 r^2 / 3``) is the series of its *unprojection* (the exact factor
``atan(2 r tan(omega / 2)) / (r omega)`` is ``1 + omega^2 / 12 - omega^2 r^2 / 3 + ...``), so
for such small omega COLMAP's projection is not the inverse of its own unprojection (0.02 px at
omega = 0.009, r = 1, f = 500; tests/test_camera_oracles.py). Here both directions use the exact
formula, with series only where it is 0 / 0 (``tan(x) / x``, ``atan(x) / x`` at 0, exact to
rounding there).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ._base import (CameraModel, check_inputs, check_positive, check_range, near_zero_radius,
                    polar, polymul, safe_div, safe_sqrt, series_or, smallest_positive_root,
                    undistort_2d)

#: Default maximum number of 2-D Newton iterations of the ``opencv`` undistortion. Started from
#: the inverse of the radial part, Newton converges quadratically; 50 steps leave a wide margin
#: (the round trips of tests/test_cameras.py reach float64 precision in fewer than 10).
OPENCV_ITERATIONS = 50

_GROUPS = {"focal": (0, 1), "center": (2, 3)}
_FOV_NAMES = ("fx", "fy", "cx", "cy", "omega")
_DIVISION_NAMES = ("fx", "fy", "cx", "cy", "k")
_OPENCV_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6",
                 "s1", "s2", "s3", "s4")

#: Below this |x| the removable singularities use their series (exact to float64 rounding:
#: the first term left out is below 1e-18 relative there).
_SMALL = 1e-3


def _normalised(pixels: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    return ((pixels[..., 0] - params[..., 2]) / params[..., 0],
            (pixels[..., 1] - params[..., 3]) / params[..., 1])


def _pixels(xd: Tensor, yd: Tensor, params: Tensor) -> Tensor:
    return torch.stack((params[..., 0] * xd + params[..., 2], params[..., 1] * yd + params[..., 3]),
                       dim=-1)


def _normalise(x: Tensor, y: Tensor, z: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Unit rays of ``(x, y, z)``; invalid lanes get the optical axis."""
    n2 = x * x + y * y + z * z
    ok = valid & (n2 > 0)
    inv = torch.rsqrt(torch.where(ok, n2, torch.ones_like(n2)))
    zero = torch.zeros_like(x)
    rays = torch.stack((torch.where(ok, x * inv, zero), torch.where(ok, y * inv, zero),
                        torch.where(ok, z * inv, zero + 1)), dim=-1)
    return rays, ok


def _plane(points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(x / z, y / z)`` and ``z > 0``; 0 where z <= 0."""
    x, y, z = points.unbind(-1)
    front = z > 0
    return safe_div(x, z, front), safe_div(y, z, front), front


# --------------------------------------------------------------------------------------------
# FOV (Devernay-Faugeras)
# --------------------------------------------------------------------------------------------

def _tan_ratio(omega: Tensor) -> Tensor:
    """``2 tan(omega / 2) / omega``, 1 at omega = 0."""
    return series_or(omega, omega.abs() < _SMALL, lambda w: 2 * torch.tan(0.5 * w) / w,
                     lambda w: 1 + w * w / 12 + w ** 4 / 120)


def _atan_ratio(x: Tensor) -> Tensor:
    """``atan(x) / x``, 1 at x = 0."""
    return series_or(x, x.abs() < _SMALL, lambda t: torch.atan(t) / t,
                     lambda t: 1 - t * t / 3 + t ** 4 / 5)


def _sinc(x: Tensor) -> Tensor:
    return series_or(x, x.abs() < _SMALL, lambda t: torch.sin(t) / t,
                     lambda t: 1 - t * t / 6 + t ** 4 / 120)


def fov_project(points: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """FOV (Devernay-Faugeras) projection ``rd = atan(2 r tan(omega / 2)) / omega``.

    ``(xd, yd) = (mx, my) q(omega) g(2 tan(omega / 2) r)`` with ``q = 2 tan(omega / 2) / omega``
    and ``g(a) = atan(a) / a``: the same numbers, without 0 / 0 on the axis or at omega = 0.

    Args:
        points: ``(..., 3)`` points in the camera frame (x right, y down, z forward).
        params: ``(..., 5)`` fx, fy, cx, cy, omega (radians).

    Returns:
        ``pixels (..., 2)`` and ``valid (...)``: z > 0.
    """
    check_inputs("fov", points, params, 3, 5, "points")
    mx, my, valid = _plane(points)
    omega = params[..., 4]
    r2 = mx * mx + my * my
    r = safe_sqrt(r2, ~near_zero_radius(r2, 1.0))
    factor = _tan_ratio(omega) * _atan_ratio(2 * torch.tan(0.5 * omega) * r)
    return _pixels(mx * factor, my * factor, params), valid


def fov_unproject(pixels: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """FOV unprojection, closed form: ``r = tan(omega rd) / (2 tan(omega / 2))``.

    The ray is ``(xd sinc(omega rd), yd sinc(omega rd), q(omega) cos(omega rd))``, normalised
    (``(mx, my, 1)`` multiplied by ``cos(omega rd) omega / (2 tan(omega / 2))``).

    Args:
        pixels: ``(..., 2)`` pixel coordinates (u, v).
        params: ``(..., 5)`` fx, fy, cx, cy, omega.

    Returns:
        ``rays (..., 3)`` unit norm and ``valid (...)``: ``omega rd < pi / 2``.
    """
    check_inputs("fov", pixels, params, 2, 5, "pixels")
    xd, yd = _normalised(pixels, params)
    omega = params[..., 4]
    rd2 = xd * xd + yd * yd
    rd = safe_sqrt(rd2, ~near_zero_radius(rd2, 1.0))
    angle = omega * rd
    valid = angle < 0.5 * math.pi
    angle = torch.where(valid, angle, torch.zeros_like(angle))
    s = _sinc(angle)
    return _normalise(xd * s, yd * s, _tan_ratio(omega) * torch.cos(angle), valid)


def fov_domain_end(params: Tensor) -> Tensor:
    """``pi / (2 omega)``: valid pixels lie at normalised radii below it (inf for omega = 0)."""
    omega = params[..., 4]
    return torch.where(omega > 0, 0.5 * math.pi / torch.where(omega > 0, omega,
                                                               torch.ones_like(omega)),
                       torch.full_like(omega, math.inf)).detach()


def _check_fov(params: Tensor) -> None:
    check_positive(params, (0, 1), _FOV_NAMES, "fov")
    check_range(params, 4, 0.0, math.nextafter(math.pi, 0.0), _FOV_NAMES, "fov")


FOV = CameraModel(
    "fov", _FOV_NAMES, fov_project, fov_unproject,
    lambda p: torch.full(p.shape[:-1], math.pi / 2, dtype=p.dtype, device=p.device),
    {**_GROUPS, "distortion": (4,)}, check_values=_check_fov, domain_end=fov_domain_end)


# --------------------------------------------------------------------------------------------
# Division (Fitzgibbon)
# --------------------------------------------------------------------------------------------

def division_max_angle(params: Tensor) -> Tensor:
    """``atan(1 / (2 sqrt(k)))`` for k > 0 (the ray's angle ``atan2(rd, 1 + k rd^2)`` peaks at
    ``rd^2 = 1 / k``), pi for k < 0 (it grows to pi), pi / 2 for k = 0 (the pinhole)."""
    k = params[..., 4].detach()
    pos = k > 0
    fold = torch.atan(0.5 * torch.rsqrt(torch.where(pos, k, torch.ones_like(k))))
    other = torch.where(k < 0, torch.full_like(k, math.pi), torch.full_like(k, math.pi / 2))
    return torch.where(pos, fold, other)


def division_domain_end(params: Tensor) -> Tensor:
    """``1 / sqrt(k)`` for k > 0, inf otherwise (normalised radius)."""
    k = params[..., 4].detach()
    pos = k > 0
    return torch.where(pos, torch.rsqrt(torch.where(pos, k, torch.ones_like(k))),
                       torch.full_like(k, math.inf))


def division_project(points: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """Division-model projection (COLMAP ``DIVISION``): ``(xd, yd) = t (x, y)`` with ``t`` the
    smaller root of ``k r^2 t^2 - z t + 1 = 0`` (``r = |(x, y)|``), so that ``(xd, yd, 1 + k
    rd^2)`` is parallel to the point.

    ``t = 2 / (z + sqrt(z^2 - 4 k r^2))``, and behind the camera (z < 0, only for k < 0) the
    same root as ``(z - sqrt(z^2 - 4 k r^2)) / (2 k r^2)``, without cancellation.

    Args:
        points: ``(..., 3)``.
        params: ``(..., 5)`` fx, fy, cx, cy, k.

    Returns:
        ``pixels (..., 2)`` and ``valid (...)``: ``theta < max_angle`` (see
        `division_max_angle`).
    """
    check_inputs("division", points, params, 3, 5, "points")
    k = params[..., 4]
    x, y, z = points.unbind(-1)
    rho, theta, axis = polar(points)
    valid = (theta < division_max_angle(params)) & ((x * x + y * y + z * z) > 0)
    rho2 = rho * rho
    disc2 = z * z - 4 * k * rho2
    disc = safe_sqrt(disc2, valid & (disc2 > 0))
    front = z >= 0
    t = torch.where(front, safe_div(torch.full_like(z, 2.0), z + disc, valid & front),
                    safe_div(z - disc, 2 * k * rho2, valid & ~front))
    return _pixels(t * x, t * y, params), valid


def division_unproject(pixels: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """Division-model unprojection, closed form: the ray ``(xd, yd, 1 + k rd^2)``, normalised.

    Args:
        pixels: ``(..., 2)``.
        params: ``(..., 5)`` fx, fy, cx, cy, k.

    Returns:
        ``rays (..., 3)`` unit norm and ``valid (...)``: ``k rd^2 < 1`` where k > 0 (inside the
        fold), everywhere otherwise.
    """
    check_inputs("division", pixels, params, 2, 5, "pixels")
    k = params[..., 4]
    xd, yd = _normalised(pixels, params)
    rd2 = xd * xd + yd * yd
    valid = (k <= 0) | (k * rd2 < 1)
    return _normalise(xd, yd, 1 + k * rd2, valid)


def _check_division(params: Tensor) -> None:
    check_positive(params, (0, 1), _DIVISION_NAMES, "division")


DIVISION = CameraModel(
    "division", _DIVISION_NAMES, division_project, division_unproject, division_max_angle,
    {**_GROUPS, "distortion": (4,)}, check_values=_check_division,
    domain_end=division_domain_end)


# --------------------------------------------------------------------------------------------
# OpenCV (radial rational, tangential, thin prism)
# --------------------------------------------------------------------------------------------

def _opencv_distort(mx: Tensor, my: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
    """OpenCV's distortion of the normalised plane; ``c (..., 12)`` = k1 k2 p1 p2 k3 k4 k5 k6
    s1 s2 s3 s4 (real or complex: the complex step of ``_base.undistort_2d``)."""
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = c.unbind(-1)
    r2 = mx * mx + my * my
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xy = mx * my
    xd = mx * radial + 2 * p1 * xy + p2 * (r2 + 2 * mx * mx) + r2 * (s1 + s2 * r2)
    yd = my * radial + p1 * (r2 + 2 * my * my) + 2 * p2 * xy + r2 * (s3 + s4 * r2)
    return xd, yd


def _opencv_jacobian(mx: Tensor, my: Tensor, c: Tensor):
    """`_opencv_distort` and its Jacobian ``d(xd, yd) / d(mx, my)``, written out."""
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = c.unbind(-1)
    t = mx * mx + my * my
    n = 1 + t * (k1 + t * (k2 + t * k3))
    d = 1 + t * (k4 + t * (k5 + t * k6))
    radial = n / d
    radial_t = ((k1 + t * (2 * k2 + 3 * t * k3)) - radial * (k4 + t * (2 * k5 + 3 * t * k6))) / d
    xy = mx * my
    gx, gy = s1 + 2 * s2 * t, s3 + 2 * s4 * t
    xd = mx * radial + 2 * p1 * xy + p2 * (t + 2 * mx * mx) + t * (s1 + s2 * t)
    yd = my * radial + p1 * (t + 2 * my * my) + 2 * p2 * xy + t * (s3 + s4 * t)
    cross = 2 * xy * radial_t
    return (xd, yd,
            radial + 2 * mx * mx * radial_t + 2 * p1 * my + 6 * p2 * mx + 2 * gx * mx,
            cross + 2 * p1 * mx + 2 * p2 * my + 2 * gx * my,
            cross + 2 * p1 * mx + 2 * p2 * my + 2 * gy * mx,
            radial + 2 * my * my * radial_t + 6 * p1 * my + 2 * p2 * mx + 2 * gy * my)


def _opencv_radial(r: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
    """``g(r) = r N(r^2) / D(r^2)`` and ``g'(r)``."""
    k1, k2, k3, k4, k5, k6 = (c[..., i] for i in (0, 1, 4, 5, 6, 7))
    t = r * r
    n = 1 + t * (k1 + t * (k2 + t * k3))
    d = 1 + t * (k4 + t * (k5 + t * k6))
    dn = k1 + t * (2 * k2 + 3 * t * k3)
    dd = k4 + t * (2 * k5 + 3 * t * k6)
    ok = d != 0
    value = r * safe_div(n, d, ok)
    slope = safe_div(n * d + 2 * t * (dn * d - n * dd), d * d, ok)
    return value, slope


def opencv_radial_limit(params: Tensor) -> Tensor:
    """Squared normalised radius where the model's domain ends: the smaller of the radial fold
    (first positive zero of ``N D + 2 t (N' D - N D')``, ``t = r^2``, the numerator of
    ``d(r N / D) / dr``) and the pole (first positive zero of D); inf for neither."""
    c = params[..., 4:16].detach()
    one = torch.ones_like(c[..., 0])
    zero = torch.zeros_like(one)
    n = torch.stack((one, c[..., 0], c[..., 1], c[..., 4]), -1)
    d = torch.stack((one, c[..., 5], c[..., 6], c[..., 7]), -1)
    dn = torch.stack((c[..., 0], 2 * c[..., 1], 3 * c[..., 4]), -1)
    dd = torch.stack((c[..., 5], 2 * c[..., 6], 3 * c[..., 7]), -1)
    # 2 t (N' D - N D'): degree 5 shifted by one
    cross = 2 * (polymul(dn, d) - polymul(n, dd))
    slope = polymul(n, d) + torch.cat((zero[..., None], cross), -1)
    return torch.minimum(smallest_positive_root(slope), smallest_positive_root(d))


def opencv_max_angle(params: Tensor) -> Tensor:
    """``atan(sqrt(t_limit))`` (`opencv_radial_limit`), pi / 2 without a limit."""
    t = opencv_radial_limit(params)
    return torch.where(torch.isfinite(t), torch.atan(torch.sqrt(t)),
                       torch.full_like(t, math.pi / 2))


def opencv_project(points: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """OpenCV pinhole projection with radial (rational), tangential and thin-prism distortion,
    as ``cv2.projectPoints`` with the 12 coefficients (k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4).

    Args:
        points: ``(..., 3)``.
        params: ``(..., 16)`` fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4.

    Returns:
        ``pixels (..., 2)`` and ``valid (...)``: z > 0 and ``r^2`` below the radial fold and
        the pole (`opencv_radial_limit`).
    """
    check_inputs("opencv", points, params, 3, 16, "points")
    mx, my, valid = _plane(points)
    valid = valid & (mx * mx + my * my < opencv_radial_limit(params))
    zero = torch.zeros_like(mx)
    xd, yd = _opencv_distort(torch.where(valid, mx, zero), torch.where(valid, my, zero),
                             params[..., 4:16])
    return _pixels(xd, yd, params), valid


def opencv_unproject(pixels: Tensor, params: Tensor, *,
                     iterations: int = OPENCV_ITERATIONS) -> tuple[Tensor, Tensor]:
    """OpenCV unprojection: 2-D Newton on the distortion (``_base.undistort_2d``), then the ray
    ``(mx, my, 1)`` normalised.

    Args:
        pixels: ``(..., 2)``.
        params: ``(..., 16)`` fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4.
        iterations: maximum Newton iterations (see ``OPENCV_ITERATIONS``).

    Returns:
        ``rays (..., 3)`` unit norm and ``valid (...)``: converged, inside the radial limit.
    """
    check_inputs("opencv", pixels, params, 2, 16, "pixels")
    xd, yd = _normalised(pixels, params)
    t_limit = opencv_radial_limit(params)
    mx, my, valid = undistort_2d(xd, yd, params[..., 4:16], _opencv_distort, _opencv_radial,
                                 t_limit, iterations, _opencv_jacobian)
    valid = valid & (mx * mx + my * my < t_limit)
    return _normalise(mx, my, torch.ones_like(mx), valid)


def _check_opencv(params: Tensor) -> None:
    check_positive(params, (0, 1), _OPENCV_NAMES, "opencv")


OPENCV = CameraModel(
    "opencv", _OPENCV_NAMES, opencv_project, opencv_unproject, opencv_max_angle,
    {**_GROUPS, "distortion": tuple(range(4, 16))}, check_values=_check_opencv)
