"""Where a calibration's corners lie, and how well its result is known over the image.

A fit can reach the noise floor on its own corners and still be pixels off elsewhere: with a
few views the corners cover a small part of the image, and the lens is extrapolated beyond
them. `assess_coverage` measures three things over the **calibrated area** (the pixels
whose fitted ray is valid, inside the image and within ``fov``, e.g. the image circle of a
fisheye photograph):

* **cells**: the share of the calibrated area's grid cells (``CELLS`` along the longer image
  side, square cells) holding at least one corner; and, reported only, the share of the area
  inside the convex hull of all corners;
* **angle**: the largest angle off the optical axis that a corner reaches, against the largest
  of the calibrated area (its half field of view);
* **pixel error**: the predicted error of the calibration over the area **no farther off axis
  than the corners reach** (``covered_rays``): the RMS distance there between where the fitted
  and the true camera project the same ray, ``e = sqrt(mean_g |J_g delta|^2)`` for an error
  ``delta`` of the intrinsics, ``J_g = d project(d_g, p) / dp`` (autograd) at the fitted ray
  ``d_g`` of grid pixel ``g``. ``delta`` is Gaussian of covariance ``C``
  (``FitResult.covariance``: the block of the intrinsics in the inverse of the full normal
  matrix, i.e. with the poses marginalised, times the noise ``sigma^2 = sum r^2 / (2 M - n)``
  that the residuals show), so ``e^2`` is a weighted sum of chi-square variables:
  ``pixel_error`` is its median's root (`predicted_error`), ``pixel_rms`` the root of its
  mean (the RMS of the per-pixel std ``sqrt(trace(J C J^T))``, whose map ``uncertainty.png``
  draws). The median is the figure tested: a single fit's true error falls below it half the
  time (with few views one direction of the intrinsics dominates, ``e`` is then nearly
  ``|N(0, 1)|`` times ``pixel_rms``, median 0.67 of it). The area beyond the corners
  (``max_pixel_std_fov``) is reported and mapped only, as no full board can be seen at the
  rim of a 180 degree fisheye (the printed page must fit in the image circle): extrapolation
  beyond the corners is judged by the angle share instead.

Validation (``benchmarks/calibration_uncertainty.py``, ``benchmarks/results/
calibration_uncertainty.md``): synthetic views of a 9 x 6 board by a Kannala-Brandt 190-degree
and a unified 230-degree lens on 1280 x 1024, 3, 8 and 21 views, 0.1-0.5 px of noise: the
median over seeds of ``pixel_error`` / true error is within [0.7, 1.4] in every case (table
there). On real photographs `leave_one_out` refits without each view (the jackknife):
on synthetic views it gives 1.0-1.3 times ``pixel_rms``; where it is far above (5 times on
the real photographs of ``tests/data/ocamcalib_fisheye2``: 0.39 against 0.084 px),
the residuals are not independent per corner (a lens the model does not quite fit, corners
biased per view) and the prediction is too small.

Thresholds (``THRESHOLDS``; ``tests/test_calibration_report.py`` pins both sides), from that
table over the image circle (40 seeds a case): 21 spread views of the Kannala-Brandt lens give
a pixel error of 0.07-0.44 px (noise 0.1-0.5 px) and cell shares of 0.75-0.99, all passing; 3
views give 0.21-2.1 px and 0.24-0.62 (the unified lens 0.39-4.2 px, 0.12-0.38), none passing;
8 views pass where the noise is low (25 and 6 of 40). Earlier measurements (with the largest per-pixel std, 1.2-1.6
times the pixel error): a 9 x 12 checkerboard seen with 0.2 px of noise by two fisheyes of
``tests/conftest.py`` gives cell shares of 0.32-0.43 with 3-4 views and 0.78-0.95 with 10-15
views spread over the image; rendered boards with detected corners
(``tests/test_calibration_images.py``) 0.24-0.32 with 3-4 views, 0.54-0.68 with 10-12; the
real images of ``tests/data/ocamcalib_fisheye2`` (8 views) 0.78. Hence:

* ``max_pixel_error`` 0.5 px: above it the camera is not known to half a pixel (RMS) where
  the corners reach;
* ``min_cells`` 0.5: fewer than half of the area's cells hold a corner;
* ``min_angle`` 0.6: the corners stop short of 60% of the half field of view.

Any one failing makes the fit *poorly constrained*: ``omniscape-torch fit`` then exits 3 unless
``--accept-coverage``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import torch
from torch import Tensor

from ..cameras import Camera

#: Limits of a well-constrained fit (module docstring).
THRESHOLDS = {"max_pixel_error": 0.5, "min_cells": 0.5, "min_angle": 0.6}

#: Grid cells along the longer image side for the cell share.
CELLS = 12

#: Grid samples along the longer image side for the pixel std map.
STD_GRID = 48


@dataclass
class Coverage:
    """Outcome of `assess_coverage` (module docstring).

    Attributes:
        cells: share of the calibrated area's cells holding a corner, in [0, 1].
        hull: share of the calibrated area inside the convex hull of all corners.
        angle: largest angle off the optical axis of a corner, radians.
        half_fov: largest angle off the axis of the calibrated area, radians.
        pixel_error: the predicted pixel error of the calibration over the area no farther
            off axis than the corners reach: the median of its RMS distance from the truth
            there (`predicted_error`; the figure tested), pixels (inf when the
            covariance is not available: degenerate data).
        pixel_rms: the root of that RMS distance's mean square (the RMS of the predicted
            pixel std over the area), pixels; `leave_one_out` estimates the same.
        max_pixel_std: largest predicted pixel std over that area, pixels (reported).
        median_pixel_std: its median, pixels.
        max_pixel_std_fov: largest over the whole area (beyond the corners too), pixels.
        std_map: ``(h, w)`` predicted pixel std at ``grid`` (NaN outside the area).
        grid: ``(h, w, 2)`` pixels (u, v) of the std map.
        cell_map: ``(ch, cw)`` int8: -1 outside the area, 0 no corner, 1 a corner.
        fov: the full field of view that bounded the area (None: the whole valid image).
        thresholds: the limits tested.
        warnings: one line per failed limit (empty when well constrained).
    """

    cells: float
    hull: float
    angle: float
    half_fov: float
    pixel_error: float
    pixel_rms: float
    max_pixel_std: float
    median_pixel_std: float
    max_pixel_std_fov: float
    std_map: Tensor
    grid: Tensor
    cell_map: Tensor
    fov: float | None
    thresholds: dict = field(default_factory=lambda: dict(THRESHOLDS))
    warnings: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """No limit failed."""
        return not self.warnings

    @property
    def angle_share(self) -> float:
        """``angle / half_fov``."""
        return self.angle / self.half_fov if self.half_fov > 0 else 0.0

    def to_dict(self) -> dict:
        """JSON-ready figures (angles in degrees, as at every I/O boundary)."""
        def num(x: float):
            return x if math.isfinite(x) else None
        return {"ok": self.ok, "cells": self.cells, "hull": self.hull,
                "angle_deg": math.degrees(self.angle), "half_fov_deg": math.degrees(self.half_fov),
                "angle_share": self.angle_share, "pixel_error": num(self.pixel_error),
                "pixel_rms": num(self.pixel_rms),
                "max_pixel_std": num(self.max_pixel_std),
                "median_pixel_std": num(self.median_pixel_std),
                "max_pixel_std_fov": num(self.max_pixel_std_fov),
                "fov_deg": None if self.fov is None else math.degrees(self.fov),
                "thresholds": dict(self.thresholds), "warnings": list(self.warnings)}


def _angle(rays: Tensor) -> Tensor:
    return torch.atan2(torch.linalg.vector_norm(rays[..., :2], dim=-1), rays[..., 2])


def _grid(image_size: tuple[int, int], n: int, dtype) -> Tensor:
    """``(h, w, 2)`` pixel centres of an ``n``-per-longer-side grid of square cells."""
    height, width = image_size
    step = max(height, width) / n
    h, w = max(round(height / step), 1), max(round(width / step), 1)
    v = (torch.arange(h, dtype=dtype) + 0.5) * (height / h) - 0.5
    u = (torch.arange(w, dtype=dtype) + 0.5) * (width / w) - 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack((uu, vv), -1)


def _jacobian(camera: Camera, rays: Tensor) -> Tensor:
    """``(N, 2, P)`` derivative of the projection of fixed ``rays (N, 3)`` by the intrinsics."""
    params = camera.params.detach().double()
    p = params.expand(rays.shape[0], -1).clone().requires_grad_(True)
    pixels, _ = camera.model.project(rays.detach().double(), p)
    return torch.stack([torch.autograd.grad(pixels[:, k].sum(), p, retain_graph=k == 0)[0]
                        for k in range(2)], 1)


def pixel_std(camera: Camera, covariance: Tensor, rays: Tensor) -> Tensor:
    """Predicted RMS pixel error ``sqrt(trace(J C J^T))`` of projecting fixed ``rays (N, 3)``
    with intrinsics of covariance ``covariance (P, P)`` (module docstring); ``(N,)`` pixels
    (inf where the covariance is not finite)."""
    cov = covariance.detach().double()
    if not bool(torch.isfinite(cov).all()):
        return torch.full(rays.shape[:-1], math.inf, dtype=torch.float64)
    jac = _jacobian(camera, rays)
    var = torch.einsum("nkp,pq,nkq->n", jac, cov, jac)
    return var.clamp(min=0).sqrt()


def predicted_error(camera: Camera, covariance: Tensor, rays: Tensor) -> tuple[float, float]:
    """The distribution of the calibration's RMS pixel error over ``rays (N, 3)`` (module
    docstring): ``(median, rms)`` of ``e = sqrt(mean_g |J_g delta|^2)`` for intrinsics errors
    ``delta ~ N(0, covariance)``, pixels (inf where the covariance is not finite).

    ``e^2 = delta^T M delta`` with ``M = mean_g J_g^T J_g`` is a weighted sum of chi-square
    variables of weights the eigenvalues of ``M C``: its mean is ``trace(M C)`` (``rms^2``, the
    mean of ``pixel_std^2``); its median that of a scaled chi-square of the same mean and
    variance (``nu = trace(M C)^2 / trace((M C)^2)`` degrees of freedom), by Wilson and
    Hilferty's approximation ``nu (1 - 2 / (9 nu))^3``."""
    cov = covariance.detach().double()
    if rays.shape[0] == 0 or not bool(torch.isfinite(cov).all()):
        return math.inf, math.inf
    jac = _jacobian(camera, rays)
    mc = torch.einsum("nkp,nkq->pq", jac, jac) / rays.shape[0] @ cov
    mean, square = float(torch.trace(mc)), float(torch.trace(mc @ mc))
    if not mean > 0 or not square > 0:
        return 0.0, 0.0
    nu = mean * mean / square
    median = mean * (1 - 2 / (9 * nu)) ** 3
    return math.sqrt(max(median, 0.0)), math.sqrt(mean)


