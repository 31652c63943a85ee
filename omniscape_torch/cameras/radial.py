"""Radially symmetric fisheye models: r = f(theta), theta = atan2(sqrt(x**2 + y**2), z).

With ``(mx, my) = ((u - cx) / fx, (v - cy) / fy)`` and ``r = |(mx, my)|`` in focal units, a point
at angle ``theta`` from the optical axis lands at radius ``r(theta)`` in the direction of its
``(x, y)``. ``theta`` comes from ``atan2``, so points behind the camera (z < 0) keep their angle
(> 90 degrees) and never fold onto the front; each model is valid up to its own limit:

=============== ============================================= ===================================
model           r(theta)                                      valid
=============== ============================================= ===================================
equidistant     theta                                         theta < pi
equisolid       2 sin(theta / 2)                              theta < pi
stereographic   2 tan(theta / 2)                              theta < pi
orthographic    sin(theta)                                    theta <= pi / 2
kannala_brandt  theta (1 + k1 t + k2 t^2 + k3 t^3 + k4 t^4),  theta < min(pi, fold), fold: the
                t = theta^2                                   first zero of dr/dtheta
=============== ============================================= ===================================

Kannala-Brandt is OpenCV's ``cv2.fisheye`` (Kannala and Brandt, "A generic camera model and
calibration method for conventional, wide-angle, and fish-eye lenses", TPAMI 2006), here with
``atan2`` instead of ``atan(r / z)`` so that it is valid past 90 degrees; with k = 0 it is the
equidistant model. Its inverse is safeguarded Newton with a fixed maximum iteration count.
"""

from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor

from ._base import (CameraModel, FisheyeDraw, broadcast_shapes, check_inputs, check_positive, implicit_step,
                    invert_monotone, near_zero_radius, polar, polyder, polyval, safe_div,
                    safe_sqrt, smallest_positive_root)

_FOCAL_NAMES = ("fx", "fy", "cx", "cy")
_GROUPS = {"focal": (0, 1), "center": (2, 3)}

#: Default maximum number of Newton iterations of the Kannala-Brandt inverse. Safeguarded Newton
#: converges quadratically away from the fold and at least halves its bracket near it; 60 steps
#: reach the float64 tolerance everywhere the inverse is well-defined (tests/test_cameras.py).
KB_ITERATIONS = 60


def _skew(params: Tensor, index: int) -> Tensor | None:
    """The optional skew ``s`` at ``index`` (``u = fx mx + s my + cx``), None where absent."""
    return params[..., index] if params.shape[-1] > index else None


def _project_radial(points: Tensor, params: Tensor, r_of_theta: Callable[[Tensor], Tensor],
                    valid_theta: Callable[[Tensor], Tensor], skew: Tensor | None = None
                    ) -> tuple[Tensor, Tensor]:
    fx, fy, cx, cy = params[..., 0], params[..., 1], params[..., 2], params[..., 3]
    x, y, z = points.unbind(-1)
    rho, theta, axis = polar(points)
    ones = torch.ones_like(rho)
    valid = valid_theta(theta)
    r = r_of_theta(torch.where(valid, theta, torch.zeros_like(theta)))
    # r(theta) / rho, whose limit on the axis is r'(0) / z = 1 / z for every model here.
    scale = torch.where(axis, safe_div(ones, z, axis & valid), safe_div(r, rho, ~axis))
    u = fx * x * scale + cx if skew is None else (fx * x + skew * y) * scale + cx
    pixels = torch.stack((u, fy * y * scale + cy), dim=-1)
    return pixels, valid


def _unproject_radial(pixels: Tensor, params: Tensor,
                      theta_of_r: Callable[[Tensor], tuple[Tensor, Tensor]],
                      skew: Tensor | None = None) -> tuple[Tensor, Tensor]:
    x, y, z, valid = _unproject_radial_xyz(pixels[..., 0], pixels[..., 1], params, theta_of_r,
                                           skew)
    return torch.stack((x, y, z), dim=-1), valid


