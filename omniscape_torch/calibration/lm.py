"""Levenberg-Marquardt on a least-squares problem ``min_z 1/2 sum_k rho(|r_k(z)|^2)``.

The problem is given as ``evaluate(z, jacobian)``, which returns the per-observation residuals
``r (M, 2)`` (pixels) and, when asked, their Jacobian ``J (M, 2, n)``. Robust losses act
through per-observation weights (iteratively reweighted least squares): with
``s = |r|^2 / scale^2`` the cost is ``1/2 scale^2 sum rho(s)`` and each row is weighted by
``sqrt(rho'(s))`` at the current point.

Damping (Marquardt 1963, as in MINPACK): the step solves
``(A + lambda diag(A)) delta = -g`` with ``A = J^T W J``, ``g = J^T W r``, so the damping is
invariant to the scale of each variable. ``lambda`` starts at ``lambda0 = 1e-3``, is divided by
10 after a step that lowers the cost (accepted) and multiplied by 10 after one that does not
(rejected, the point stays). The run stops as converged when an accepted step lowers the cost
by less than ``ftol`` relatively, or a step (accepted, or rejected after damping) is below
``xtol`` relative to ``|z|`` (at a minimum, the damped steps shrink until no step lowers the
cost any more: the minimum to rounding), or the largest cosine between the residual and a
column of ``J`` is below ``gtol``; it stops as not converged after ``max_iterations``
Jacobians or when ``lambda`` exceeds ``1e16`` with steps still above ``xtol``. A cost below ``cost_floor`` (residuals at rounding level, where relative
tests mean nothing) is converged too.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from typing import Callable

import torch
from torch import Tensor

#: Robust losses: name -> (rho(s), rho'(s)) of ``s = |r|^2 / scale^2``.
LOSSES: dict[str, Callable[[Tensor], tuple[Tensor, Tensor]]] = {
    "linear": lambda s: (s, torch.ones_like(s)),
    # Huber: quadratic below one scale, linear in |r| above
    "huber": lambda s: (torch.where(s <= 1, s, 2 * torch.sqrt(s.clamp(min=1)) - 1),
                        torch.where(s <= 1, torch.ones_like(s),
                                    torch.rsqrt(s.clamp(min=1)))),
    # Cauchy: log(1 + s), weight 1 / (1 + s)
    "cauchy": lambda s: (torch.log1p(s), 1 / (1 + s)),
}

#: Stop when ``lambda`` exceeds this: no damped step lowers the cost any more.
MAX_LAMBDA = 1e16

Evaluate = Callable[[Tensor, bool], tuple[Tensor, Tensor | None]]


def check_loss(loss: str, loss_scale: float) -> None:
    if loss not in LOSSES:
        raise ValueError(f"loss: expected one of {', '.join(LOSSES)}, got {loss!r}")
    if isinstance(loss_scale, bool) or not isinstance(loss_scale, (int, float)) or not (
            math.isfinite(loss_scale) and loss_scale > 0):
        raise ValueError(f"loss_scale: expected a positive number of pixels, got {loss_scale!r}")


def robust_cost(residuals: Tensor, loss: str, scale: float) -> tuple[Tensor, Tensor]:
    """``(cost, weights (M,))`` of residuals ``(M, 2)``: ``1/2 scale^2 sum rho(s)``, ``rho'(s)``."""
    s = (residuals * residuals).sum(-1) / (scale * scale)
    rho, weight = LOSSES[loss](s)
    return 0.5 * scale * scale * rho.sum(), weight


@dataclass
class LMState:
    """Outcome of `levenberg_marquardt`.

    Attributes:
        z: ``(n,)`` final free vector.
        cost: final cost.
        converged: a convergence test passed.
        reason: which test, or why the run stopped.
        iterations: Jacobians evaluated.
        history: one dict per iteration (``iteration``, ``cost``, ``lambda``, ``accepted``).
    """

    z: Tensor
    cost: float
    converged: bool
    reason: str
    iterations: int
    history: list[dict] = field(default_factory=list)


def normal_equations(residuals: Tensor, jacobian: Tensor, loss: str, scale: float
                     ) -> tuple[Tensor, Tensor, Tensor]:
    """``(A, g, cost)``: ``J^T W J``, ``J^T W r`` and the robust cost."""
    cost, weight = robust_cost(residuals, loss, scale)
    w = torch.sqrt(weight)[:, None, None]
    j = (jacobian * w).reshape(-1, jacobian.shape[-1])
    r = (residuals * w[..., 0]).reshape(-1)
    return j.T @ j, j.T @ r, cost


