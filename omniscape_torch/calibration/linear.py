"""Closed-form initialisers for planar targets: OCamCalib's linear calibration and planar poses.

Both take a planar target: points ``(X, Y, 0)`` in the target's frame.

* `scaramuzza_linear`: Scaramuzza, Martinelli and Siegwart, "A toolbox for easily
  calibrating omnidirectional cameras", IROS 2006, section IV (OCamCalib's ``calibrate``).
  A pixel's sensor point ``(pu, pv)`` (centre removed, affine part identity) sees the ray
  ``(pu, pv, g(rho))`` with ``g = -f``, parallel to ``P = R X + t = X r1 + Y r2 + t``. The third
  row of ``ray x P = 0``, ``pu P_y - pv P_x = 0``, is linear and homogeneous in
  ``(r11, r12, r21, r22, t1, t2)``: per view its null vector (SVD), then ``r31, r32`` and the
  scale from the orthonormality of ``r1, r2``. The first two rows,
  ``P_x f(rho) + pu t3 = -pu (r31 X + r32 Y)`` and the same with ``(P_y, pv)``, are linear in the
  polynomial and the per-view ``t3``: one least-squares solve over all views. As in OCamCalib,
  ``a1 = 0`` (``f'(0) = 0``) and the polynomial is solved in the normalised radius ``rho / s``.
  Each view leaves a mirror ambiguity (the sign of ``(r31, r32)``); the candidate whose
  single-view solve fits better is kept.
* `planar_pose`: the pose of a planar target from unit rays (any central camera whose
  rays are known): the homography ``ray ~ H (X, Y, 1)`` by DLT on Hartley-normalised target
  coordinates, ``H = lambda [r1 r2 t]``, ``R`` the nearest rotation to ``[r1 r2 r1 x r2]``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .params import matrix_to_axis_angle


def _nearest_rotation(m: Tensor) -> Tensor:
    """The rotations nearest to ``m (..., 3, 3)`` (SVD, determinant +1)."""
    u, _, vh = torch.linalg.svd(m)
    d = torch.sign(torch.linalg.det(u @ vh))
    fix = torch.stack((torch.ones_like(d), torch.ones_like(d), d), -1)  # [..., 3]
    return (u * fix[..., None, :]) @ vh


def _null_vector(a: Tensor) -> Tensor:
    return torch.linalg.svd(a, full_matrices=False)[2][..., -1, :]


def _check_planar(points: Tensor, what: str = "object_points") -> None:
    extent = float(points[..., :2].abs().max())
    if float(points[..., 2].abs().max()) > 1e-9 * max(extent, 1.0):
        raise ValueError(f"{what}: the linear initialisation needs a planar target (Z = 0 for "
                         f"every point); pass init and poses for other targets")


def planar_pose(points: Tensor, rays: Tensor, valid: Tensor | None = None) -> Tensor:
    """Pose ``(..., 6)`` (axis-angle, translation) of a planar target from the unit rays that see
    it; batched over leading dimensions (several views of the same number of points).

    Args:
        points: ``(..., N, 3)`` target points with Z = 0, N >= 4 (valid ones).
        rays: ``(..., N, 3)`` rays (any length, pointing at the points) in the camera frame.
        valid: ``(..., N)`` the points to use (default all; at least 4 per pose): the others
            get zero weight in every sum, as if absent.

    Returns:
        ``(..., 6)`` with ``rays ~ R points + t``, float64.
    """
    _check_planar(points)
    w = (torch.ones(points.shape[:-1], dtype=points.dtype) if valid is None
         else valid.to(points.dtype))  # [..., N]
    xy = points[..., :2]
    count = w.sum(-1)  # [...]
    mean = (xy * w[..., None]).sum(-2) / count[..., None]  # [..., 2]
    spread = ((xy - mean[..., None, :]).norm(dim=-1) * w).sum(-1) / count
    scale = math.sqrt(2) / spread.clamp(min=1e-300)  # [...]
    q = torch.cat(((xy - mean[..., None, :]) * scale[..., None, None],
                   torch.ones_like(xy[..., :1])), dim=-1)  # [..., N, 3]
    rx, ry, rz = (c[..., None] for c in rays.unbind(-1))
    zero = torch.zeros_like(q)
    # rows of ray x (H q) = 0, unknowns the rows h1, h2, h3 of H; absent points weigh 0
    rows = torch.cat((
        torch.cat((zero, -rz * q, ry * q), -1),
        torch.cat((rz * q, zero, -rx * q), -1),
        torch.cat((-ry * q, rx * q, zero), -1)), -2) * torch.cat((w, w, w), -1)[..., None]
    h = _null_vector(rows).reshape(rows.shape[:-2] + (3, 3))
    zeros, ones = torch.zeros_like(scale), torch.ones_like(scale)
    norm = torch.stack((torch.stack((scale, zeros, -scale * mean[..., 0]), -1),
                        torch.stack((zeros, scale, -scale * mean[..., 1]), -1),
                        torch.stack((zeros, zeros, ones), -1)), -2)  # [..., 3, 3]
    h = h @ norm
    h = h / (0.5 * (h[..., :, 0].norm(dim=-1) + h[..., :, 1].norm(dim=-1)))[..., None, None]
    xy1 = torch.cat((xy, torch.ones_like(xy[..., :1])), -1)
    facing = (((xy1 @ h.transpose(-1, -2)) * rays).sum(-1) * w).sum(-1)  # [...]
    h = torch.where((facing < 0)[..., None, None], -h, h)
    r1, r2 = h[..., :, 0], h[..., :, 1]
    rotation = _nearest_rotation(torch.stack((r1, r2, torch.linalg.cross(r1, r2)), dim=-1))
    axis_angle = matrix_to_axis_angle(rotation.reshape(-1, 3, 3)).reshape(rotation.shape[:-2]
                                                                          + (3,))
    return torch.cat((axis_angle, h[..., :, 2]), -1)


def _extrinsic_candidates(xy: Tensor, pu: Tensor, pv: Tensor) -> list[Tensor]:
    """The two ``(r1, r2, t1, t2)`` solutions ``(8,)`` = r11, r21, r31, r12, r22, r32, t1, t2."""
    x, y = xy.unbind(-1)
    rows = torch.stack((-pv * x, -pv * y, pu * x, pu * y, -pv, pu), dim=-1)
    r11, r12, r21, r22, t1, t2 = _null_vector(rows).unbind()
    # the sensor point and (P_x, P_y) point the same way
    if float((pu * (r11 * x + r12 * y + t1) + pv * (r21 * x + r22 * y + t2)).sum()) < 0:
        r11, r12, r21, r22, t1, t2 = -r11, -r12, -r21, -r22, -t1, -t2
    # |r1| = |r2| and r1 . r2 = 0 give r31, r32 up to a common sign
    a = r11 * r12 + r21 * r22
    b, c = r11 * r11 + r21 * r21, r12 * r12 + r22 * r22
    r32_sq = 0.5 * ((b - c) + torch.sqrt((b - c) ** 2 + 4 * a * a))
    r32 = torch.sqrt(r32_sq)
    r31 = -a / r32 if float(r32) > 1e-12 * float(b + c) else torch.sqrt((c - b).clamp(min=0))
    scale = torch.rsqrt(b + r31 * r31)
    out = []
    for sign in (1.0, -1.0):
        out.append(scale * torch.stack((r11, r21, sign * r31, r12, r22, sign * r32, t1, t2)))
    return out


def _poly_system(views, degree: int, s: float):
    """Rows of the second linear system: ``[P f-columns | p t3-columns] = -p Cz``."""
    powers = [0] + list(range(2, degree + 1))
    blocks, rhs = [], []
    n_views = len(views)
    for k, (xy, pu, pv, ext) in enumerate(views):
        r11, r21, r31, r12, r22, r32, t1, t2 = ext.unbind()
        x, y = xy.unbind(-1)
        rho = torch.sqrt(pu * pu + pv * pv)
        cols = torch.stack([s * (rho / s) ** i for i in powers], -1)  # [N, degree]
        cz = r31 * x + r32 * y
        for p_comp, s_comp in ((r11 * x + r12 * y + t1, pu), (r21 * x + r22 * y + t2, pv)):
            t3 = torch.zeros(len(x), n_views, dtype=xy.dtype)
            t3[:, k] = s_comp
            blocks.append(torch.cat((p_comp[:, None] * cols, t3), -1))
            rhs.append(-s_comp * cz)
    return torch.cat(blocks), torch.cat(rhs), powers


def _lstsq(a: Tensor, b: Tensor) -> tuple[Tensor, float]:
    norm = a.norm(dim=0).clamp(min=1e-300)
    sol = torch.linalg.lstsq(a / norm, b[:, None]).solution[:, 0] / norm
    return sol, float((a @ sol - b).norm())


def scaramuzza_linear(object_points: list[Tensor], image_points: list[Tensor],
                      image_size: tuple[int, int], degree: int = 4,
                      center: tuple[float, float] | None = None) -> tuple[Tensor, Tensor]:
    """OCamCalib's linear calibration (see the module docstring).

    Args:
        object_points: per view ``(N_i, 3)`` planar target points (Z = 0), float64.
        image_points: per view ``(N_i, 2)`` pixels (u, v).
        image_size: ``(H, W)``.
        degree: polynomial degree N (coefficients a0, a1 = 0, a2, ..., aN).
        center: ``(cx, cy)``; default the image centre ``((W - 1) / 2, (H - 1) / 2)``.

    Returns:
        ``params (6 + N,)`` = cx, cy, 1, 0, 0, a0, ..., aN and ``poses (V, 6)``.

    Raises:
        ValueError: a non-planar target, or a solution that is not a camera (a0 >= 0).
    """
    h, w = image_size
    cx, cy = ((w - 1) / 2, (h - 1) / 2) if center is None else center
    s = 0.5 * math.hypot(h, w)
    prepared = []
    for pts, pix in zip(object_points, image_points):
        _check_planar(pts)
        prepared.append((pts[:, :2], pix[:, 0] - cx, pix[:, 1] - cy))
    chosen = []
    for xy, pu, pv in prepared:
        best = None
        for ext in _extrinsic_candidates(xy, pu, pv):
            a, b, _ = _poly_system([(xy, pu, pv, ext)], degree, s)
            sol, res = _lstsq(a, b)
            physical = float(sol[0]) < 0 and float(sol[-1]) > 0  # a0 < 0, t3 > 0
            key = (not physical, res)
            if best is None or key < best[0]:
                best = (key, ext)
        chosen.append(best[1])
    a, b, powers = _poly_system([(*p, e) for p, e in zip(prepared, chosen)], degree, s)
    sol, _ = _lstsq(a, b)
    poly = torch.zeros(degree + 1, dtype=a.dtype)
    for j, i in enumerate(powers):
        poly[i] = sol[j] * s ** (1 - i)
    if float(poly[0]) >= 0:
        raise ValueError("image_points: the linear solution is not a camera (a0 >= 0); are the "
                         "points of each view in the same order as object_points?")
    poses = []
    for ext, t3 in zip(chosen, sol[len(powers):]):
        r1, r2, t12 = ext[:3], ext[3:6], ext[6:]
        rotation = _nearest_rotation(torch.stack((r1, r2, torch.linalg.cross(r1, r2)), -1))
        poses.append(torch.cat((matrix_to_axis_angle(rotation), t12, t3[None])))
    params = torch.cat((torch.tensor([cx, cy, 1.0, 0.0, 0.0], dtype=a.dtype), poly))
    return params, torch.stack(poses)