def _unproject_radial_xyz(u: Tensor, v: Tensor, params: Tensor,
                          theta_of_r: Callable[[Tensor], tuple[Tensor, Tensor]],
                          skew: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The unit ray's components ``x, y, z`` of pixel ``(u, v)``, and its validity. Components
    rather than a stacked ``(..., 3)``: compiled into a larger kernel, a stack is a buffer
    written to memory, the components are not (``render.kernels.camera_grid``)."""
    fx, fy, cx, cy = params[..., 0], params[..., 1], params[..., 2], params[..., 3]
    my = (v - cy) / fy
    mx = (u - cx) / fx if skew is None else (u - cx - skew * my) / fx
    r2 = mx * mx + my * my
    axis = near_zero_radius(r2, 1.0)
    r = safe_sqrt(r2, ~axis)
    theta, valid = theta_of_r(r)
    theta = torch.where(valid, theta, torch.zeros_like(theta))
    # sin(theta) / r -> theta'(0) = 1 on the axis.
    sin_over_r = torch.where(axis, torch.ones_like(r), safe_div(torch.sin(theta), r, ~axis))
    return mx * sin_over_r, my * sin_over_r, torch.cos(theta), valid


def _check_focal(params: Tensor, name: str) -> None:
    check_positive(params, (0, 1), _FOCAL_NAMES, name)


def _closed_form_model(name: str, r_of_theta, theta_of_r, r_limit: float, theta_limit: float,
                       inclusive: bool, doc: str, fisheye_draw: FisheyeDraw | None = None
                       ) -> CameraModel:
    """A parameter-free radial law ``r(theta)`` scaled by (fx, fy) and shifted by (cx, cy);
    ``fisheye_draw``: the augmentation draws it (``CameraModel.fisheye_draw``)."""

    def valid_theta(theta: Tensor) -> Tensor:
        return theta <= theta_limit if inclusive else theta < theta_limit

    def project(points: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
        check_inputs(name, points, params, 3, 4, "points")
        return _project_radial(points, params, r_of_theta, valid_theta)

    def inverse(r: Tensor) -> tuple[Tensor, Tensor]:
        valid = r <= r_limit if inclusive else r < r_limit
        return theta_of_r(torch.where(valid, r, torch.zeros_like(r))), valid

    def unproject(pixels: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
        check_inputs(name, pixels, params, 2, 4, "pixels")
        return _unproject_radial(pixels, params, inverse)

    def unproject_xyz(u: Tensor, v: Tensor, params: Tensor
                      ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        return _unproject_radial_xyz(u, v, params, inverse)

    def max_angle(params: Tensor) -> Tensor:
        return torch.full(params.shape[:-1], theta_limit, dtype=params.dtype, device=params.device)

    # valid where r < end: the next number above an inclusive limit
    end = math.nextafter(r_limit, math.inf) if inclusive else r_limit

    def domain_end(params: Tensor) -> Tensor:
        return torch.full(params.shape[:-1], end, dtype=params.dtype, device=params.device)

    project.__doc__ = unproject.__doc__ = doc
    return CameraModel(name, _FOCAL_NAMES, project, unproject, max_angle, _GROUPS,
                       check_values=lambda p: _check_focal(p, name), unproject_xyz=unproject_xyz,
                       domain_end=domain_end, radial=True, fisheye_draw=fisheye_draw)


def _orthographic_theta(r: Tensor) -> Tensor:
    # asin has an infinite slope at r = 1 (the image-circle edge); pin the gradient there finite.
    edge = r >= 1.0
    return torch.where(edge, math.pi / 2 * torch.ones_like(r),
                       torch.asin(torch.where(edge, torch.zeros_like(r), r)))


def _equisolid_theta(r: Tensor) -> Tensor:
    return 2.0 * torch.asin(0.5 * r)


EQUIDISTANT = _closed_form_model(
    "equidistant", lambda t: t, lambda r: r, math.pi, math.pi, False,
    "Equidistant fisheye: r = f theta, valid for theta < pi.", FisheyeDraw())
EQUISOLID = _closed_form_model(
    "equisolid", lambda t: 2.0 * torch.sin(0.5 * t), _equisolid_theta, 2.0, math.pi, False,
    "Equisolid-angle fisheye: r = 2 f sin(theta / 2), valid for theta < pi.", FisheyeDraw())
STEREOGRAPHIC = _closed_form_model(
    "stereographic", lambda t: 2.0 * torch.tan(0.5 * t), lambda r: 2.0 * torch.atan(0.5 * r),
    math.inf, math.pi, False,
    "Stereographic fisheye: r = 2 f tan(theta / 2), valid for theta < pi.", FisheyeDraw())
ORTHOGRAPHIC = _closed_form_model(
    "orthographic", torch.sin, _orthographic_theta, 1.0, math.pi / 2, True,
    "Orthographic fisheye: r = f sin(theta), valid for theta <= pi / 2.")


# --------------------------------------------------------------------------------------------
# Kannala-Brandt
# --------------------------------------------------------------------------------------------

_KB_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")


def _kb_poly(params: Tensor) -> Tensor:
    """Coefficients of r(theta) = theta * P(theta^2), as P's ascending coefficients (1, k1..k4)."""
    return torch.cat((torch.ones_like(params[..., :1]), params[..., 4:8]), dim=-1)


def kannala_brandt_max_angle(params: Tensor) -> Tensor:
    """min(pi, fold): the fold is the first theta > 0 with dr/dtheta = 0, i.e. the smallest
    positive root t of ``1 + 3 k1 t + 5 k2 t^2 + 7 k3 t^3 + 9 k4 t^4`` at t = theta^2."""
    odd = torch.tensor([1.0, 3.0, 5.0, 7.0, 9.0], dtype=params.dtype, device=params.device)
    t_fold = smallest_positive_root(_kb_poly(params) * odd)
    return torch.sqrt(t_fold).clamp(max=math.pi)


def kannala_brandt_domain_end(params: Tensor) -> Tensor:
    """The normalised radius ``r(max_angle)`` where the unprojection's domain ends: valid pixels
    lie at ``r < end``."""
    return _kb_r(kannala_brandt_max_angle(params), _kb_poly(params))[0]


def _kb_r(theta: Tensor, coeffs: Tensor) -> tuple[Tensor, Tensor]:
    """r(theta) and dr/dtheta for ``coeffs = (1, k1, ..., k4)``."""
    t = theta * theta
    p = polyval(coeffs, t)
    dp = polyval(polyder(coeffs), t)
    return theta * p, p + 2.0 * t * dp


def kannala_brandt_project(points: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """Kannala-Brandt projection, ``r = theta (1 + k1 theta^2 + ... + k4 theta^8)``.

    Args:
        points: ``(..., 3)`` points in the camera frame (OpenCV: x right, y down, z forward).
        params: ``(..., 8)`` fx, fy, cx, cy, k1, k2, k3, k4, or ``(..., 9)`` with the skew
            ``s`` (``u = fx mx + s my + cx``; OpenCV's ``alpha`` is ``s / fx``).

    Returns:
        ``pixels (..., 2)`` and ``valid (...)``: ``theta < min(pi, fold)``.
    """
    check_inputs("kannala_brandt", points, params, 3, (8, 9), "points")
    coeffs = _kb_poly(params)
    limit = kannala_brandt_max_angle(params)
    return _project_radial(points, params, lambda th: _kb_r(th, coeffs)[0],
                           lambda th: th < limit, _skew(params, 8))


def kannala_brandt_unproject(pixels: Tensor, params: Tensor, *,
                             iterations: int = KB_ITERATIONS) -> tuple[Tensor, Tensor]:
    """Kannala-Brandt unprojection: solve ``r(theta) = r`` by safeguarded Newton on [0, limit].

    Args:
        pixels: ``(..., 2)`` pixel coordinates (u, v).
        params: ``(..., 8)`` fx, fy, cx, cy, k1, k2, k3, k4, or ``(..., 9)`` with the skew ``s``.
        iterations: maximum Newton iterations (fixed; see ``KB_ITERATIONS``).

    Returns:
        ``rays (..., 3)`` unit norm and ``valid (...)``: ``r < r(limit)`` and Newton converged.
    """
    check_inputs("kannala_brandt", pixels, params, 2, (8, 9), "pixels")
    coeffs = _kb_poly(params)
    limit = kannala_brandt_max_angle(params)
    r_limit = kannala_brandt_domain_end(params)
    tol = 4 * torch.finfo(params.dtype).eps

    def theta_of_r(r: Tensor) -> tuple[Tensor, Tensor]:
        inside = r < r_limit
        target = torch.where(inside, r, torch.zeros_like(r)).detach()
        theta, converged = invert_monotone(lambda th: _kb_r(th, coeffs.detach()), target,
                                           limit, iterations, tol)
        # one more Newton step, with gradient: polishes the root and carries the implicit
        # function theorem's derivative to r and the coefficients
        value, slope = _kb_r(theta, coeffs)
        theta = implicit_step(theta, value - torch.where(inside, r, torch.zeros_like(r)), slope)
        return theta, inside & converged

    return _unproject_radial(pixels, params, theta_of_r, _skew(params, 8))


#: Entries of the radius -> angle table of `kannala_brandt_tabulate`, and the safeguarded
#: Newton steps that polish its interpolation per pixel (quadratic away from the fold; next to
#: it, where the inverse has a square-root singularity, at least a halving of the bracket).
KB_TABLE, KB_TABLE_STEPS = 256, 4


def kannala_brandt_tabulate(params: Tensor, image_size: tuple[int, int],
                            entries: int = KB_TABLE) -> Tensor:
    """The parameters of ``B`` Kannala-Brandt cameras with their radius -> angle tables, for
    `kannala_brandt_unproject_table_xyz`: the inverse solved once per camera at
    ``entries + 1`` radii (the safeguarded Newton of `kannala_brandt_unproject`) instead
    of at every pixel. The table spans the radii of the image (its farthest corner), up to the
    model's limit (the fold, or pi).

    Args:
        params: ``(B, 8)`` fx, fy, cx, cy, k1, k2, k3, k4, or ``(B, 9)`` with the skew ``s``.
        image_size: ``(H, W)`` of the pixels to unproject.
        entries: intervals of the table.

    Returns:
        ``(B, 9 + 2 + entries + 1)``: the parameters with the skew (0 where absent),
        ``r(limit)`` (the normalised radius beyond which no ray exists), the table's last
        radius ``r_end``, then ``theta`` at ``r_j = j r_end / entries``, ``j = 0..entries``.
    """
    if not isinstance(params, Tensor) or params.dim() != 2 or params.shape[-1] not in (8, 9):
        raise ValueError(f"params: expected (B, 8) or (B, 9) Kannala-Brandt parameters, got "
                         f"{tuple(getattr(params, 'shape', ()))}")
    if params.shape[-1] == 8:
        params = torch.cat((params, torch.zeros_like(params[:, :1])), -1)
    with torch.no_grad():
        coeffs = _kb_poly(params)[:, None, :]
        limit = kannala_brandt_max_angle(params)
        r_limit = _kb_r(limit, coeffs[:, 0])[0]
        h, w = image_size
        corners = params.new_tensor([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]])
        my = (corners[:, 1] - params[:, 3:4]) / params[:, 1:2]
        mx = (corners[:, 0] - params[:, 2:3] - params[:, 8:9] * my) / params[:, 0:1]
        r_end = torch.minimum(torch.sqrt(mx * mx + my * my).amax(-1), r_limit)
        radii = r_end[:, None] * torch.linspace(0, 1, entries + 1, dtype=params.dtype,
                                                device=params.device)
        theta, _ = invert_monotone(lambda th: _kb_r(th, coeffs), radii, limit[:, None],
                                   KB_ITERATIONS, 4 * torch.finfo(params.dtype).eps)
    return torch.cat((params, r_limit[:, None], r_end[:, None], theta), -1)


def _bracketed_newton(theta: Tensor, target: Tensor, lo: Tensor, hi: Tensor, coeffs: Tensor,
                      steps: int) -> Tensor:
    """``steps`` Newton steps on ``r(theta) = target`` from ``theta``, kept inside the bracket
    ``[lo, hi]`` of the root (narrowed by every step; bisection where a step leaves it)."""
    for _ in range(steps):
        value, slope = _kb_r(theta, coeffs)
        residual = value - target
        lo = torch.where(residual < 0, theta, lo)
        hi = torch.where(residual > 0, theta, hi)
        step = theta - safe_div(residual, slope, slope > 0)
        theta = torch.where((step >= lo) & (step <= hi), step, 0.5 * (lo + hi))
    return theta


#: Angles of the forward sweep of `kannala_brandt_angles`, and its polishing steps.
KB_SWEEP, KB_SWEEP_STEPS = 256, 2


def kannala_brandt_angles(params: Tensor, radii: Tensor, *, samples: int = KB_SWEEP,
                          steps: int = KB_SWEEP_STEPS) -> Tensor:
    """The angles ``theta (B, K)`` with ``r(theta) = radii (B, K)`` (normalised radii up to
    each camera's ``r(max_angle)``) of ``B`` Kannala-Brandt cameras, for many radii at once (the
    tables of ``render.kernels.radial_table``): ``r`` swept forward over ``samples + 1`` angles
    evenly spaced on ``[0, max_angle]`` (increasing there), each radius bracketed between two of
    them (``searchsorted``) and its angle interpolated linearly in ``w = sqrt(r_end - r)``, in
    which ``theta`` is smooth up to the fold (in ``r`` it has a square-root singularity there),
    then polished by ``steps`` Newton steps kept inside the bracket (bisection where a step
    leaves it). The roots of the safeguarded Newton of `kannala_brandt_unproject` to
    1e-9 rad (tests/test_camera_grid.py), without its 60 iterations over every radius; no
    gradient.
    """
    with torch.no_grad():
        coeffs = _kb_poly(params)[:, None, :]                              # (B, 1, 5)
        limit = kannala_brandt_max_angle(params)[:, None]                  # (B, 1)
        sweep = limit * torch.linspace(0, 1, samples + 1, dtype=params.dtype,
                                       device=params.device)               # (B, S)
        r_sweep = _kb_r(sweep, coeffs)[0]
        r_end = r_sweep[:, -1:]
        target = torch.minimum(radii, r_end)
        j = torch.searchsorted(r_sweep.contiguous(), target.contiguous()).clamp(1, samples)
        lo, hi = sweep.gather(1, j - 1), sweep.gather(1, j)
        w_lo, w_hi, w = (torch.sqrt((r_end - r).clamp_min(0)) for r in
                         (r_sweep.gather(1, j - 1), r_sweep.gather(1, j), target))
        span = w_hi - w_lo
        theta = lo + safe_div(w - w_lo, span, span != 0) * (hi - lo)
        return _bracketed_newton(theta, target, lo, hi, coeffs, steps)


def kannala_brandt_unproject_table_xyz(u: Tensor, v: Tensor, table: Tensor
                                       ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Kannala-Brandt unprojection of pixel ``(u, v)`` through a radius -> angle table of
    `kannala_brandt_tabulate` (broadcasting ``table (..., 9 + 2 + T + 1)`` against the
    pixels): the angle interpolated linearly between the two entries around the pixel's
    radius, then polished by ``KB_TABLE_STEPS`` Newton steps on the polynomial, kept within the
    bracket of the two entries (bisection where a step leaves it); tests/test_camera_grid.py
    bounds the result at 0.01 px. No loop and no data-dependent branch: the
    whole unprojection compiles into one kernel (``render.kernels.camera_grid``).

    Returns:
        The unit ray's components ``x, y, z`` and ``valid``: ``r < r(limit)``.
    """
    entries = table.shape[-1] - 12
    coeffs = torch.cat((torch.ones_like(table[..., :1]), table[..., 4:8]), -1)
    r_limit, r_end, thetas = table[..., 9], table[..., 10], table[..., 11:]

    def theta_of_r(r: Tensor) -> tuple[Tensor, Tensor]:
        inside = r < r_limit
        target = torch.where(inside, r, torch.zeros_like(r))
        s = (target / r_end * entries).clamp(0, entries)
        j = torch.floor(s).clamp(max=entries - 1)
        shape = broadcast_shapes(s.shape, thetas.shape[:-1])
        index = j.long().expand(shape).unsqueeze(-1)
        t0 = torch.gather(thetas.expand(*shape, entries + 1), -1, index).squeeze(-1)
        t1 = torch.gather(thetas.expand(*shape, entries + 1), -1, index + 1).squeeze(-1)
        theta = t0 + (s - j) * (t1 - t0)
        # the entries bracket the root: r is monotonic
        return _bracketed_newton(theta, target, t0, t1, coeffs, KB_TABLE_STEPS), inside

    return _unproject_radial_xyz(u, v, table, theta_of_r, table[..., 8])


def _check_kb(params: Tensor) -> None:
    _check_focal(params, "kannala_brandt")


KANNALA_BRANDT = CameraModel(
    "kannala_brandt", _KB_NAMES, kannala_brandt_project, kannala_brandt_unproject,
    kannala_brandt_max_angle, {**_GROUPS, "distortion": (4, 5, 6, 7), "skew": (8,)},
    check_values=_check_kb, domain_end=kannala_brandt_domain_end, optional=("s",), radial=True,
    fisheye_draw=FisheyeDraw(distortion=True))