def levenberg_marquardt(evaluate: Evaluate, z0: Tensor, *, loss: str = "linear",
                        loss_scale: float = 1.0, max_iterations: int = 100, ftol: float = 1e-10,
                        xtol: float = 1e-10, gtol: float = 1e-10, lambda0: float = 1e-3,
                        cost_floor: float = 0.0, progress: bool | None = False) -> LMState:
    """Minimise the robust cost of ``evaluate`` from ``z0`` (see the module docstring).

    Args:
        evaluate: ``(z (n,), jacobian: bool) -> (residuals (M, 2), J (M, 2, n) or None)``.
        z0: ``(n,)`` start, float64.
        loss, loss_scale: robust loss (``LOSSES``) and its scale in pixels.
        max_iterations: maximum number of Jacobian evaluations.
        ftol, xtol, gtol: the convergence tolerances (module docstring).
        lambda0: initial damping.
        cost_floor: a cost at or below it is converged (exact data).
        progress: show a tqdm bar (``None``: when stderr is a terminal).

    Returns:
        An `LMState`.
    """
    from tqdm import tqdm

    z = z0.detach().clone()
    lam = lambda0
    history: list[dict] = []
    residuals, jac = evaluate(z, True)
    a, g, cost = normal_equations(residuals, jac, loss, loss_scale)
    bar = tqdm(total=max_iterations, disable=not (sys.stderr.isatty() if progress is None
                                                  else progress), desc="LM", file=sys.stderr)
    try:
        for iteration in range(1, max_iterations + 1):
            bar.update(1)
            if float(cost) <= cost_floor:
                return LMState(z, float(cost), True, "residuals at rounding level",
                               iteration - 1, history)
            col = torch.sqrt(torch.diagonal(a))
            cosine = (g.abs() / (col * math.sqrt(2 * float(cost))).clamp(min=1e-300)).max()
            if float(cosine) <= gtol:
                return LMState(z, float(cost), True, f"gradient below gtol ({gtol:g})",
                               iteration - 1, history)
            diag = torch.diagonal(a).clamp(min=1e-300 + 1e-12 * float(torch.diagonal(a).max()))
            while True:
                if lam > MAX_LAMBDA:
                    return LMState(z, float(cost), False, f"damping above {MAX_LAMBDA:g}: no "
                                   f"step lowers the cost", iteration, history)
                delta = _solve(a + lam * torch.diag(diag), -g)
                if delta is None:
                    lam *= 10
                    continue
                new_res, _ = evaluate(z + delta, False)
                new_cost, _ = robust_cost(new_res, loss, loss_scale)
                accepted = bool(torch.isfinite(new_cost)) and float(new_cost) < float(cost)
                history.append({"iteration": iteration, "cost": float(new_cost if accepted
                                                                      else cost),
                                "lambda": lam, "accepted": accepted})
                if accepted:
                    break
                if float(delta.norm()) <= xtol * (float(z.norm()) + xtol):
                    # damped down to a step below xtol and still no decrease: the minimum, to
                    # rounding (MINPACK's xtol test, on the rejected step)
                    return LMState(z, float(cost), True, f"no step above xtol ({xtol:g}) lowers "
                                   f"the cost", iteration, history)
                lam *= 10
            lam = max(lam / 10, 1e-15)
            small_step = float(delta.norm()) <= xtol * (float(z.norm()) + xtol)
            small_gain = float(cost - new_cost) <= ftol * float(cost)
            z = z + delta
            residuals, jac = evaluate(z, True)
            a, g, cost = normal_equations(residuals, jac, loss, loss_scale)
            if small_gain or small_step:
                why = (f"relative cost reduction below ftol ({ftol:g})" if small_gain
                       else f"step below xtol ({xtol:g})")
                return LMState(z, float(cost), True, why, iteration, history)
        return LMState(z, float(cost), False, f"{max_iterations} iterations without converging",
                       max_iterations, history)
    finally:
        bar.close()


def _solve(matrix: Tensor, rhs: Tensor) -> Tensor | None:
    """Cholesky solve; None where the matrix is not numerically positive definite."""
    factor, info = torch.linalg.cholesky_ex(matrix)
    if int(info) != 0:
        return None
    out = torch.cholesky_solve(rhs[:, None], factor)[:, 0]
    return out if bool(torch.isfinite(out).all()) else None


def gauss_newton_gain(a: Tensor, g: Tensor) -> float:
    """Cost reduction a full Gauss-Newton step predicts, ``g^T A^-1 g / 2``: near zero at a
    minimum, whatever method got there."""
    scale = torch.rsqrt(torch.diagonal(a).clamp(min=1e-300))
    step = torch.linalg.lstsq(a * scale[:, None] * scale[None], g * scale).solution
    return 0.5 * float((g * scale) @ step)


def scaled_condition(a: Tensor) -> float:
    """Condition number of ``A`` scaled to a unit diagonal (a correlation matrix): large when
    the data do not determine some combination of the parameters."""
    scale = torch.rsqrt(torch.diagonal(a).clamp(min=1e-300))
    eig = torch.linalg.eigvalsh(a * scale[:, None] * scale[None])
    return float(eig[-1] / eig[0]) if float(eig[0]) > 0 else math.inf
