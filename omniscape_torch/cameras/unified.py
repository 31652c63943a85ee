"""Unified projection models: central catadioptric cameras and their fisheye successors.

* ``unified`` (fx, fy, cx, cy, xi, k1, k2, p1, p2): Geyer and Daniilidis, "A unifying theory for
  central panoramic systems", ECCV 2000 (k = p = 0); Mei and Rives, "Single view point
  omnidirectional camera calibration from planar grids", ICRA 2007 (radial-tangential distortion
  of the normalised plane). The point goes to the unit sphere, then through a pinhole at
  ``(0, 0, -xi)``: ``m = (x, y) / (z + xi |X|)``, distorted, scaled by ``f``. OpenCV's
  ``cv2.omnidir`` uses the same parameters in the same order. Barreto and Araujo's mirror
  parameterisation is ``unified_from_mirror``.
* ``eucm`` (fx, fy, cx, cy, alpha, beta): Khomenko et al., "An enhanced unified camera model",
  RA-L 2016: ``u = fx x / (alpha d + (1 - alpha) z) + cx``, ``d = sqrt(beta (x^2 + y^2) + z^2)``.
  With beta = 1 it is the unified model with ``xi = alpha / (1 - alpha)``, ``f / (1 - alpha)``.
* ``double_sphere`` (fx, fy, cx, cy, xi, alpha): Usenko, Demmel and Cremers, "The double sphere
  camera model", 3DV 2018: ``u = fx x / (alpha d2 + (1 - alpha) (xi d1 + z)) + cx``,
  ``d1 = |X|``, ``d2 = |(x, y, xi d1 + z)|``. With xi = 0 it is the unified model in alpha form.

Valid sets, written once each (the projection folds beyond them):

* unified: ``z > -w |X|``, ``w = xi`` if xi <= 1 else ``1 / xi``; with distortion also
  ``r^2 = |m|^2`` below the first zero of ``d/dr [r (1 + k1 r^2 + k2 r^4)]``.
* eucm: ``z > -w d``, ``w = alpha / (1 - alpha)`` if alpha <= 1/2 else ``(1 - alpha) / alpha``.
* double_sphere: ``z > -w2 |X|``, ``w2 = (w1 + xi) / sqrt(2 w1 xi + xi^2 + 1)``, ``w1`` as eucm's w.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ._base import (CameraModel, FisheyeDraw, check_inputs, check_positive, check_range,
                    fold_guarded_step, newton_step_2d, safe_div, safe_sqrt, smallest_positive_root)

#: Default maximum number of Newton iterations when undistorting the unified model's
#: radial-tangential distortion: 2-D Newton converges quadratically inside the fold and about
#: halves its error per step next to it, where 50 steps reach float64 precision (the tests).
UNIFIED_ITERATIONS = 50

_UNIFIED_NAMES = ("fx", "fy", "cx", "cy", "xi", "k1", "k2", "p1", "p2")
_EUCM_NAMES = ("fx", "fy", "cx", "cy", "alpha", "beta")
_DS_NAMES = ("fx", "fy", "cx", "cy", "xi", "alpha")


def _norm(points: Tensor) -> tuple[Tensor, Tensor]:
    """|X| and ``nonzero``; |X| = 0 with a finite gradient at the origin."""
    x, y, z = points.unbind(-1)
    n2 = x * x + y * y + z * z
    nonzero = n2 > torch.finfo(points.dtype).tiny
    return safe_sqrt(n2, nonzero), nonzero


def _alpha_w(alpha: Tensor) -> Tensor:
    """w = alpha / (1 - alpha) if alpha <= 1/2 else (1 - alpha) / alpha (Usenko et al. 2018)."""
    low = alpha <= 0.5
    return torch.where(low, alpha / torch.where(low, 1 - alpha, torch.ones_like(alpha)),
                       (1 - alpha) / torch.where(low, torch.ones_like(alpha), alpha))


def _pixels(mx: Tensor, my: Tensor, params: Tensor) -> Tensor:
    """``u = fx mx (+ s my) + cx``, ``v = fy my + cy``; the skew ``s`` of a 10-parameter
    unified camera (OpenCV omnidir's ``K[0, 1]``)."""
    u = params[..., 0] * mx
    if params.shape[-1] == 10:
        u = u + params[..., 9] * my
    return torch.stack((u + params[..., 2], params[..., 1] * my + params[..., 3]), dim=-1)


def _normalised(pixels: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    return _normalised_uv(pixels[..., 0], pixels[..., 1], params)


def _normalised_uv(u: Tensor, v: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """The inverse of `_pixels`."""
    my = (v - params[..., 3]) / params[..., 1]
    if params.shape[-1] == 10:
        return (u - params[..., 2] - params[..., 9] * my) / params[..., 0], my
    return (u - params[..., 2]) / params[..., 0], my


# --------------------------------------------------------------------------------------------
# Unified (Geyer-Daniilidis / Mei-Rives)
# --------------------------------------------------------------------------------------------

def _distort(mx: Tensor, my: Tensor, k1, k2, p1, p2) -> tuple[Tensor, Tensor]:
    r2 = mx * mx + my * my
    radial = 1 + r2 * (k1 + k2 * r2)
    xd = mx * radial + 2 * p1 * mx * my + p2 * (r2 + 2 * mx * mx)
    yd = my * radial + p1 * (r2 + 2 * my * my) + 2 * p2 * mx * my
    return xd, yd


def _distort_jacobian(mx, my, k1, k2, p1, p2):
    r2 = mx * mx + my * my
    radial = 1 + r2 * (k1 + k2 * r2)
    g = 2 * (k1 + 2 * k2 * r2)
    j11 = radial + g * mx * mx + 2 * p1 * my + 6 * p2 * mx
    j12 = g * mx * my + 2 * p1 * mx + 2 * p2 * my
    j22 = radial + g * my * my + 6 * p1 * my + 2 * p2 * mx
    return j11, j12, j12, j22


def unified_distortion_fold(params: Tensor) -> Tensor:
    """Squared normalised radius where the radial distortion ``r (1 + k1 r^2 + k2 r^4)`` stops
    growing: the smallest positive root of ``1 + 3 k1 t + 5 k2 t^2``; inf without a fold."""
    coeffs = torch.stack((torch.ones_like(params[..., 5]), 3 * params[..., 5], 5 * params[..., 6]),
                         dim=-1)
    return smallest_positive_root(coeffs)


def _unified_w(xi: Tensor) -> Tensor:
    big = xi > 1
    return torch.where(big, 1 / torch.where(big, xi, torch.ones_like(xi)), xi)


def unified_project(points: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """Unified (Mei) projection: ``m = (x, y) / (z + xi |X|)``, radial-tangential distortion.

    Args:
        points: ``(..., 3)`` points in the camera frame.
        params: ``(..., 9)`` fx, fy, cx, cy, xi, k1, k2, p1, p2, or ``(..., 10)`` with the skew
            ``s`` (``u = fx mx + s my + cx``, OpenCV omnidir's ``K[0, 1]``).

    Returns:
        ``pixels (..., 2)`` and ``valid (...)``: ``z > -w |X|`` (w = xi, or 1/xi for xi > 1) and
        ``|m|^2`` inside the distortion's fold.
    """
    check_inputs("unified", points, params, 3, (9, 10), "points")
    xi, k1, k2, p1, p2 = params[..., 4:9].unbind(-1)
    d, nonzero = _norm(points)
    x, y, z = points.unbind(-1)
    valid = nonzero & (z > -_unified_w(xi) * d)
    den = z + xi * d
    mx, my = safe_div(x, den, valid), safe_div(y, den, valid)
    valid = valid & (mx * mx + my * my < unified_distortion_fold(params))
    xd, yd = _distort(mx, my, k1, k2, p1, p2)
    return _pixels(xd, yd, params), valid


def _undistort(xd: Tensor, yd: Tensor, params: Tensor, iterations: int
               ) -> tuple[Tensor, Tensor, Tensor]:
    """Invert the radial-tangential distortion by 2-D Newton from ``m = m_d``.

    A step that would cross the radial fold (``|m|^2 >= t_fold``, where the distortion stops
    being invertible) is shortened to land halfway to it, so the iteration stays on the valid
    sheet. The root is found without gradient; one implicit Newton step with gradient then
    carries ``dm = J^-1 (dm_d - dD/dparams)`` to the pixels and the parameters.
    """
    k1, k2, p1, p2 = params[..., 5:9].unbind(-1)
    tol = 8 * torch.finfo(xd.dtype).eps
    with torch.no_grad():
        kd = [t.detach() for t in (k1, k2, p1, p2)]
        t_fold = unified_distortion_fold(params)
        tx, ty = xd.detach(), yd.detach()
        bound = tol * (1 + tx.abs() + ty.abs())
        mx, my = tx, ty
        r2 = mx * mx + my * my
        inside = r2 < t_fold
        shrink = torch.sqrt(torch.where(inside, torch.ones_like(r2), 0.5 * t_fold / r2))
        mx, my = mx * shrink, my * shrink
        for _ in range(iterations):
            fx, fy = _distort(mx, my, *kd)
            rx, ry = fx - tx, fy - ty
            if bool(((rx.abs() + ry.abs()) <= bound).all()):
                break
            mx, my = fold_guarded_step(mx, my, rx, ry, *_distort_jacobian(mx, my, *kd), t_fold)
        fx, fy = _distort(mx, my, *kd)
        converged = ((fx - tx).abs() + (fy - ty).abs()) <= bound
        converged = converged & torch.isfinite(mx) & torch.isfinite(my)
        mx = torch.where(converged, mx, torch.zeros_like(mx))
        my = torch.where(converged, my, torch.zeros_like(my))
        jac = _distort_jacobian(mx, my, *kd)
    fx, fy = _distort(mx, my, k1, k2, p1, p2)
    mx, my, ok = newton_step_2d(mx, my, fx - xd, fy - yd, *jac)
    return mx, my, converged & ok


def unified_unproject(pixels: Tensor, params: Tensor, *,
                      iterations: int = UNIFIED_ITERATIONS) -> tuple[Tensor, Tensor]:
    """Unified (Mei) unprojection: undistort, then lift ``m`` to the unit sphere.

    ``X = (eta mx, eta my, eta - xi)``, ``eta = (xi + sqrt(1 + (1 - xi^2) r^2)) / (1 + r^2)``.

    Args:
        pixels: ``(..., 2)`` pixel coordinates.
        params: ``(..., 9)`` fx, fy, cx, cy, xi, k1, k2, p1, p2, or ``(..., 10)`` with the skew
            ``s`` (``u = fx mx + s my + cx``, OpenCV omnidir's ``K[0, 1]``).
        iterations: maximum Newton iterations of the undistortion (skipped when k = p = 0).

    Returns:
        ``rays (..., 3)`` unit norm and ``valid (...)``: ``1 + (1 - xi^2) r^2 > 0``, inside the
        distortion's fold, undistortion converged.
    """
    check_inputs("unified", pixels, params, 2, (9, 10), "pixels")
    if not (bool(params[..., 5:9].detach().ne(0).any()) or params.requires_grad):
        return unified_unproject_undistorted(pixels, params)
    mx, my, valid = _undistort(*_normalised(pixels, params), params, iterations)
    valid = valid & (mx * mx + my * my < unified_distortion_fold(params))
    return _lift(mx, my, params[..., 4], valid)


def unified_unproject_undistorted(pixels: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """`unified_unproject` of a camera without lens distortion (k = p = 0, which this does
    not check): the closed form alone, without the data-dependent branch, so ``torch.compile``
    traces it whole (``render.kernels.camera_grid``)."""
    check_inputs("unified", pixels, params, 2, (9, 10), "pixels")
    mx, my = _normalised(pixels, params)
    return _lift(mx, my, params[..., 4], torch.ones_like(mx, dtype=torch.bool))


def unified_unproject_undistorted_xyz(u: Tensor, v: Tensor, params: Tensor
                                      ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """`unified_unproject_undistorted` as components ``x, y, z, valid`` of pixel
    ``(u, v)``, without input checks (``CameraModel.unproject_xyz``)."""
    mx, my = _normalised_uv(u, v, params)
    return _lift_xyz(mx, my, params[..., 4], torch.ones_like(mx, dtype=torch.bool))


def _lift(mx: Tensor, my: Tensor, xi: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Undistorted normalised coordinates -> unit rays on the sphere (and their validity)."""
    x, y, z, valid = _lift_xyz(mx, my, xi, valid)
    return torch.stack((x, y, z), dim=-1), valid


def _lift_xyz(mx: Tensor, my: Tensor, xi: Tensor, valid: Tensor
              ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """`_lift` as components; invalid pixels get the optical axis (0, 0, 1)."""
    r2 = mx * mx + my * my
    rad = 1 + (1 - xi * xi) * r2
    valid = valid & (rad > 0)
    eta = (xi + safe_sqrt(rad, valid)) / (1 + r2)
    zero = torch.zeros_like(eta)
    return (torch.where(valid, eta * mx, zero), torch.where(valid, eta * my, zero),
            torch.where(valid, eta - xi, zero + 1), valid)


def _axis(like: Tensor) -> Tensor:
    return torch.tensor([0.0, 0.0, 1.0], dtype=like.dtype, device=like.device)


def unified_max_angle(params: Tensor) -> Tensor:
    """acos(-w), reduced to the angle of the distortion's fold where that comes first."""
    xi = params[..., 4]
    limit = torch.acos(-_unified_w(xi).clamp(max=1.0))
    t = unified_distortion_fold(params)
    finite = torch.isfinite(t)
    t = torch.where(finite, t, torch.zeros_like(t))
    rad = (1 + (1 - xi * xi) * t).clamp(min=0)
    eta = (xi + torch.sqrt(rad)) / (1 + t)
    fold = torch.acos((eta - xi).clamp(-1.0, 1.0))
    return torch.where(finite & (rad > 0), torch.minimum(limit, fold), limit).detach()


def _check_unified(params: Tensor) -> None:
    check_positive(params, (0, 1), _UNIFIED_NAMES, "unified")
    check_range(params, 4, 0.0, math.inf, _UNIFIED_NAMES, "unified")


UNIFIED = CameraModel(
    "unified", _UNIFIED_NAMES, unified_project, unified_unproject, unified_max_angle,
    {"focal": (0, 1), "center": (2, 3), "distortion": (4, 5, 6, 7, 8), "skew": (9,)},
    check_values=_check_unified, optional=("s",), radial=True,
    fisheye_draw=FisheyeDraw(ranges=(("unified_xi_range", (0.5, 1.0)),), zeros=4))


def unified_from_mirror(mirror: str, *, p: float = 0.0, d: float = 0.0, focal: float,
                        cx: float, cy: float, dtype: torch.dtype = torch.float64) -> Tensor:
    """Unified-model parameters of a central catadioptric camera, from its mirror (Barreto-Araujo).

    Barreto and Araujo, "Issues on the geometry of central catadioptric image formation",
    CVPR 2001 (and Geyer and Daniilidis, ECCV 2000): a mirror whose foci are ``d`` apart with
    latus rectum ``4 p``, seen by a camera at its second focus, is the unified model with

    ============ =========================== ===================================
    mirror       xi                          generalised focal gamma
    ============ =========================== ===================================
    parabolic    1                           2 p * focal (orthographic camera,
                                             ``focal`` in pixels per unit length)
    hyperbolic   d / sqrt(d^2 + 4 p^2)       2 p focal / sqrt(d^2 + 4 p^2)
    elliptic     d / sqrt(d^2 + 4 p^2)       2 p focal / sqrt(d^2 + 4 p^2)
    planar       0                           focal
    ============ =========================== ===================================

    The optical axis of the unified camera points from the mirror's focus towards the camera
    (the camera sees itself at the image centre); the image inversion of the mirror is absorbed
    into the orientation of the image axes, as a calibration does, so gamma is positive.

    Args:
        mirror: ``"parabolic"``, ``"hyperbolic"``, ``"elliptic"`` or ``"planar"``.
        p: latus rectum / 4, same unit as ``d`` (parabolic, hyperbolic, elliptic).
        d: distance between the foci (hyperbolic, elliptic).
        focal: the camera's focal length in pixels (pixels per unit length for parabolic).
        cx: principal point's u in pixels.
        cy: principal point's v in pixels.

    Returns:
        ``(9,)`` parameters fx, fy, cx, cy, xi, 0, 0, 0, 0 of the ``unified`` model.
    """
    if not isinstance(mirror, str):
        raise TypeError(f"mirror: expected a string, got {type(mirror).__name__}")
    for name, value in (("p", p), ("d", d), ("focal", focal), ("cx", cx), ("cy", cy)):
        if not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ValueError(f"{name}: expected a finite number, got {value!r}")
    if focal <= 0:
        raise ValueError(f"focal: expected > 0, got {focal}")
    if mirror == "parabolic":
        if p <= 0:
            raise ValueError(f"p: a parabolic mirror needs p > 0, got {p}")
        xi, gamma = 1.0, 2.0 * p * focal
    elif mirror in ("hyperbolic", "elliptic"):
        if p <= 0 or d <= 0:
            raise ValueError(f"p, d: a {mirror} mirror needs p > 0 and d > 0, got p={p}, d={d}")
        norm = math.sqrt(d * d + 4.0 * p * p)
        xi, gamma = d / norm, 2.0 * p * focal / norm
    elif mirror == "planar":
        xi, gamma = 0.0, float(focal)
    else:
        raise ValueError(f"mirror: expected 'parabolic', 'hyperbolic', 'elliptic' or 'planar', "
                         f"got {mirror!r}")
    return torch.tensor([gamma, gamma, cx, cy, xi, 0.0, 0.0, 0.0, 0.0], dtype=dtype)


# --------------------------------------------------------------------------------------------
# Extended unified (EUCM)
# --------------------------------------------------------------------------------------------

def eucm_project(points: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """EUCM projection ``u = fx x / (alpha d + (1 - alpha) z) + cx``.

    Args:
        points: ``(..., 3)``.
        params: ``(..., 6)`` fx, fy, cx, cy, alpha, beta.

    Returns:
        ``pixels (..., 2)`` and ``valid (...)``: ``z > -w d``.
    """
    check_inputs("eucm", points, params, 3, 6, "points")
    alpha, beta = params[..., 4], params[..., 5]
    x, y, z = points.unbind(-1)
    d2 = beta * (x * x + y * y) + z * z
    nonzero = d2 > torch.finfo(points.dtype).tiny
    d = safe_sqrt(d2, nonzero)
    valid = nonzero & (z > -_alpha_w(alpha) * d)
    den = alpha * d + (1 - alpha) * z
    return _pixels(safe_div(x, den, valid), safe_div(y, den, valid), params), valid


def eucm_unproject(pixels: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """EUCM unprojection ``mz = (1 - beta alpha^2 r^2) / (alpha sqrt(1 - (2 alpha - 1) beta r^2)
    + 1 - alpha)``, ray = normalise(mx, my, mz).

    Returns:
        ``rays (..., 3)`` and ``valid (...)``: alpha <= 1/2 or ``r^2 < 1 / (beta (2 alpha - 1))``.
    """
    check_inputs("eucm", pixels, params, 2, 6, "pixels")
    alpha, beta = params[..., 4], params[..., 5]
    mx, my = _normalised(pixels, params)
    r2 = mx * mx + my * my
    rad = 1 - (2 * alpha - 1) * beta * r2
    valid = rad > 0
    den = alpha * safe_sqrt(rad, valid) + 1 - alpha
    valid = valid & (den > 0)
    mz = safe_div(1 - beta * alpha * alpha * r2, den, valid)
    rays = torch.stack((mx, my, mz), dim=-1)
    n2 = r2 + mz * mz
    rays = rays * torch.rsqrt(torch.where(valid, n2, torch.ones_like(n2))).unsqueeze(-1)
    return rays, valid


def eucm_max_angle(params: Tensor) -> Tensor:
    """Angle where ``cos(theta) = -w sqrt(beta sin^2 + cos^2)``: pi - atan(sqrt((1 - w^2) /
    (w^2 beta))), pi for w >= 1."""
    w = _alpha_w(params[..., 4]).clamp(min=0)
    beta = params[..., 5]
    ok = (w > 0) & (w < 1)
    ratio = safe_div(1 - w * w, w * w * beta, ok)
    angle = math.pi - torch.atan(torch.sqrt(ratio.clamp(min=0)))
    return torch.where(w >= 1, torch.full_like(w, math.pi),
                       torch.where(w > 0, angle, torch.full_like(w, math.pi / 2))).detach()


def _check_eucm(params: Tensor) -> None:
    check_positive(params, (0, 1, 5), _EUCM_NAMES, "eucm")
    check_range(params, 4, 0.0, 1.0, _EUCM_NAMES, "eucm")


EUCM = CameraModel(
    "eucm", _EUCM_NAMES, eucm_project, eucm_unproject, eucm_max_angle,
    {"focal": (0, 1), "center": (2, 3), "distortion": (4, 5)}, check_values=_check_eucm,
    radial=True, fisheye_draw=FisheyeDraw(ranges=(("eucm_alpha_range", (0.55, 0.7)),
                                                  ("eucm_beta_range", (0.9, 1.2)))))


# --------------------------------------------------------------------------------------------
# Double sphere
# --------------------------------------------------------------------------------------------

def _ds_w2(xi: Tensor, alpha: Tensor) -> Tensor:
    w1 = _alpha_w(alpha)
    return (w1 + xi) / torch.sqrt(2 * w1 * xi + xi * xi + 1)


def double_sphere_project(points: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """Double-sphere projection ``u = fx x / (alpha d2 + (1 - alpha) (xi d1 + z)) + cx``.

    Args:
        points: ``(..., 3)``.
        params: ``(..., 6)`` fx, fy, cx, cy, xi, alpha.

    Returns:
        ``pixels (..., 2)`` and ``valid (...)``: ``z > -w2 d1``.
    """
    check_inputs("double_sphere", points, params, 3, 6, "points")
    xi, alpha = params[..., 4], params[..., 5]
    x, y, z = points.unbind(-1)
    d1, nonzero = _norm(points)
    zz = xi * d1 + z
    q2 = x * x + y * y + zz * zz
    d2 = safe_sqrt(q2, q2 > torch.finfo(points.dtype).tiny)
    valid = nonzero & (z > -_ds_w2(xi, alpha) * d1)
    den = alpha * d2 + (1 - alpha) * zz
    valid = valid & (den > 0)
    return _pixels(safe_div(x, den, valid), safe_div(y, den, valid), params), valid


def double_sphere_unproject(pixels: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """Double-sphere unprojection (Usenko et al. 2018, eq. 46-50).

    ``mz = (1 - alpha^2 r^2) / (alpha sqrt(1 - (2 alpha - 1) r^2) + 1 - alpha)``,
    ``X = (mz xi + sqrt(mz^2 + (1 - xi^2) r^2)) / (mz^2 + r^2) (mx, my, mz) - (0, 0, xi)``.

    Returns:
        ``rays (..., 3)`` unit norm and ``valid (...)``: alpha <= 1/2 or
        ``r^2 < 1 / (2 alpha - 1)``, and a real second square root.
    """
    check_inputs("double_sphere", pixels, params, 2, 6, "pixels")
    xi, alpha = params[..., 4], params[..., 5]
    mx, my = _normalised(pixels, params)
    r2 = mx * mx + my * my
    rad = 1 - (2 * alpha - 1) * r2
    valid = rad > 0
    den = alpha * safe_sqrt(rad, valid) + 1 - alpha
    valid = valid & (den > 0)
    mz = safe_div(1 - alpha * alpha * r2, den, valid)
    rad2 = mz * mz + (1 - xi * xi) * r2
    valid = valid & (rad2 >= 0)
    scale = safe_div(mz * xi + safe_sqrt(rad2, valid & (rad2 > 0)), mz * mz + r2, valid)
    rays = torch.stack((scale * mx, scale * my, scale * mz - xi), dim=-1)
    rays = torch.where(valid.unsqueeze(-1), rays, torch.zeros_like(rays) + _axis(rays))
    return rays, valid


def double_sphere_max_angle(params: Tensor) -> Tensor:
    """acos(-w2)."""
    return torch.acos(-_ds_w2(params[..., 4], params[..., 5]).clamp(-1.0, 1.0)).detach()


def _check_ds(params: Tensor) -> None:
    check_positive(params, (0, 1), _DS_NAMES, "double_sphere")
    check_range(params, 4, -1.0, 1.0, _DS_NAMES, "double_sphere")
    check_range(params, 5, 0.0, 1.0, _DS_NAMES, "double_sphere")


DOUBLE_SPHERE = CameraModel(
    "double_sphere", _DS_NAMES, double_sphere_project, double_sphere_unproject,
    double_sphere_max_angle, {"focal": (0, 1), "center": (2, 3), "distortion": (4, 5)},
    check_values=_check_ds, radial=True,
    fisheye_draw=FisheyeDraw(ranges=(("ds_xi_range", (-0.3, 0.0)), ("ds_alpha_range", (0.5, 0.7)))))
