"""Calibration from correspondences: intrinsics and per-view poses by least squares.

Given target points ``X`` (checkerboard corners or any known points, in the target's frame)
and their detected pixels in several views, `fit` minimises the reprojection error

    sum_views sum_points rho(|project(R_v X + t_v, params) - pixels|^2 / scale^2)

over the intrinsics of one model and the pose ``(r_v, t_v)`` of every view, with the model's own
differentiable ``project`` as the residual function. Jacobians come from autograd in float64:
every observation gets its own copy of the parameters and of its view's pose, so two backward
passes (one per pixel coordinate) give the whole ``(M, 2, n)`` Jacobian, whatever ``n``
(observations are independent given the parameters). Free variables, constraints and the
normalised polynomial radius are described in `omniscape_torch.calibration.params`, the
damping in `omniscape_torch.calibration.lm`.

Initialisation (`omniscape_torch.calibration.starts`): OCamCalib's linear solution for
``scaramuzza``; for the other models several starts (the linear solution converted, and
undistorted defaults for several fields of view), ranked by a short Levenberg-Marquardt run;
the fit goes on from the best one (``FitResult.start`` names it). Where Levenberg-Marquardt
stops on its own test at a point the checks below reject, the next starts are finished in turn
(at most ``RETRY_STARTS``) and the first that passes is kept (where none does, one that fails
the near-degenerate check only, then the lowest cost). L-BFGS and Adam start from the
single default start (no least-squares run chooses it for them).

Iterations: by default Levenberg-Marquardt runs in rounds of ``LM_ROUND`` iterations and starts
another while the last round lowered the cost by more than ``LM_PROGRESS`` (relative) and the
data determine the parameters at its end (the condition and standard-deviation checks below),
up to ``LM_MAX_ITERATIONS``: a run crawling along a narrow valley (the unified model's ``xi``,
focal length and ``k1`` trade off) is not stopped while it still makes progress, and one on
degenerate views is not kept crawling. An explicit ``max_iterations`` is a hard limit.

Outliers (``reject_outliers=True``): a first fit with a robust loss (``loss``, Cauchy by
default), then rounds that mark as outliers the observations whose residual distance exceeds
what a Gaussian residual exceeds with the probability of an ``outlier_threshold``-sigma event
(``sigma``: 1.4826 times the median absolute deviation of the kept residuals' coordinates, a
robust estimate of the noise per coordinate) and refit the others with the plain squared loss,
until a round marks the same observations as the round before; ``FitResult.outliers`` lists
them per view. A clean observation is marked with the probability of that event (0.27% at
``k = 3``).

Methods: Levenberg-Marquardt is the method for correspondences (a small dense least-squares
problem whose Jacobian is at hand: it converges in tens of iterations where the scaled
condition number of ``J^T J`` reaches 1e7). L-BFGS and Adam are first-order methods, for losses
without a least-squares Jacobian (photometric fitting: `fit_photometric` uses Adam);
here they serve as a cross-check of the LM minimum on well-conditioned problems, and
``benchmarks/calibration_stability.py`` shows them not converging within their budgets on a
real lens: use them on points only to compare.

Every method ends with the same checks, so that a failure is reported as one: the result is
``converged`` only when the method's own test passed, no observation projects outside the
model's domain, a Gauss-Newton step would lower the cost by less than ``optimality_tol``
(relative: the point is a minimum, whatever method reached it; or by less than ``COST_FLOOR``
per observation, residuals at rounding level), the parameters are determined by
the data (scaled condition number of ``J^T J`` below ``max_condition``, and no free intrinsic
with a standard deviation above ``max_std`` in free units) and the parameters are inside the
model's range. ``FitResult.failed_checks`` names the checks that failed (``CHECKS``); where the
standard deviations are the only one (``FitResult.only_near_degenerate``), the result is a
least-squares minimum that the views leave a direction of, and ``FitResult.near_degenerate``
names each loose intrinsic with the one most correlated with it (``omniscape-torch fit``
writes such a fit with exit 3 and that line, or refuses it with ``--strict``).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from typing import Callable, Sequence

import torch
from torch import Tensor

from ..cameras import Camera, CameraModel, get_model
from ..cameras.camera import _check_image_size
from .linear import scaramuzza_linear
from .lm import (check_loss, gauss_newton_gain, levenberg_marquardt, normal_equations,
                 robust_cost, scaled_condition)
from .params import IntrinsicsMap, frozen_indices, transform
from .problem import COST_FLOOR, Problem, view_index
from .starts import default_fov, default_intrinsics, default_starts, initial_poses, rank_starts

#: Optimisation methods of `fit`.
METHODS = ("lm", "lbfgs", "adam", "linear")

#: Parameters held by default: OCamCalib's ``a1 = 0`` (``f'(0) = 0``); for ``opencv``, as
#: ``cv2.calibrateCamera`` without ``CALIB_RATIONAL_MODEL`` and ``CALIB_THIN_PRISM_MODEL``, the
#: rational denominator and the thin prism (with small coefficients k1..k3 and k4..k6 are
#: nearly redundant: a board's views leave J^T J singular to 1e13).
DEFAULT_FREEZE = {"scaramuzza": ("a1", "e"),
                  "opencv": ("k4", "k5", "k6", "s1", "s2", "s3", "s4")}

#: Where the fit from the best start fails a check, the next starts (in their order) finished
#: at most: along the unified model's xi-focal-k1 valley LM can stop where ``J^T J`` is nearly
#: singular (reported as near-degenerate) while another start reaches a determined minimum.
RETRY_STARTS = 2

#: Default Levenberg-Marquardt budget: rounds of ``LM_ROUND`` iterations, another while the last
#: lowered the cost by more than ``LM_PROGRESS`` relative, at most ``LM_MAX_ITERATIONS``.
LM_ROUND = 100
LM_PROGRESS = 1e-6
LM_MAX_ITERATIONS = 1000

#: The checks of every fit (module docstring), as named in ``FitResult.failed_checks``: the
#: method's own test, the parameters inside the model's range, every observation inside the
#: model's domain, at a minimum, the condition number, the standard deviations.
CHECKS = ("method", "range", "domain", "minimum", "degenerate", "near_degenerate")

#: Rounds of outlier rejection at most (each drops points, so few are ever needed).
MAX_REJECTION_ROUNDS = 10

#: Residual distance (pixels) below which no observation is an outlier: rounding, on exact data.
OUTLIER_FLOOR = 1e-6


@dataclass
class FitResult:
    """Outcome of `fit` (also of a model conversion's fit).

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
        covariance: ``(P, P)`` covariance of ``params``, the intrinsics' block of
            ``sigma^2 (J^T J)^-1`` over all ``n`` free variables (the poses marginalised) with
            ``sigma^2 = sum r^2 / (2 M - n)``, mapped to the natural parameters by the Jacobian
            of the reparametrisation (delta method); zero rows for frozen parameters.
        std: ``(P,)`` square root of its diagonal, in the order of ``param_names``
            (``std_by_name`` names them).
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
        outliers: per view, the ``int64`` indices (into that view's points) of the
            observations dropped as outliers (``reject_outliers``); empty tensors where none
            (or without rejection), ``[]`` for a conversion. Dropped observations count in no
            other field but ``residuals``.
        start: which start the fit went on from (``"init"``, ``"linear"``, ``"fov 180"``...).
        failed_checks: the names of the checks that failed (empty when ``converged``), of
            ``CHECKS``.
        near_degenerate: where the near-degenerate check failed, per free intrinsic whose
            standard deviation exceeds ``max_std``: ``(name, partner, correlation)``, the
            intrinsic most correlated with it and their correlation (from ``covariance``;
            ``partner`` None when no other intrinsic is free). A fit whose only failed check
            is this one is a least-squares minimum that these views leave a direction of
            (``omniscape-torch fit`` writes it and exits 3, as for poor coverage).

    With outliers dropped, ``residuals`` still holds every input observation (the dropped ones'
    residuals at the final parameters, to show them); ``rms``, ``cost``, ``num_observations`` and
    the covariance are the kept observations'.
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
    outliers: list[Tensor] = field(default_factory=list)
    start: str = "init"
    failed_checks: tuple[str, ...] = ()
    near_degenerate: list[tuple[str, str | None, float]] = field(default_factory=list)

    @property
    def params_by_name(self) -> dict[str, float]:
        """``{name: value}`` of the fitted parameters (``params``, named), e.g. ``["fx"]``."""
        return dict(zip(self.param_names, self.params.tolist()))

    @property
    def std_by_name(self) -> dict[str, float]:
        """``{name: standard deviation}`` (``std``, named; 0 for a frozen parameter), e.g.
        ``result.std_by_name["k1"]``."""
        return dict(zip(self.param_names, self.std.tolist()))

    @property
    def only_near_degenerate(self) -> bool:
        """The near-degenerate check is the only one that failed (see ``near_degenerate``)."""
        return self.failed_checks == ("near_degenerate",)

    def to_dict(self) -> dict:
        """A JSON-ready report (no residuals or history)."""
        return {
            "converged": self.converged, "reason": self.reason, "method": self.method,
            "iterations": self.iterations, "rms_px": self.rms, "cost": self.cost,
            "num_observations": self.num_observations, "num_free": self.num_free,
            "num_invalid": self.num_invalid, "gauss_newton_gain": self.gauss_newton_gain,
            "condition": self.condition,
            "params": self.params_by_name, "std": self.std_by_name,
            "free": list(self.free_names), "poses": self.poses.tolist(),
            "start": self.start, "outliers": [o.tolist() for o in self.outliers],
            "failed_checks": list(self.failed_checks),
            "near_degenerate": [{"name": n, "partner": p, "correlation": c}
                                for n, p, c in self.near_degenerate],
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
    return (best_z, False, f"{max_iterations} iterations without converging", max_iterations,
            history)


# --------------------------------------------------------------------------------------------
# fit
# --------------------------------------------------------------------------------------------

def _check_choice(value, name: str, choices) -> None:
    if value not in choices:
        raise ValueError(f"{name}: expected one of {', '.join(map(str, choices))}, got {value!r}")


def fit(object_points, image_points, model: str | CameraModel, image_size: tuple[int, int], *,
        method: str = "lm", degree: int = 4, init=None, poses=None, fov: float | None = None,
        freeze: Sequence[str] | None = None, loss: str = "linear", loss_scale: float = 1.0,
        reject_outliers: bool = False, outlier_threshold: float = 3.0,
        max_iterations: int | None = None, optimality_tol: float = 1e-6,
        max_condition: float = 1e12, max_std: float = 1.0,
        progress: bool | None = False) -> FitResult:
    """Fit the intrinsics of ``model`` and the pose of every view to correspondences.

    Use ``method="lm"`` (the default) on correspondences: L-BFGS and Adam are first-order
    methods for losses without a least-squares Jacobian (photometric fitting); on points they
    serve to cross-check LM's minimum and do not converge on ill-conditioned lenses within their
    budgets (module docstring).

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
        init: starting intrinsics ``(P,)`` or a ``Camera`` (default: several starts, the best
            kept; module docstring).
        poses: starting poses ``(V, 6)`` (default: from the start, by planar homography).
        fov: full field of view in radians: one more start for non-polynomial models (the
            only one for L-BFGS and Adam).
        freeze: parameter groups (``focal``, ``center``, ``distortion``, ``affine``) or names
            held at their start (default ``DEFAULT_FREEZE``: a1 and e of ``scaramuzza``,
            k4..k6 and s1..s4 of ``opencv``).
        loss: ``"linear"``, ``"huber"`` or ``"cauchy"`` (``omniscape_torch.calibration.lm``);
            with ``reject_outliers``, the loss of the first fit (``"linear"`` means Cauchy
            there), the refits being plain least squares.
        loss_scale: where the robust loss departs from the square, pixels.
        reject_outliers: fit with a robust loss, drop the observations beyond
            ``outlier_threshold`` and refit with the plain loss until none is dropped
            (``FitResult.outliers`` lists them). Off by default: it discards data, which
            should be a choice; with clean data it drops about 0.3% of the points (at the
            default threshold) for nothing.
        outlier_threshold: ``k``: an observation is an outlier when its residual distance
            exceeds ``sigma sqrt(-2 ln p)``, ``p = erfc(k / sqrt 2)``, the distance a Gaussian
            residual of ``sigma`` per coordinate exceeds with the probability of a ``k``-sigma
            deviation of one coordinate (``k = 3``: 3.44 sigma, 0.27%); ``sigma = 1.4826 MAD``
            of the kept residuals' coordinates. At least 4 points of each view are kept.
        max_iterations: iterations of the method, a hard limit (default LM: rounds of
            ``LM_ROUND`` while the cost still falls by more than ``LM_PROGRESS``, at most
            ``LM_MAX_ITERATIONS``; 500 L-BFGS, 3000 Adam).
        optimality_tol: largest relative cost reduction a Gauss-Newton step may still promise
            at a converged result.
        max_condition: largest scaled condition number of ``J^T J`` at a converged result.
        max_std: largest standard deviation of a free intrinsic in free units (module
            ``params``: a unit step moves the image by about its size) at a converged result.
        progress: show a tqdm bar (``None``: when stderr is a terminal).

    Returns:
        A `FitResult`; check ``converged``.

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
    if not isinstance(reject_outliers, bool):
        raise TypeError(f"reject_outliers: expected True or False, got {reject_outliers!r}")
    if (isinstance(outlier_threshold, bool) or not isinstance(outlier_threshold, (int, float))
            or not (math.isfinite(outlier_threshold) and outlier_threshold > 0)):
        raise ValueError(f"outlier_threshold: expected a positive number of sigmas, got "
                         f"{outlier_threshold!r}")
    if reject_outliers and method == "linear":
        raise ValueError("reject_outliers: the linear method fits nothing to reject from; use "
                         "method='lm'")

    start_poses = None
    if init is None and model.name == "scaramuzza":
        params0, start_poses = scaramuzza_linear(points, pixels, image_size, degree)
        starts = [("linear", params0)]
    elif init is None:
        starts = [(f"fov {math.degrees(fov if fov is not None else default_fov(model)):g}",
                   default_intrinsics(model, image_size, fov))]
    else:
        params0 = (init.params if isinstance(init, Camera) else _as_float64(init, "init"))
        params0 = params0.detach().to(torch.float64).reshape(-1)
        try:
            model.validate_params(params0, "init")
        except ValueError as err:
            raise ValueError(f"init: {err}") from None
        starts = [("init", params0)]
    if poses is not None:
        start_poses = _as_float64(poses, "poses")
        if start_poses.shape != (len(points), 6):
            raise ValueError(f"poses: expected shape ({len(points)}, 6), got "
                             f"{tuple(start_poses.shape)}")

    names = model.names_for(starts[0][1].shape[-1])
    frozen = frozen_indices(model, names, DEFAULT_FREEZE.get(model.name, ()) if freeze is None
                            else freeze)
    m = sum(len(p) for p in points)
    num_free = len(names) - len(frozen) + 6 * len(points)
    if 2 * m <= num_free:
        raise ValueError(f"object_points: {m} points give {2 * m} residuals, not more than the "
                         f"{num_free} free parameters ({len(names) - len(frozen)} "
                         f"intrinsics + 6 per view)")
    first_loss = "cauchy" if reject_outliers and loss == "linear" else loss
    if method == "lm" and init is None and model.name != "scaramuzza":
        starts = default_starts(model, image_size, fov, points, pixels, frozen)
        ranked = rank_starts(model, starts, image_size, frozen, points, pixels, start_poses,
                              first_loss, loss_scale)[:1 + RETRY_STARTS]
    else:
        label, params0 = starts[0]
        ranked = [(label, params0, start_poses if start_poses is not None
                   else initial_poses(model, params0, points, pixels))]

    view = view_index(points)
    settings = dict(max_iterations=max_iterations, optimality_tol=optimality_tol,
                    max_condition=max_condition, max_std=max_std, progress=progress,
                    image_size=image_size)
    result = None
    for label, params0, start_poses in ranked:
        problem = Problem(IntrinsicsMap(model, params0, image_size, frozen), torch.cat(points),
                          torch.cat(pixels), view, start_poses)
        candidate, stopped_at_minimum = _solve(problem, method, loss=first_loss,
                                               loss_scale=loss_scale,
                                               sizes=[len(p) for p in points], **settings)
        candidate.start = label
        if result is None or _rank(candidate) > _rank(result):
            result = candidate
        # another start only after a stop at a point the checks reject; where LM ran out of
        # budget or of determined parameters, other starts fare no better
        if result.converged or not stopped_at_minimum:
            break
    if reject_outliers:
        result = _reject_outliers(result, model, frozen, points, pixels, outlier_threshold,
                                  method, loss_scale, settings)
    return result


def _rank(result: FitResult) -> tuple[bool, bool, float]:
    """Which of two fits of the same data `fit` keeps: a converged one, else one whose
    only failed check is the near-degenerate one (a minimum, written by ``omniscape-torch
    fit`` with exit 3), else the lower cost."""
    return result.converged, result.only_near_degenerate, -result.cost


def _outlier_distance(residuals: Tensor, threshold: float) -> float:
    """The residual distance beyond which an observation is an outlier (``fit``'s
    ``outlier_threshold``), from the residuals ``(M, 2)`` of the kept observations."""
    coords = residuals.reshape(-1)
    sigma = 1.4826 * float((coords - coords.median()).abs().median())
    tail = math.erfc(threshold / math.sqrt(2))
    # residuals at rounding level are never outliers (exact data)
    return max(sigma * math.sqrt(-2 * math.log(tail)), OUTLIER_FLOOR)


def _reject_outliers(result: FitResult, model: CameraModel, frozen: list[int],
                     points: list[Tensor], pixels: list[Tensor], threshold: float,
                     method: str, loss_scale: float, settings: dict) -> FitResult:
    """Rounds of: the outliers among all observations at the current solution (the threshold
    from the residuals of the observations kept so far), a refit of the others with the plain
    loss from the current solution; until a round finds the outliers of the round before.

    The set is found anew each round rather than grown, so that a point dropped while the
    solution was still pulled by the gross errors comes back, and the inliers are not eroded
    a tail at a time."""
    view = view_index(points)
    all_points, all_pixels = torch.cat(points), torch.cat(pixels)
    keep = torch.ones(len(view), dtype=torch.bool)
    previous = None
    iterations, history = result.iterations, [dict(h, round=0) for h in result.history]
    for round_ in range(1, MAX_REJECTION_ROUNDS + 1):
        residuals = _all_residuals(result, model, all_points, all_pixels, view)
        distance = residuals.norm(dim=-1)
        outlier = distance > _outlier_distance(residuals[keep], threshold)
        for i in range(len(points)):  # every view keeps its 4 best points
            mine = torch.nonzero(view == i).squeeze(-1)
            if int((~outlier[mine]).sum()) < 4:
                outlier[mine[distance[mine].argsort()[:4]]] = False
        if previous is not None and torch.equal(outlier, previous):
            break
        if 2 * int((~outlier).sum()) <= result.num_free:
            break
        previous, keep = outlier, ~outlier
        problem = Problem(IntrinsicsMap(model, result.params, settings["image_size"], frozen),
                          all_points[keep], all_pixels[keep], view[keep], result.poses)
        sizes = [int(((view == i) & keep).sum()) for i in range(len(points))]
        start = result.start
        result = solve(problem, method, loss="linear", loss_scale=loss_scale, sizes=sizes,
                       **settings)
        result.start = start
        iterations += result.iterations
        history += [dict(h, round=round_) for h in result.history]
    result.residuals = list(_all_residuals(result, model, all_points, all_pixels, view).split(
        [len(p) for p in points]))
    result.outliers = [torch.nonzero(~keep[view == i]).squeeze(-1) for i in range(len(points))]
    result.iterations, result.history = iterations, history
    return result


def _all_residuals(result: FitResult, model: CameraModel, points: Tensor, pixels: Tensor,
                   view: Tensor) -> Tensor:
    """``(M, 2)`` residuals of every observation (kept or not) at ``result``'s solution."""
    with torch.no_grad():
        projected, _ = model.project(transform(result.poses[view], points), result.params)
    return projected - pixels


def _levenberg_marquardt(problem: Problem, z0: Tensor, loss: str, loss_scale: float,
                         max_iterations: int | None, progress,
                         determined: Callable[[Tensor], bool]
                         ) -> tuple[Tensor, bool, str, int, list[dict]]:
    """Levenberg-Marquardt with ``max_iterations`` as a hard limit, or by default in rounds
    (module docstring: ``LM_ROUND``, ``LM_PROGRESS``, ``LM_MAX_ITERATIONS``); a round starts
    only where ``determined(z)``: the data determine the parameters there."""
    floor = COST_FLOOR * problem.points.shape[0]
    if max_iterations is not None:
        state = levenberg_marquardt(problem.evaluate, z0, loss=loss, loss_scale=loss_scale,
                                    max_iterations=max_iterations, progress=progress,
                                    cost_floor=floor)
        return state.z, state.converged, state.reason, state.iterations, state.history
    z, lam, done, history = z0, 1e-3, 0, []
    while True:
        before = float(robust_cost(problem.evaluate(z, False)[0], loss, loss_scale)[0])
        state = levenberg_marquardt(problem.evaluate, z, loss=loss, loss_scale=loss_scale,
                                    max_iterations=min(LM_ROUND, LM_MAX_ITERATIONS - done),
                                    lambda0=lam, progress=progress, cost_floor=floor)
        history += [dict(h, iteration=h["iteration"] + done) for h in state.history]
        done += state.iterations
        z = state.z
        if state.converged or "iterations without converging" not in state.reason:
            return z, state.converged, state.reason, done, history
        fall = (before - state.cost) / state.cost if state.cost > 0 else 0.0
        why = ("the most by default" if done >= LM_MAX_ITERATIONS else
               f"the last {LM_ROUND} lowered the cost by {fall:.2g} (relative)"
               if not fall > LM_PROGRESS else
               "no more: these views do not determine the parameters there"
               if not determined(z) else None)
        if why is not None:
            return z, False, f"{done} iterations without converging ({why})", done, history
        lam = max(state.history[-1]["lambda"] / 10, 1e-15) if state.history else lam


def solve(problem: Problem, method: str, *, loss: str, loss_scale: float,
          max_iterations: int | None, optimality_tol: float, max_condition: float,
          max_std: float, progress, sizes: list[int], image_size: tuple[int, int]
          ) -> FitResult:
    """Run ``method`` on ``problem`` from its start and check the result (module docstring)."""
    return _solve(problem, method, loss=loss, loss_scale=loss_scale,
                  max_iterations=max_iterations, optimality_tol=optimality_tol,
                  max_condition=max_condition, max_std=max_std, progress=progress,
                  sizes=sizes, image_size=image_size)[0]


def _uncertainty(problem: Problem, z: Tensor, loss: str, loss_scale: float,
                max_condition: float, max_std: float) -> tuple[float, Tensor, Tensor]:
    """``(condition, covariance, std_free)`` at ``z`` (the checks of the module docstring)."""
    residuals, jac = problem.evaluate(z, True)
    a, _, _ = normal_equations(residuals, jac, loss, loss_scale)
    condition = scaled_condition(a) if bool(torch.isfinite(a).all()) else math.inf
    m, n = residuals.shape[0], problem.num_free
    sigma2 = _weighted_square(residuals, loss, loss_scale) / (2 * m - n)
    return (condition, *_covariance(a, sigma2, problem, z, condition, max_condition))


def _solve(problem: Problem, method: str, *, loss: str, loss_scale: float,
           max_iterations: int | None, optimality_tol: float, max_condition: float,
           max_std: float, progress, sizes: list[int], image_size: tuple[int, int]
           ) -> tuple[FitResult, bool]:
    """`solve`, and whether the method itself stopped on a convergence test (rather than
    on its budget, or on data that do not determine the parameters)."""
    def determined(z: Tensor) -> bool:
        condition, _, std_free = _uncertainty(problem, z, loss, loss_scale, max_condition,
                                             max_std)
        return condition <= max_condition and not bool((std_free > max_std).any())

    z0 = problem.z0()
    if method == "linear":
        z, ok, iterations, history = z0, True, 0, []
        reason = "closed-form linear solution (not refined; not a least-squares minimum)"
    elif method == "lm":
        z, ok, reason, iterations, history = _levenberg_marquardt(
            problem, z0, loss, loss_scale, max_iterations, progress, determined)
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

    camera, failures = None, {} if ok else {"method": reason}
    try:
        camera = Camera(problem.model, params, image_size)
    except ValueError as err:
        failures["range"] = f"the parameters left the model's range: {err}"
    if num_invalid:
        failures["domain"] = (f"{num_invalid} of {m} observations project outside the model's "
                              "domain")
    if method != "linear" and not at_minimum:
        failures["minimum"] = (f"not at a minimum: a Gauss-Newton step would lower the cost by "
                               f"{gain:.2e} (relative), above optimality_tol {optimality_tol:g}")
    near_degenerate = []
    if not condition <= max_condition:
        failures["degenerate"] = (f"degenerate data: the scaled condition number of J^T J is "
                                  f"{condition:.3g}, above max_condition {max_condition:g}; "
                                  f"some parameters are not determined by these views")
    else:
        names = problem.intrinsics.free_names
        loose = [k for k, sd in enumerate(std_free) if sd > max_std]
        near_degenerate = [_partner(covariance, problem.intrinsics.free, names, k)
                           for k in loose]
        if loose:
            failures["near_degenerate"] = (
                f"near-degenerate data: " + ", ".join(
                    f"{names[k]} (+- {float(covariance[i, i]) ** 0.5:.3g})"
                    for k, i in ((k, problem.intrinsics.free[k]) for k in loose))
                + f" not determined by these views (standard deviation above max_std "
                f"{max_std:g} in free units); " + correlated_pairs(near_degenerate))
    method_ok = ok
    ok, reason = (True, reason) if not failures else (False, "; ".join(failures.values()))
    return FitResult(
        camera=camera, params=params, param_names=problem.intrinsics.names,
        free_names=problem.intrinsics.free_names, poses=poses,
        rms=float(torch.sqrt((residuals * residuals).sum(-1).mean())), converged=ok,
        reason=reason,
        iterations=iterations, method=method, covariance=covariance,
        std=torch.sqrt(torch.diagonal(covariance).clamp(min=0)),
        residuals=list(residuals.split(sizes)) if problem.num_views else [residuals],
        num_invalid=num_invalid, gauss_newton_gain=gain, condition=condition,
        num_observations=m, num_free=n, cost=cost, history=history,
        outliers=[torch.zeros(0, dtype=torch.long) for _ in sizes]
        if problem.num_views else [], failed_checks=tuple(c for c in CHECKS if c in failures),
        near_degenerate=near_degenerate), method_ok


def correlated_pairs(near_degenerate: list[tuple[str, str | None, float]]) -> str:
    """``FitResult.near_degenerate`` in words, each pair once: ``"xi and k2 correlated at
    0.998"`` (``"xi undetermined"`` where no other intrinsic is free)."""
    seen, words = set(), []
    for name, partner, corr in near_degenerate:
        if partner is None:
            words.append(f"{name} undetermined")
        elif frozenset((name, partner)) not in seen:
            seen.add(frozenset((name, partner)))
            words.append(f"{name} and {partner} correlated at {corr:.3f}")
    return "; ".join(words)


def _partner(covariance: Tensor, free: list[int], names: tuple[str, ...], k: int
             ) -> tuple[str, str | None, float]:
    """``(name, partner, correlation)`` of the ``k``-th free intrinsic: the other free
    intrinsic most correlated with it in ``covariance`` (natural parameters)."""
    idx = torch.tensor(free, dtype=torch.long)
    cov = covariance[idx][:, idx]
    sd = torch.diagonal(cov).clamp(min=1e-300).sqrt()
    corr = cov / sd[:, None] / sd[None]
    row = corr[k].clone()
    row[k] = 0.0
    if row.numel() < 2 or not bool(torch.isfinite(row).all()):
        return names[k], None, math.nan
    j = int(row.abs().argmax())
    return names[k], names[j], float(row[j])


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