def _within_reach(theta: Tensor, valid: Tensor, angle: float) -> Tensor:
    """Where the grid's angles off axis ``theta`` are no farther than the corners reach
    (``angle``), or at the area's innermost sample (a board seen on the axis only)."""
    nearest = float(theta[valid].min()) if bool(valid.any()) else 0.0
    return theta <= max(angle, nearest)


def covered_rays(camera: Camera, image_points: Sequence[Tensor], *, fov: float | None = None,
                 std_grid: int = STD_GRID) -> tuple[Tensor, Tensor]:
    """The grid pixels over which the calibration is judged and their rays through ``camera``:
    the valid pixels of a ``std_grid``-per-longer-side grid (within ``fov``) no farther off the
    optical axis than the corners reach (module docstring).

    Args:
        camera: the fitted camera.
        image_points: per view ``(N_i, 2)`` corner pixels.
        fov: full field of view bounding the area (radians; None: the whole valid image).
        std_grid: grid samples along the longer image side.

    Returns:
        ``(K, 2)`` pixels (u, v) and ``(K, 3)`` unit rays, float64.
    """
    cam = Camera(camera.model, camera.params.detach().double(), camera.image_size, fov=fov)
    grid = _grid(cam.image_size, std_grid, torch.float64)
    corners = torch.cat([p.detach().double().reshape(-1, 2) for p in image_points])
    with torch.no_grad():
        rays, valid = cam.unproject(grid)
        corner_rays, corner_valid = cam.model.unproject(corners, cam.params)
    angle = float(_angle(corner_rays)[corner_valid].max()) if bool(corner_valid.any()) else 0.0
    keep = valid & _within_reach(_angle(rays), valid, angle)
    return grid[keep], rays[keep]


