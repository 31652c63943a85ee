"""Calibration from correspondences: intrinsics and per-view poses by least squares.

Given target points ``X`` (checkerboard corners or any known points, in the target's frame)
and their detected pixels in several views, :func:`fit` minimises the reprojection error

    sum_views sum_points rho(|project(R_v X + t_v, params) - pixels|^2 / scale^2)

over the intrinsics of one model and the pose ``(r_v, t_v)`` of every view, with the model's own
differentiable ``project`` as the residual function. Jacobians come from autograd in float64:
every observation gets its own copy of the parameters and of its view's pose, so two backward
passes (one per pixel coordinate) give the whole ``(M, 2, n)`` Jacobian, whatever ``n``
(observations are independent given the parameters). Free variables, constraints and the
normalised polynomial radius are described in :mod:`omniscape_torch.calibration.params`, the
damping in :mod:`omniscape_torch.calibration.lm`.

Initialisation: OCamCalib's linear solution for ``scaramuzza``
(:func:`omniscape_torch.calibration.linear.scaramuzza_linear`); for the other models the focal
length from the field of view (a ray at ``fov / 2`` lands on the inscribed image circle) with
the model's undistorted defaults, then each view's pose from a planar homography on the
unprojected rays (:func:`omniscape_torch.calibration.linear.planar_pose`).

Every method ends with the same checks, so that a failure is reported as one: the result is
``converged`` only when the method's own test passed, no observation projects outside the
model's domain, a Gauss-Newton step would lower the cost by less than ``optimality_tol``
(relative: the point is a minimum, whatever method reached it; or by less than ``COST_FLOOR``
per observation, residuals at rounding level), the parameters are determined by
the data (scaled condition number of ``J^T J`` below ``max_condition``, and no free intrinsic
with a standard deviation above ``max_std`` in free units) and the parameters are inside the
model's range.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from typing import Sequence

import torch
from torch import Tensor

from ..cameras import Camera, CameraModel, get_model
from ..cameras.camera import _check_image_size
from .linear import planar_pose, scaramuzza_linear
from .lm import (check_loss, gauss_newton_gain, levenberg_marquardt, normal_equations,
                 robust_cost, scaled_condition)
from .params import IntrinsicsMap, frozen_indices, transform

#: Optimisation methods of :func:`fit`.
METHODS = ("lm", "lbfgs", "adam", "linear")

#: Parameters held by default: OCamCalib's ``a1 = 0`` (``f'(0) = 0``).
DEFAULT_FREEZE = {"scaramuzza": ("a1", "e")}

#: Undistorted starting values of the models' non-focal parameters (unified xi = 1 and its
#: equivalents: a parabolic mirror, the middle of the fisheye range).
DEFAULT_DISTORTION = {"kannala_brandt": (0.0, 0.0, 0.0, 0.0), "unified": (1.0, 0.0, 0.0, 0.0, 0.0),
                      "eucm": (0.5, 1.0), "double_sphere": (0.0, 0.5)}

#: Cost per observation (pixels squared) below which residuals are at rounding level: relative
#: convergence tests are then skipped (exact data, as in a conversion between nested models).
COST_FLOOR = 0.5e-18

#: Default full field of view of :func:`default_intrinsics`, radians.
DEFAULT_FOV = {"pinhole": math.radians(90)}


@dataclass
class FitResult:
    """Outcome of :func:`fit` (also of a model conversion's fit).

    Attributes:
        camera: the fitted ``ot.Camera`` (None only when the parameters left the model's range,
            then ``converged`` is False).
        params: ``(P,)`` fitted parameters (natural, float64).
        param_names: their names.
        free_names: the names of the fitted (not frozen) parameters.
        poses: ``(V, 6)`` per view: axis-angle (radians) and translation (target units),
            ``X_cam = R X + t``; ``(0, 6)`` for a conversion.
        rms: RMS reprojection error, the root of the mean squared pixel distance over the ``M``
            observations (the one RMS of this package: conversions and model selection report
            the same), so that Gaussian noise of ``sigma`` per coordinate gives
            ``sigma sqrt(2) sqrt((2 M - n) / (2 M))`` at the optimum with ``n`` free variables.
        converged: all checks passed (module docstring); when False, ``reason`` says which not.
        reason: why the run stopped or which check failed.
        iterations: iterations of the method.
        method: the method.
        covariance: ``(P, P)`` covariance of ``params``, ``sigma^2 (J^T J)^-1`` with
            ``sigma^2 = sum r^2 / (2 M - n)``, mapped to the natural parameters by the Jacobian
            of the reparametrisation (delta method); zero rows for frozen parameters.
        std: ``(P,)`` square root of its diagonal.
        residuals: per view ``(N_i, 2)`` projected minus observed pixels.
        num_invalid: observations projecting outside the model's domain.
        gauss_newton_gain: cost reduction a Gauss-Newton step would still give, relative to
            the cost.
        condition: scaled condition number of ``J^T J``.
        num_observations: ``M`` (points over all views).
        num_free: ``n``: free intrinsics plus 6 per view.
        cost: final robust cost (pixels squared).
        history: per iteration ``{"iteration", "cost", ...}`` (L-BFGS: per cost evaluation,
            ``{"evaluation", "cost"}``, several per iteration with its line search).
    """

    camera: Camera | None
    params: Tensor
    param_names: tuple[str, ...]
    free_names: tuple[str, ...]
    poses: Tensor
    rms: float
    converged: bool
    reason: str
    iterations: int
    method: str
    covariance: Tensor
    std: Tensor
    residuals: list[Tensor]
    num_invalid: int
    gauss_newton_gain: float
    condition: float
    num_observations: int
    num_free: int
    cost: float
    history: list[dict] = field(default_factory=list, repr=False)

    def to_dict(self) -> dict:
        """A JSON-ready report (no residuals or history)."""
        return {
            "converged": self.converged, "reason": self.reason, "method": self.method,
            "iterations": self.iterations, "rms_px": self.rms, "cost": self.cost,
            "num_observations": self.num_observations, "num_free": self.num_free,
            "num_invalid": self.num_invalid, "gauss_newton_gain": self.gauss_newton_gain,
            "condition": self.condition,
            "params": dict(zip(self.param_names, self.params.tolist())),
            "std": dict(zip(self.param_names, self.std.tolist())),
            "free": list(self.free_names), "poses": self.poses.tolist(),
        }


# --------------------------------------------------------------------------------------------
# Input checks
# --------------------------------------------------------------------------------------------

def _as_float64(value, name: str) -> Tensor:
    if isinstance(value, Tensor):
        if not (value.is_floating_point() or value.dtype in (torch.int32, torch.int64)):
            raise TypeError(f"{name}: expected a real tensor, got {value.dtype}")
        return value.detach().to(torch.float64)
    try:
        return torch.as_tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"{name}: expected a tensor, an array or a sequence of numbers, got "
                        f"{type(value).__name__}") from None


def _per_view(value, name: str, dim: int) -> list[Tensor]:
    """``(V, N, dim)`` or a sequence of ``(N_i, dim)`` -> a list of float64 tensors."""
    if isinstance(value, (list, tuple)):
        views = [_as_float64(v, f"{name}[{i}]") for i, v in enumerate(value)]
    else:
        t = _as_float64(value, name)
        if t.dim() != 3:
            raise ValueError(f"{name}: expected shape (V, N, {dim}) or a list of (N, {dim}), got "
                             f"{tuple(t.shape)}")
        views = list(t.unbind(0))
    if not views:
        raise ValueError(f"{name}: expected at least one view, got none")
    for i, v in enumerate(views):
        if v.dim() != 2 or v.shape[-1] != dim:
            raise ValueError(f"{name}[{i}]: expected shape (N, {dim}), got {tuple(v.shape)}")
        bad = ~torch.isfinite(v).all(-1)
        if bool(bad.any()):
            raise ValueError(f"{name}[{i}]: values must be finite; point "
                             f"{int(bad.nonzero()[0])} is {v[bad][0].tolist()}")
    return views


def prepare_views(object_points, image_points) -> tuple[list[Tensor], list[Tensor]]:
    """Checked per-view ``(N_i, 3)`` target points and ``(N_i, 2)`` pixels, float64.

    ``object_points`` may be one ``(N, 3)`` target seen in every view, ``(V, N, 3)`` or a list of
    ``(N_i, 3)``; ``image_points`` ``(V, N, 2)`` or a list of ``(N_i, 2)``.
    """
    pixels = _per_view(image_points, "image_points", 2)
    shared = not isinstance(object_points, (list, tuple)) and _as_float64(
        object_points, "object_points").dim() == 2
    points = ([_as_float64(object_points, "object_points")] * len(pixels) if shared
              else _per_view(object_points, "object_points", 3))
    if shared:
        _per_view([points[0]], "object_points", 3)
    if len(points) != len(pixels):
        raise ValueError(f"object_points and image_points: {len(points)} views of target points "
                         f"but {len(pixels)} views of pixels")
    for i, (p, q) in enumerate(zip(points, pixels)):
        if p.shape[0] != q.shape[0]:
            raise ValueError(f"view {i}: {p.shape[0]} target points but {q.shape[0]} pixels")
        if p.shape[0] < 4:
            raise ValueError(f"view {i}: a view needs at least 4 points to fix its pose, got "
                             f"{p.shape[0]}")
    return points, pixels


# --------------------------------------------------------------------------------------------
# The least-squares problem
# --------------------------------------------------------------------------------------------

class Problem:
    """Residuals ``project(R_v X + t_v, params) - pixels`` and their Jacobian in free variables.

    With no views (``poses0`` of shape ``(0, 6)``) the points are already in the camera frame
    (a model conversion fits rays to pixels); with ``rotation_only`` the views' translations
    stay at ``poses0``'s (a conversion that fits the rotation between two camera frames).
    ``weights`` ``(M,)`` scale each observation's squared residual (its residual by their
    square root).

    Args:
        intrinsics: the :class:`IntrinsicsMap` of the model.
        points: ``(M, 3)`` target points of every observation.
        pixels: ``(M, 2)`` observed pixels.
        view: ``(M,)`` view index of each observation.
        poses0: ``(V, 6)`` initial poses.
        rotation_only: free rotations, held translations.
        weights: ``(M,)`` positive weights (None: all 1).
    """

    def __init__(self, intrinsics: IntrinsicsMap, points: Tensor, pixels: Tensor, view: Tensor,
                 poses0: Tensor, *, rotation_only: bool = False,
                 weights: Tensor | None = None) -> None:
        self.intrinsics = intrinsics
        self.model = intrinsics.model
        self.points, self.pixels, self.view = points, pixels, view
        self.scale = None if weights is None else weights.sqrt()[:, None]
        self.poses0 = poses0.detach().clone()
        self.num_views = poses0.shape[0]
        self.pose_dofs = 3 if rotation_only else 6
        self.pose_scale = float(poses0[:, 3:].norm(dim=-1).mean()) if self.num_views else 1.0
        self.num_intrinsics = len(intrinsics.free)
        self.num_free = self.num_intrinsics + self.pose_dofs * self.num_views

    def z0(self) -> Tensor:
        return torch.cat((self.intrinsics.z0(),
                          torch.zeros(self.pose_dofs * self.num_views, dtype=torch.float64)))

    def poses(self, z: Tensor) -> Tensor:
        dz = z[self.num_intrinsics:].reshape(self.num_views, self.pose_dofs)
        dz = torch.cat((dz, dz.new_zeros(self.num_views, 6 - self.pose_dofs)), -1)
        return self.poses0 + dz * torch.tensor([1.0] * 3 + [self.pose_scale] * 3,
                                               dtype=z.dtype)

    def _weighted(self, residuals: Tensor) -> Tensor:
        return residuals if self.scale is None else residuals * self.scale

    def project(self, params: Tensor, poses: Tensor | None) -> tuple[Tensor, Tensor]:
        """``(M, 2)`` pixels and ``(M,)`` model validity; ``params`` ``(P,)`` or ``(M, P)``,
        ``poses`` per observation ``(M, 6)`` (None without views)."""
        points = self.points if poses is None else transform(poses, self.points)
        return self.model.project(points, params)

    def residuals(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """``(M, 2)`` residuals (differentiable in ``z``) and ``(M,)`` validity."""
        poses = self.poses(z)[self.view] if self.num_views else None
        pixels, valid = self.project(self.intrinsics.natural(z[:self.num_intrinsics]), poses)
        return self._weighted(pixels - self.pixels), valid

    def evaluate(self, z: Tensor, jacobian: bool) -> tuple[Tensor, Tensor | None]:
        """Residuals ``(M, 2)`` and, if asked, the Jacobian ``(M, 2, n)`` (module docstring)."""
        if not jacobian:
            with torch.no_grad():
                return self.residuals(z)[0], None
        m = self.points.shape[0]
        zi = z[:self.num_intrinsics]
        params = self.intrinsics.natural(zi).detach()
        p_obs = params.expand(m, -1).clone().requires_grad_(True)
        leaves, pose_obs = [p_obs], None
        if self.num_views:
            pose_obs = self.poses(z).detach()[self.view].clone().requires_grad_(True)
            leaves.append(pose_obs)
        res = self._weighted(self.project(p_obs, pose_obs)[0] - self.pixels)
        grads = [torch.autograd.grad(res[:, k].sum(), leaves, retain_graph=k == 0)
                 for k in range(2)]
        jac = torch.zeros(m, 2, self.num_free, dtype=torch.float64)
        d_natural = self.intrinsics.jacobian(zi)  # [P, n_i]
        jac[:, :, :self.num_intrinsics] = torch.stack([g[0] for g in grads], 1) @ d_natural
        if self.num_views:
            k = self.pose_dofs
            d_pose = torch.stack([g[1] for g in grads], 1)[..., :k]  # [M, 2, k]
            d_pose = d_pose * torch.tensor([1.0] * 3 + [self.pose_scale] * 3,
                                           dtype=z.dtype)[:k]
            cols = self.num_intrinsics + k * self.view[:, None] + torch.arange(k)  # [M, k]
            rows = torch.arange(m)[:, None].expand(m, k)
            for k in range(2):
                jac[:, k][rows, cols] = d_pose[:, k]
        return res.detach(), jac


# --------------------------------------------------------------------------------------------
# Gradient methods
# --------------------------------------------------------------------------------------------

def _bar(total: int, progress: bool | None, desc: str):
    from tqdm import tqdm
    return tqdm(total=total, disable=not (sys.stderr.isatty() if progress is None else progress),
                desc=desc, file=sys.stderr)


def _lbfgs(problem: Problem, z0: Tensor, loss: str, scale: float, max_iterations: int,
           progress) -> tuple[Tensor, bool, str, int, list[dict]]:
    """L-BFGS with a strong-Wolfe line search; converged when it stops on its tolerances."""
    z = z0.clone().requires_grad_(True)
    opt = torch.optim.LBFGS([z], lr=1.0, max_iter=max_iterations, max_eval=3 * max_iterations,
                            tolerance_grad=1e-12,
                            tolerance_change=1e-12, history_size=20,
                            line_search_fn="strong_wolfe")
    history: list[dict] = []
    bar = _bar(max_iterations, progress, "L-BFGS")

    def closure():
        opt.zero_grad()
        cost, _ = robust_cost(problem.residuals(z)[0], loss, scale)
        cost.backward()
        history.append({"evaluation": len(history) + 1, "cost": float(cost.detach())})
        bar.update(1)
        return cost

    try:
        opt.step(closure)
    finally:
        bar.close()
    state = opt.state[opt._params[0]]
    n_iter = state["n_iter"]
    ok = (n_iter < max_iterations and state["func_evals"] < 3 * max_iterations
          and math.isfinite(history[-1]["cost"]))
    reason = ("stopped on its tolerances" if ok else
              f"{max_iterations} iterations without converging")
    return z.detach(), ok, reason, n_iter, history


def _adam(problem: Problem, z0: Tensor, loss: str, scale: float, max_iterations: int,
          progress, lr: float = 1e-2, patience: int = 50, min_lr: float = 1e-6
          ) -> tuple[Tensor, bool, str, int, list[dict]]:
    """Adam; the learning rate halves after ``patience`` iterations without a new best cost and
    the run ends (as converged) once it falls below ``min_lr``."""
    z = z0.clone().requires_grad_(True)
    opt = torch.optim.Adam([z], lr=lr)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.5, patience=patience,
                                                       threshold=1e-9)
    history: list[dict] = []
    best, best_z = math.inf, z.detach().clone()
    with _bar(max_iterations, progress, "Adam") as bar:
        for iteration in range(1, max_iterations + 1):
            opt.zero_grad()
            cost, _ = robust_cost(problem.residuals(z)[0], loss, scale)
            cost.backward()
            value = float(cost.detach())
            if value < best:
                best, best_z = value, z.detach().clone()
            history.append({"iteration": iteration, "cost": value,
                            "lr": opt.param_groups[0]["lr"]})
            opt.step()
            sched.step(value)
            bar.update(1)
            if opt.param_groups[0]["lr"] < min_lr:
                return best_z, True, "learning rate decayed below min_lr", iteration, history
    return best_z, False, f"{max_iterations} iterations without converging", max_iterations, \
        history


# --------------------------------------------------------------------------------------------
# fit
# --------------------------------------------------------------------------------------------

def default_intrinsics(model: str | CameraModel, image_size: tuple[int, int],
                       fov: float | None = None) -> Tensor:
    """Starting intrinsics from the field of view: centre at the image centre, undistorted
    defaults (``DEFAULT_DISTORTION``), focal such that a ray at ``fov / 2`` from the axis lands
    on the inscribed image circle.

    Args:
        model: any model but ``scaramuzza`` (whose start is the linear solution).
        image_size: ``(H, W)``.
        fov: full field of view, radians (default: ``DEFAULT_FOV``, else pi).

    Returns:
        ``(P,)`` float64 parameters.
    """
    model = get_model(model)
    if model.name == "scaramuzza":
        raise ValueError("model: the scaramuzza model starts from its linear solution "
                         "(scaramuzza_linear), not from a field of view")
    h, w = _check_image_size(image_size)
    fov = DEFAULT_FOV.get(model.name, math.pi) if fov is None else fov
    if not (isinstance(fov, (int, float)) and 0 < fov <= 2 * math.pi):
        raise ValueError(f"fov: expected a full angle in (0, 2 pi] radians, got {fov!r}")
    unit = torch.tensor([1.0, 1.0, 0.0, 0.0, *DEFAULT_DISTORTION.get(model.name, ())],
                        dtype=torch.float64)
    theta = min(0.5 * fov, 0.999 * float(model.max_angle(unit)))
    ray = torch.tensor([math.sin(theta), 0.0, math.cos(theta)], dtype=torch.float64)
    radius = float(model.project(ray, unit)[0][0])
    focal = 0.5 * min(h, w) / radius
    return torch.cat((torch.tensor([focal, focal, (w - 1) / 2, (h - 1) / 2],
                                   dtype=torch.float64), unit[4:]))


def _initial_poses(model: CameraModel, params: Tensor, points: list[Tensor],
                   pixels: list[Tensor]) -> Tensor:
    poses = []
    for i, (pts, pix) in enumerate(zip(points, pixels)):
        rays, valid = model.unproject(pix, params)
        if int(valid.sum()) < 4:
            raise ValueError(f"view {i}: fewer than 4 pixels are inside the initial camera's "
                             f"domain; pass init (or fov) closer to the camera")
        poses.append(planar_pose(pts[valid], rays[valid]))
    return torch.stack(poses)


def _check_choice(value, name: str, choices) -> None:
    if value not in choices:
        raise ValueError(f"{name}: expected one of {', '.join(map(str, choices))}, got {value!r}")


def fit(object_points, image_points, model: str | CameraModel, image_size: tuple[int, int], *,
        method: str = "lm", degree: int = 4, init=None, poses=None, fov: float | None = None,
        freeze: Sequence[str] | None = None, loss: str = "linear", loss_scale: float = 1.0,
        max_iterations: int | None = None, optimality_tol: float = 1e-6,
        max_condition: float = 1e12, max_std: float = 1.0,
        progress: bool | None = False) -> FitResult:
    """Fit the intrinsics of ``model`` and the pose of every view to correspondences.

    Args:
        object_points: target points: one ``(N, 3)`` target seen in every view, ``(V, N, 3)``,
            or a list of ``(N_i, 3)`` (metres or any unit; poses come out in it).
        image_points: ``(V, N, 2)`` or a list of ``(N_i, 2)`` pixels (u, v), pixel centres at
            integers.
        model: a model name of ``ot.cameras.MODELS`` (not ``equirectangular``) or a model.
        image_size: ``(H, W)``.
        method: ``"lm"`` (Levenberg-Marquardt), ``"lbfgs"``, ``"adam"``, or ``"linear"``
            (``scaramuzza`` only: OCamCalib's linear solution, not refined).
        degree: ``scaramuzza`` polynomial degree N (a0, ..., aN) when ``init`` is None.
        init: starting intrinsics ``(P,)`` or a ``Camera`` (default: module docstring).
        poses: starting poses ``(V, 6)`` (default: from ``init``, by planar homography).
        fov: full field of view in radians for the default start of non-polynomial models.
        freeze: parameter groups (``focal``, ``center``, ``distortion``, ``affine``) or names
            held at their start (default ``DEFAULT_FREEZE``: a1 of ``scaramuzza``).
        loss: ``"linear"``, ``"huber"`` or ``"cauchy"`` (``omniscape_torch.calibration.lm``).
        loss_scale: where the robust loss departs from the square, pixels.
        max_iterations: iterations of the method (default 100 LM, 500 L-BFGS, 3000 Adam).
        optimality_tol: largest relative cost reduction a Gauss-Newton step may still promise
            at a converged result.
        max_condition: largest scaled condition number of ``J^T J`` at a converged result.
        max_std: largest standard deviation of a free intrinsic in free units (module
            ``params``: a unit step moves the image by about its size) at a converged result.
        progress: show a tqdm bar (``None``: when stderr is a terminal).

    Returns:
        A :class:`FitResult`; check ``converged``.

    Raises:
        ValueError, TypeError: bad input (shapes, NaN, fewer observations than free
        parameters, unknown names), naming the argument.
    """
    model = get_model(model)
    if model.name == "equirectangular":
        raise ValueError("model: equirectangular is a panorama projection, not a lens to "
                         "calibrate")
    _check_choice(method, "method", METHODS)
    check_loss(loss, loss_scale)
    image_size = _check_image_size(image_size)
    points, pixels = prepare_views(object_points, image_points)
    if method == "linear" and model.name != "scaramuzza":
        raise ValueError(f"method: 'linear' is OCamCalib's solution for the scaramuzza model, "
                         f"not {model.name}")
    if isinstance(degree, bool) or not isinstance(degree, int) or degree < 1:
        raise ValueError(f"degree: expected an integer >= 1, got {degree!r}")
    if max_iterations is not None and (isinstance(max_iterations, bool) or not isinstance(
            max_iterations, int) or max_iterations < 1):
        raise ValueError(f"max_iterations: expected a positive integer, got {max_iterations!r}")

    start_poses = None
    if init is None and model.name == "scaramuzza":
        params0, start_poses = scaramuzza_linear(points, pixels, image_size, degree)
    elif init is None:
        params0 = default_intrinsics(model, image_size, fov)
    else:
        params0 = (init.params if isinstance(init, Camera) else _as_float64(init, "init"))
        params0 = params0.detach().to(torch.float64).reshape(-1)
        try:
            model.validate_params(params0, "init")
        except ValueError as err:
            raise ValueError(f"init: {err}") from None
    if poses is not None:
        start_poses = _as_float64(poses, "poses")
        if start_poses.shape != (len(points), 6):
            raise ValueError(f"poses: expected shape ({len(points)}, 6), got "
                             f"{tuple(start_poses.shape)}")
    elif start_poses is None:
        start_poses = _initial_poses(model, params0, points, pixels)

    names = model.names_for(params0.shape[-1])
    frozen = frozen_indices(model, names, DEFAULT_FREEZE.get(model.name, ()) if freeze is None
                            else freeze)
    intrinsics = IntrinsicsMap(model, params0, image_size, frozen)
    view = torch.cat([torch.full((len(p),), i) for i, p in enumerate(points)])
    problem = Problem(intrinsics, torch.cat(points), torch.cat(pixels), view, start_poses)
    m = problem.points.shape[0]
    if 2 * m <= problem.num_free:
        raise ValueError(f"object_points: {m} points give {2 * m} residuals, not more than the "
                         f"{problem.num_free} free parameters ({len(intrinsics.free)} "
                         f"intrinsics + 6 per view)")
    return solve(problem, method, loss=loss, loss_scale=loss_scale,
                 max_iterations=max_iterations, optimality_tol=optimality_tol,
                 max_condition=max_condition, max_std=max_std, progress=progress,
                 sizes=[len(p) for p in points], image_size=image_size)


def solve(problem: Problem, method: str, *, loss: str, loss_scale: float,
          max_iterations: int | None, optimality_tol: float, max_condition: float,
          max_std: float, progress, sizes: list[int], image_size: tuple[int, int]
          ) -> FitResult:
    """Run ``method`` on ``problem`` from its start and check the result (module docstring)."""
    z0 = problem.z0()
    if method == "linear":
        z, ok, reason, iterations, history = z0, True, "closed-form linear solution (not " \
            "refined; not a least-squares minimum)", 0, []
    elif method == "lm":
        state = levenberg_marquardt(problem.evaluate, z0, loss=loss, loss_scale=loss_scale,
                                    max_iterations=max_iterations or 100, progress=progress,
                                    cost_floor=COST_FLOOR * problem.points.shape[0])
        z, ok, reason, iterations, history = (state.z, state.converged, state.reason,
                                              state.iterations, state.history)
    else:
        run = _lbfgs if method == "lbfgs" else _adam
        z, ok, reason, iterations, history = run(
            problem, z0, loss, loss_scale,
            max_iterations or (500 if method == "lbfgs" else 3000), progress)

    residuals, jac = problem.evaluate(z, True)
    _, valid = problem.residuals(z)
    a, g, cost = normal_equations(residuals, jac, loss, loss_scale)
    cost = float(cost)
    num_invalid = int((~valid).sum())
    params = problem.intrinsics.natural(z[:problem.num_intrinsics]).detach()
    poses = problem.poses(z).detach()
    finite = bool(torch.isfinite(a).all()) and math.isfinite(cost)
    gain = gauss_newton_gain(a, g) if finite else math.inf
    at_minimum = gain <= optimality_tol * cost or gain <= COST_FLOOR * problem.points.shape[0]
    gain = gain / cost if cost > 0 else gain
    condition = scaled_condition(a) if finite else math.inf

    m, n = residuals.shape[0], problem.num_free
    sigma2 = _weighted_square(residuals, loss, loss_scale) / (2 * m - n)
    covariance, std_free = _covariance(a, sigma2, problem, z, condition, max_condition)

    camera, failures = None, [] if ok else [reason]
    try:
        camera = Camera(problem.model, params, image_size)
    except ValueError as err:
        failures.append(f"the parameters left the model's range: {err}")
    if num_invalid:
        failures.append(f"{num_invalid} of {m} observations project outside the model's domain")
    if method != "linear" and not at_minimum:
        failures.append(f"not at a minimum: a Gauss-Newton step would lower the cost by "
                        f"{gain:.2e} (relative), above optimality_tol {optimality_tol:g}")
    if not condition <= max_condition:
        failures.append(f"degenerate data: the scaled condition number of J^T J is "
                        f"{condition:.3g}, above max_condition {max_condition:g}; some "
                        f"parameters are not determined by these views")
    else:
        loose = [f"{name} (+- {float(covariance[i, i]) ** 0.5:.3g})" for name, i, sd in zip(
            problem.intrinsics.free_names, problem.intrinsics.free, std_free) if sd > max_std]
        if loose:
            failures.append(f"near-degenerate data: {', '.join(loose)} not determined by these "
                            f"views (standard deviation above max_std {max_std:g} in free "
                            f"units)")
    ok, reason = (True, reason) if not failures else (False, "; ".join(failures))
    return FitResult(
        camera=camera, params=params, param_names=problem.intrinsics.names,
        free_names=problem.intrinsics.free_names, poses=poses,
        rms=float(torch.sqrt((residuals * residuals).sum(-1).mean())), converged=ok,
        reason=reason,
        iterations=iterations, method=method, covariance=covariance,
        std=torch.sqrt(torch.diagonal(covariance).clamp(min=0)),
        residuals=list(residuals.split(sizes)) if problem.num_views else [residuals],
        num_invalid=num_invalid, gauss_newton_gain=gain, condition=condition,
        num_observations=m, num_free=n, cost=cost, history=history)


def _weighted_square(residuals: Tensor, loss: str, scale: float) -> float:
    _, weight = robust_cost(residuals, loss, scale)
    return float((weight * (residuals * residuals).sum(-1)).sum())


def _covariance(a: Tensor, sigma2: float, problem: Problem, z: Tensor, condition: float,
                max_condition: float) -> tuple[Tensor, Tensor]:
    """``(P, P)`` covariance of the natural intrinsics (inf on the diagonal when singular) and
    ``(n_free,)`` standard deviations of the free intrinsics in free units."""
    p = len(problem.intrinsics.names)
    k = problem.num_intrinsics
    d = problem.intrinsics.jacobian(z[:k])  # [P, k]
    if not condition <= 1e3 * max_condition:
        cov = torch.zeros(p, p, dtype=torch.float64)
        free = torch.tensor(problem.intrinsics.free, dtype=torch.long)
        cov[free, free] = math.inf
        return cov, torch.full((k,), math.inf, dtype=torch.float64)
    scale = torch.rsqrt(torch.diagonal(a))
    inv = torch.linalg.inv(a * scale[:, None] * scale[None]) * scale[:, None] * scale[None]
    cov_z = sigma2 * inv[:k, :k]
    return d @ cov_z @ d.T, torch.sqrt(torch.diagonal(cov_z).clamp(min=0))