@dataclass
class Resampling:
    """Outcome of `leave_one_out`.

    Attributes:
        pixel_error: the jackknife estimate of the calibration's pixel error over the area the
            corners reach, pixels: the RMS over that area of
            ``sqrt((V - 1) / V sum_i |x_i - x_mean|^2)``, ``x_i`` the projection of a fixed ray
            by the fit without view ``i``; the same statistic as ``Coverage.pixel_error``.
        moves: ``(V,)`` RMS move of the projections (over that area) from the full fit to the
            fit without each view, pixels.
        failed: views whose refit did not converge (their fits are still used).
    """

    pixel_error: float
    moves: Tensor
    failed: list[int]

    def to_dict(self) -> dict:
        """JSON-ready figures."""
        return {"pixel_error": self.pixel_error, "moves": self.moves.tolist(),
                "failed": list(self.failed)}


def leave_one_out(result, object_points, image_points, *, fov: float | None = None,
                  std_grid: int = STD_GRID) -> Resampling:
    """Resampling check of a fit's predicted error (``Coverage.pixel_error``): refit without
    each view in turn (from the fit's own intrinsics and poses, the same frozen parameters) and
    measure how far the projections of fixed rays over the area the corners reach move (the
    jackknife; `Resampling`). Where the views are alike and the residuals independent it
    agrees with the prediction; on real photographs it also sees what the noise model does not
    (corners biased per view, a lens the model does not quite fit).

    Args:
        result: the `FitResult` of ``fit`` on these views
            (not a conversion), at least 3 views.
        object_points: the target points given to ``fit``.
        image_points: the pixels given to ``fit`` (per view).
        fov: full field of view bounding the area (radians; None: the whole valid image).
        std_grid: grid samples along the longer image side.

    Returns:
        A `Resampling`.
    """
    from .fit import fit, prepare_views

    points, pixels = prepare_views(object_points, image_points)
    if result.camera is None or len(points) != result.poses.shape[0] or len(points) < 3:
        raise ValueError(f"result: expected the fit of these {len(points)} views (at least 3) "
                         f"with a camera, got {result.poses.shape[0]} poses")
    camera = result.camera
    _, rays = covered_rays(camera, pixels, fov=fov, std_grid=std_grid)
    with torch.no_grad():
        base, _ = camera.model.project(rays, camera.params.double())
    frozen = [n for n in result.param_names if n not in result.free_names]
    projected, failed = [], []
    for i in range(len(points)):
        keep = [j for j in range(len(points)) if j != i]
        refit = fit([points[j] for j in keep], [pixels[j] for j in keep], camera.model,
                    camera.image_size, init=result.params, poses=result.poses[keep],
                    freeze=frozen)
        if not refit.converged:
            failed.append(i)
        with torch.no_grad():
            projected.append(camera.model.project(rays, refit.params)[0])
    stack = torch.stack(projected)                                   # [V, K, 2]
    v = len(points)
    spread = (stack - stack.mean(0)).square().sum(-1).sum(0) * (v - 1) / v
    moves = (stack - base).square().sum(-1).mean(-1).sqrt()
    error = float(spread.mean().sqrt()) if rays.shape[0] else math.nan
    return Resampling(pixel_error=error, moves=moves, failed=failed)


def _convex_hull(points: Tensor) -> list[tuple[float, float]]:
    """Vertices of the convex hull of ``points (N, 2)``, counter-clockwise (monotone chain)."""
    pts = sorted(set(map(tuple, points.tolist())))

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list = []
    upper: list = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return lower[:-1] + upper[:-1]


def _inside_hull(points: Tensor, query: Tensor) -> Tensor:
    """``(M,)`` True where ``query (M, 2)`` lies in the convex hull of ``points (N, 2)``."""
    vertices = _convex_hull(points)
    if len(vertices) < 3:
        return torch.zeros(query.shape[0], dtype=torch.bool)
    hull = torch.tensor(vertices, dtype=query.dtype)                     # counter-clockwise
    a, b = hull, hull.roll(-1, 0)
    edge = b - a                                                         # [K, 2]
    rel = query[:, None, :] - a[None]                                    # [M, K, 2]
    side = edge[None, :, 0] * rel[..., 1] - edge[None, :, 1] * rel[..., 0]
    return (side >= 0).all(-1)


def assess_coverage(camera: Camera, covariance: Tensor, image_points: Sequence[Tensor], *,
                    fov: float | None = None, thresholds: dict | None = None,
                    cells: int = CELLS, std_grid: int = STD_GRID) -> Coverage:
    """Coverage figures and warnings of a calibration (module docstring).

    Args:
        camera: the fitted camera (``FitResult.camera``).
        covariance: ``(P, P)`` covariance of its intrinsics (``FitResult.covariance``).
        image_points: per view ``(N_i, 2)`` corner pixels used by the fit.
        fov: full field of view (radians) bounding the calibrated area, e.g. the image
            circle (``calibration.convert.image_circle``); None: the whole valid image.
        thresholds: overrides of ``THRESHOLDS``.
        cells: grid cells along the longer image side.
        std_grid: std map samples along the longer image side.

    Returns:
        A `Coverage`.
    """
    limits = {**THRESHOLDS, **(thresholds or {})}
    unknown = set(limits) - set(THRESHOLDS)
    if unknown:
        raise ValueError(f"thresholds: unknown names {sorted(unknown)}; expected "
                         f"{sorted(THRESHOLDS)}")
    cam = Camera(camera.model, camera.params.detach().double(), camera.image_size, fov=fov)
    corners = torch.cat([p.detach().double().reshape(-1, 2) for p in image_points])

    # the calibrated area on a fine grid of square cells
    grid = _grid(cam.image_size, std_grid, torch.float64)
    with torch.no_grad():
        rays, valid = cam.unproject(grid)
    theta = _angle(rays)
    half_fov = float(theta[valid].max()) if bool(valid.any()) else 0.0
    corner_rays, corner_valid = cam.model.unproject(corners, cam.params)
    angle = float(_angle(corner_rays)[corner_valid].max()) if bool(corner_valid.any()) else 0.0

    std = torch.full(valid.shape, math.nan, dtype=torch.float64)
    if bool(valid.any()):
        std[valid] = pixel_std(cam, covariance, rays[valid])
    reached = valid & _within_reach(theta, valid, angle)
    within = std[reached]
    max_std = float(within.max()) if within.numel() else math.inf
    median_std = float(within.median()) if within.numel() else math.inf
    error, rms = predicted_error(cam, covariance, rays[reached])
    max_std_fov = float(std[valid].max()) if bool(valid.any()) else math.inf

    cell_centres = _grid(cam.image_size, cells, torch.float64)
    ch, cw = cell_centres.shape[:2]
    with torch.no_grad():
        _, cell_valid = cam.unproject(cell_centres)
    h, w = cam.image_size
    col = (((corners[:, 0] + 0.5) / w) * cw).floor().long().clamp(0, cw - 1)
    row = (((corners[:, 1] + 0.5) / h) * ch).floor().long().clamp(0, ch - 1)
    touched = torch.zeros(ch, cw, dtype=torch.bool)
    touched[row, col] = True
    cell_map = torch.where(cell_valid, touched.to(torch.int8), torch.full_like(
        touched, -1, dtype=torch.int8))
    n_valid = int(cell_valid.sum())
    cell_share = float((touched & cell_valid).sum()) / n_valid if n_valid else 0.0
    inside = _inside_hull(corners, grid[valid]) if bool(valid.any()) else torch.zeros(0)
    hull_share = float(inside.double().mean()) if inside.numel() else 0.0

    warnings = []
    if not error <= limits["max_pixel_error"]:
        where = ""
        if math.isfinite(max_std):
            u, v = grid[reached][within.argmax()].tolist()
            where = f" (largest {max_std:.3g} px at u, v = {u:.0f}, {v:.0f})"
        warnings.append(
            f"the calibration is uncertain: its predicted pixel error is {error:.3g} px "
            f"(RMS where the corners reach){where}, above {limits['max_pixel_error']:g} px: add "
            f"views (or corners per view) where it is largest"
            if math.isfinite(error) else
            "the calibration is undetermined: its covariance is not finite (degenerate views)")
    if cell_share < limits["min_cells"]:
        warnings.append(f"the corners cover {100 * cell_share:.0f}% of the image's cells, below "
                        f"{100 * limits['min_cells']:.0f}%: add views with the board near the "
                        f"edges and corners of the image")
    share = angle / half_fov if half_fov > 0 else 0.0
    if share < limits["min_angle"]:
        warnings.append(f"the corners reach {math.degrees(angle):.1f} deg off the optical axis, "
                        f"{100 * share:.0f}% of the {math.degrees(half_fov):.1f} deg the image "
                        f"sees (below {100 * limits['min_angle']:.0f}%): add views near the "
                        f"edge of the field of view")
    return Coverage(cells=cell_share, hull=hull_share, angle=angle, half_fov=half_fov,
                    pixel_error=error, pixel_rms=rms, max_pixel_std=max_std, median_pixel_std=median_std,
                    max_pixel_std_fov=max_std_fov, std_map=std, grid=grid,
                    cell_map=cell_map, fov=fov, thresholds=limits, warnings=warnings)
