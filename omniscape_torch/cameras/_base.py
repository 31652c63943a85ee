"""What every camera model shares: the model record, entry checks and the numerical helpers.

A model is a record of two pure functions over tensors that broadcast over leading dimensions:

    project(points (..., 3), params (..., P)) -> (pixels (..., 2), valid (...))
    unproject(pixels (..., 2), params (..., P)) -> (rays (..., 3) unit norm, valid (...))

plus ``max_angle(params) -> (...)``, the supremum of the angle between a ray of the model's domain
and the optical axis (radians). Invalid lanes hold finite values with finite gradients: unsafe
denominators and radicands are replaced with ``torch.where`` *before* the operation, never after.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np
import torch
from torch import Tensor


@dataclass(frozen=True)
class FisheyeDraw:
    """How the augmentation modules draw a fisheye lens of a model (`render/kernels/draw.py`).

    Attributes:
        ranges: per parameter drawn after ``fx, fy, cx, cy``: the augmentation modules' argument
            that holds its ``(min, max)`` range, and that range's default.
        zeros: parameters after the drawn ones that are 0 (unified's ``k1, k2, p1, p2``: no
            lens distortion).
        distortion: the model's coefficients are drawn in ``+-kb_distortion`` and halved
            until the lens stays monotonic past the drawn half field of view
            (Kannala-Brandt's ``k1..k4``).
    """

    ranges: tuple[tuple[str, tuple[float, float]], ...] = ()
    zeros: int = 0
    distortion: bool = False

    @property
    def fixed_reach(self) -> bool:
        """No lens parameters: the model's reach is fixed, so a ``fov_range`` beyond it is
        refused at construction; the others are fitted to each drawn field of view."""
        return not self.ranges and not self.distortion


@dataclass(frozen=True)
class CameraModel:
    """One camera model of the registry.

    Attributes:
        name: registry key, e.g. ``"kannala_brandt"``.
        param_names: names of the flat parameter vector, in order. For a ``variadic`` model the
            last name is the first of a series that may go on (``a0, a1, ..., aN``).
        project: ``(points (..., 3), params (..., P)) -> (pixels (..., 2), valid (...))``.
        unproject: ``(pixels (..., 2), params (..., P)) -> (unit rays (..., 3), valid (...))``.
        max_angle: ``params (..., P) -> (...)``: supremum of the angle to the optical axis over the
            model's domain, radians; no gradient.
        groups: parameter groups (``focal``, ``center``, ``distortion``, ``affine``) as index
            tuples, so that a fit can freeze a group.
        variadic: the polynomial at the end of ``param_names`` has any length >= 1.
        optional: names that may follow ``param_names``, all of them or none (the skew ``s``
            of ``kannala_brandt`` and ``unified``, as OpenCV's ``fisheye`` and ``omnidir`` have
            it): a parameter vector holds ``len(param_names)`` or
            ``len(param_names) + len(optional)`` values.
        check_values: raises ``ValueError`` for parameter values outside the model's range.
        unproject_xyz: for a closed-form model, ``unproject`` as components:
            ``(u (...), v (...), params (..., P)) -> (x, y, z, valid)``, without input checks
            (for fused kernels: ``render.kernels.camera_grid``); None for the others.
        domain_end: for a radially symmetric model whose unprojection is valid exactly where
            the normalised radius is below a bound: ``params (..., P) -> (...)``, that bound
            (``inf``: none), so that ``render.kernels.radial_table`` need not search for it;
            None for the others.
        radial: the ray of a pixel depends on its distance from the principal point in
            normalised coordinates alone (radially symmetric), so one radius -> ray table per
            camera holds every pixel's ray (``render.kernels.camera.radial_table``).
        fisheye_draw: how the augmentation modules draw a fisheye lens of this model
            (``ot.augment``'s ``fisheye_models``), or None: not drawn.
    """

    name: str
    param_names: tuple[str, ...]
    project: Callable[..., tuple[Tensor, Tensor]]
    unproject: Callable[..., tuple[Tensor, Tensor]]
    max_angle: Callable[[Tensor], Tensor]
    groups: Mapping[str, tuple[int, ...]] = field(default_factory=dict)
    variadic: bool = False
    check_values: Callable[[Tensor], None] | None = None
    unproject_xyz: Callable[..., tuple[Tensor, Tensor, Tensor, Tensor]] | None = None
    domain_end: Callable[[Tensor], Tensor] | None = None
    optional: tuple[str, ...] = ()
    radial: bool = False
    fisheye_draw: FisheyeDraw | None = None

    @property
    def num_params(self) -> int:
        """Number of parameters (the minimum for a variadic model or one with optional ones)."""
        return len(self.param_names)

    @property
    def counts(self) -> tuple[int, ...]:
        """The parameter counts a non-variadic model takes."""
        n = len(self.param_names)
        return (n, n + len(self.optional)) if self.optional else (n,)

    def names_for(self, num_params: int) -> tuple[str, ...]:
        """Parameter names for a parameter vector of length ``num_params``."""
        self.check_num_params(num_params, "params")
        if not self.variadic:
            return self.param_names + (self.optional if num_params > self.num_params else ())
        stem = self.param_names[-1].rstrip("0123456789")
        first = int(self.param_names[-1][len(stem):])
        return self.param_names[:-1] + tuple(
            f"{stem}{first + i}" for i in range(num_params - len(self.param_names) + 1))

    def check_num_params(self, num_params: int, what: str = "params") -> None:
        ok = num_params >= self.num_params if self.variadic else num_params in self.counts
        if not ok:
            expected = (f"at least {self.num_params}" if self.variadic
                        else " or ".join(map(str, self.counts)))
            optional = f", optionally {', '.join(self.optional)}" if self.optional else ""
            raise ValueError(
                f"{what}: the {self.name} model takes {expected} parameters "
                f"({', '.join(self.param_names)}{', ...' if self.variadic else ''}{optional}), "
                f"got {num_params}")

    def validate_params(self, params: Tensor, what: str = "params") -> None:
        """Full check of a parameter tensor: type, length, finiteness and the model's ranges."""
        if not isinstance(params, Tensor):
            raise TypeError(f"{what}: expected a torch.Tensor, got {type(params).__name__}")
        if not params.is_floating_point():
            raise TypeError(f"{what}: expected a floating-point tensor, got {params.dtype}")
        if params.dim() == 0:
            raise ValueError(f"{what}: expected shape (..., P), got a scalar")
        self.check_num_params(params.shape[-1], what)
        finite = torch.isfinite(params.detach()).reshape(-1, params.shape[-1]).all(0)
        if not bool(finite.all()):
            names = self.names_for(params.shape[-1])
            bad = [names[i] for i in (~finite).nonzero()[:, 0].tolist()]
            raise ValueError(f"{what}: {', '.join(bad)} of the {self.name} model must be finite, "
                             f"got {params.detach().cpu().tolist()}")
        if self.check_values is not None:
            try:
                self.check_values(params.detach())
            except ValueError as err:   # the checks say "params: ..."; name the argument
                raise ValueError(f"{what}: {str(err).removeprefix('params: ')}") from None

    def __repr__(self) -> str:
        return f"CameraModel({self.name!r}, params={self.param_names})"


# --------------------------------------------------------------------------------------------
# Entry checks (one per public function; shapes only: values are checked once, in Camera).
# --------------------------------------------------------------------------------------------

def broadcast_shapes(*shapes) -> torch.Size:
    """``torch.broadcast_shapes`` (same rules, same ``RuntimeError``), without the 0.5 s its
    first call takes to import ``torch._refs``: numpy's implementation of the rules."""
    try:
        return torch.Size(np.broadcast_shapes(*(tuple(s) for s in shapes)))
    except ValueError as err:
        raise RuntimeError(str(err)) from None


def check_inputs(model_name: str, values: Tensor, params: Tensor, dim: int,
                 num_params: int | tuple[int, ...], what: str, variadic: bool = False) -> None:
    """Shape and dtype check at the entry of ``project``/``unproject``; ``num_params``: the
    count, the counts a model takes, or the least count of a ``variadic`` one."""
    for name, t in ((what, values), ("params", params)):
        if not isinstance(t, Tensor):
            raise TypeError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
        if not t.is_floating_point():
            raise TypeError(f"{name}: expected a floating-point tensor, got {t.dtype}")
    if values.dim() == 0 or values.shape[-1] != dim:
        raise ValueError(f"{what}: expected shape (..., {dim}), got {tuple(values.shape)}")
    n = params.shape[-1] if params.dim() else 0
    counts = num_params if isinstance(num_params, tuple) else (num_params,)
    if (n < counts[0]) if variadic else (n not in counts):
        expected = f"at least {counts[0]}" if variadic else " or ".join(map(str, counts))
        raise ValueError(f"params: the {model_name} model takes {expected} parameters on the "
                         f"last axis, got shape {tuple(params.shape)}")
    if values.dtype != params.dtype:
        raise TypeError(f"{what} and params must have the same dtype, got {values.dtype} and "
                        f"{params.dtype}")
    if values.device != params.device:
        raise ValueError(f"{what} and params must be on the same device, got {values.device} "
                         f"and {params.device}")
    try:
        broadcast_shapes(values.shape[:-1], params.shape[:-1])
    except RuntimeError:
        raise ValueError(f"{what} of shape {tuple(values.shape)} and params of shape "
                         f"{tuple(params.shape)} do not broadcast over their leading dimensions"
                         ) from None


def check_positive(params: Tensor, index: tuple[int, ...], names: tuple[str, ...],
                   model: str) -> None:
    bad = (params[..., list(index)] <= 0).any(dim=tuple(range(params.dim() - 1)))
    for i, b in zip(index, bad.tolist() if bad.dim() else [bool(bad)]):
        if b:
            raise ValueError(f"params: {names[i]} of the {model} model must be > 0, got "
                             f"{params[..., i].cpu().tolist()}")


def check_range(params: Tensor, i: int, lo: float, hi: float, names: tuple[str, ...],
                model: str) -> None:
    p = params[..., i]
    if bool(((p < lo) | (p > hi)).any()):
        raise ValueError(f"params: {names[i]} of the {model} model must lie in [{lo}, {hi}], got "
                         f"{p.cpu().tolist()}")


# --------------------------------------------------------------------------------------------
# NaN-safe building blocks.
# --------------------------------------------------------------------------------------------

def near_zero_radius(rho2: Tensor, scale2: Tensor | float) -> Tensor:
    """True where a squared radius ``rho2`` is too small to divide by, relative to ``scale2``.

    Below ``eps**2 * scale2`` the first-order series of every radial model is exact to rounding,
    so the caller switches to it; the absolute floor keeps ``sqrt`` away from denormals.
    """
    info = torch.finfo(rho2.dtype)
    threshold = info.eps * info.eps * scale2
    if isinstance(threshold, Tensor):
        return rho2 <= torch.clamp(threshold, min=info.tiny)
    return rho2 <= max(threshold, info.tiny)


def polar(points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``rho = |(x, y)|``, ``theta = atan2(rho, z)`` and ``axis`` (rho too small to divide by).

    On the axis, ``rho`` is 0 and ``theta`` is 0 in front (z > 0) and pi behind, without ever
    evaluating ``atan2(0, .)``, whose gradient is NaN at the origin.
    """
    # contiguous components: torch's atan2 on stride-3 views takes its slow scalar loop (16x)
    x, y, z = (c.contiguous() for c in points.unbind(-1))
    rho2 = x * x + y * y
    axis = near_zero_radius(rho2, z * z)
    rho = safe_sqrt(rho2, ~axis)
    ones = torch.ones_like(rho)
    theta = torch.where(axis, torch.where(z > 0, 0.0 * ones, math.pi * ones),
                        torch.atan2(torch.where(axis, ones, rho), z))
    return rho, theta, axis


def safe_sqrt(x: Tensor, ok: Tensor) -> Tensor:
    """``sqrt(x)`` where ``ok``, 0 elsewhere, with a finite gradient everywhere."""
    return torch.where(ok, torch.sqrt(torch.where(ok, x, torch.ones_like(x))), torch.zeros_like(x))


def safe_div(num: Tensor, den: Tensor, ok: Tensor) -> Tensor:
    """``num / den`` where ``ok``, 0 elsewhere, with a finite gradient everywhere."""
    return torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(num))


def polyval(coeffs: Tensor, x: Tensor) -> Tensor:
    """Evaluate ``sum_i coeffs[..., i] * x**i`` (Horner), broadcasting ``coeffs (..., N)``."""
    out = coeffs[..., -1]
    for i in range(coeffs.shape[-1] - 2, -1, -1):
        out = out * x + coeffs[..., i]
    return out


def polyder(coeffs: Tensor) -> Tensor:
    """Coefficients (ascending) of the derivative of an ascending-order polynomial."""
    n = coeffs.shape[-1]
    if n == 1:
        return torch.zeros_like(coeffs)
    k = torch.arange(1, n, dtype=coeffs.dtype, device=coeffs.device)
    return coeffs[..., 1:] * k


def smallest_positive_root(coeffs: Tensor, scale: Tensor | float = 1.0) -> Tensor:
    """Smallest positive real root of ``c0 + c1 t + ... + cn t**n`` with ``c0 != 0``; inf if none.

    The roots are the reciprocals of the eigenvalues of the companion matrix of the reversed
    polynomial ``c0 s**n + ... + cn``, whose leading coefficient ``c0`` is never zero, so vanishing
    high-order coefficients need no special case. ``t`` is rescaled by ``scale`` first so that the
    coefficients are of order one (a radius in pixels otherwise spans 30 orders of magnitude).
    Computed in float64 without gradient: it decides validity, it is not differentiated.

    Args:
        coeffs: ``(..., n + 1)`` ascending coefficients.
        scale: typical magnitude of ``t`` (broadcasts over ``...``).

    Returns:
        ``(...)`` tensor, dtype and device of ``coeffs``.
    """
    with torch.no_grad():
        c = coeffs.detach().to(torch.float64)
        scale = torch.as_tensor(scale, dtype=torch.float64, device=c.device)
        n = c.shape[-1] - 1
        out_shape = broadcast_shapes(c.shape[:-1], scale.shape)
        # a constant polynomial has no root (nor has one whose higher coefficients all vanish,
        # e.g. an undistorted lens's fold: the eigenvalue solve would give the same inf)
        if n == 0 or not bool(c[..., 1:].any()):
            return torch.full(out_shape, math.inf, dtype=coeffs.dtype, device=coeffs.device)
        powers = scale.unsqueeze(-1) ** torch.arange(n + 1, dtype=torch.float64, device=c.device)
        c = c * powers
        c = c / c[..., :1]
        # the companion matrix: -c1 .. -cn on its first row, ones below the diagonal (a
        # concatenation, and the eigenvalues' parts as real tensors: the index assignments and
        # complex arithmetic this replaces were 0.25 of the 0.5 ms a one-row call took)
        shift = torch.eye(n - 1, n, dtype=torch.float64, device=c.device)
        comp = torch.cat((-c[..., None, 1:], shift.expand(*c.shape[:-1], n - 1, n)), -2)
        s = torch.view_as_real(torch.linalg.eigvals(comp))
        re, im = s[..., 0], s[..., 1]
        real = (im.abs() <= 1e-7 * torch.hypot(re, im).clamp(min=1e-300)) & (re > 0)
        s_max = torch.where(real, re, torch.zeros_like(re)).amax(dim=-1)
        t = torch.where(s_max > 0, 1.0 / s_max.clamp(min=1e-300), math.inf) * scale
        return t.to(coeffs.dtype)


def invert_monotone(f: Callable[[Tensor], tuple[Tensor, Tensor]], target: Tensor, hi: Tensor,
                    iterations: int, tol: float) -> tuple[Tensor, Tensor]:
    """Solve ``f(x) = target`` for ``x`` in ``[0, hi]`` where ``f`` increases; no gradient.

    Safeguarded Newton: a Newton step that leaves the bracket is replaced by bisection, so each
    iteration at least halves the bracket or converges quadratically; at most ``iterations`` steps,
    ending early once every lane has converged.

    Args:
        f: ``x -> (f(x), f'(x))``, broadcasting.
        target: ``(...)`` values to reach.
        hi: ``(...)`` upper end of the bracket (finite).
        iterations: maximum number of iterations.
        tol: tolerance on ``|f(x) - target|``, relative to ``1 + |target|``.

    Returns:
        ``x (...)`` and ``converged (...)``.
    """
    with torch.no_grad():
        bound = tol * (1 + target.abs())
        lo = torch.zeros_like(target)
        hi = torch.broadcast_to(hi, target.shape).clone()
        x = 0.5 * (lo + hi)
        converged = torch.zeros_like(target, dtype=torch.bool)
        for _ in range(iterations):
            fx, dfx = f(x)
            res = fx - target
            converged = res.abs() <= bound
            if bool(converged.all()):
                return x, converged
            # lerp with a 0/1 weight selects like torch.where (finite values), 6x faster on
            # data-dependent masks; this loop runs without gradient
            below = (res < 0).to(x.dtype)
            lo = torch.lerp(lo, x, below)
            hi = torch.lerp(x, hi, below)
            slope_ok = dfx > 0
            newton = x - res / torch.where(slope_ok, dfx, torch.ones_like(dfx))
            inside = (slope_ok & (newton > lo) & (newton < hi)).to(x.dtype)
            step = torch.lerp(0.5 * (lo + hi), newton, inside)
            x = torch.lerp(step, x, converged.to(x.dtype))
        fx, _ = f(x)
        return x, (fx - target).abs() <= bound


def implicit_step(x_star: Tensor, residual: Tensor, slope: Tensor) -> Tensor:
    """One Newton step from a detached root ``x_star``: ``x_star - residual / slope``.

    ``residual`` is ``f(x_star) - target`` computed *with* gradient; at a converged root it is zero
    in value, so this adds nothing to ``x_star`` but carries the implicit-function-theorem
    gradient ``-(d residual) / slope`` to the parameters and the target.
    """
    ok = slope.detach().abs() > 0
    return x_star - safe_div(residual, slope.detach(), ok)


# --------------------------------------------------------------------------------------------
# Shared by the models with a distortion of the plane (tangential, thin prism): their inverse.
# --------------------------------------------------------------------------------------------

def series_or(x: Tensor, small: Tensor, exact: Callable[[Tensor], Tensor],
              series: Callable[[Tensor], Tensor]) -> Tensor:
    """``exact(x)`` where not ``small``, ``series(x)`` where ``small``: for removable
    singularities (``sin(x) / x`` at 0), NaN-free in value and gradient on both branches."""
    return torch.where(small, series(torch.where(small, x, torch.zeros_like(x))),
                       exact(torch.where(small, torch.ones_like(x), x)))


def polymul(a: Tensor, b: Tensor) -> Tensor:
    """Ascending coefficients ``(..., n + m - 1)`` of the product of ``a (..., n)`` and
    ``b (..., m)``."""
    n, m = a.shape[-1], b.shape[-1]
    shape = broadcast_shapes(a.shape[:-1], b.shape[:-1])
    out = [torch.zeros(shape, dtype=a.dtype, device=a.device) for _ in range(n + m - 1)]
    for i in range(n):
        for j in range(m):
            out[i + j] = out[i + j] + a[..., i] * b[..., j]
    return torch.stack(out, -1)


def _complex_step(distort: Callable, mx: Tensor, my: Tensor, coeffs: Tensor):
    """The map ``distort(mx, my, coeffs) -> (x, y)`` and its 2 x 2 Jacobian by the complex step
    ``df/dx = Im f(x + i h) / h``: exact to rounding for the analytic maps here (polynomials and
    ratios of them), with no subtraction and so no step size to tune (Squire and Trapp 1998)."""
    h = torch.finfo(mx.dtype).eps ** 2
    c = coeffs.to(torch.complex128 if mx.dtype == torch.float64 else torch.complex64)
    zero = torch.zeros_like(mx)
    x1, y1 = distort(torch.complex(mx, zero + h), torch.complex(my, zero), c)
    x2, y2 = distort(torch.complex(mx, zero), torch.complex(my, zero + h), c)
    return x1.real, y1.real, x1.imag / h, x2.imag / h, y1.imag / h, y2.imag / h


def newton_step_2d(mx: Tensor, my: Tensor, rx: Tensor, ry: Tensor, a: Tensor, b: Tensor,
                   c: Tensor, e: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """One 2-D Newton step ``m - J^-1 r`` with ``J = [[a, b], [c, e]]`` and the residual
    ``r = (rx, ry)``: ``(mx, my, ok)``, ``ok`` where ``J`` is invertible (elsewhere the step
    is 0, with a finite gradient)."""
    det = a * e - b * c
    ok = det.abs() > torch.finfo(det.dtype).tiny
    return mx - safe_div(e * rx - b * ry, det, ok), my - safe_div(a * ry - c * rx, det, ok), ok


def fold_guarded_step(mx: Tensor, my: Tensor, rx: Tensor, ry: Tensor, a: Tensor, b: Tensor,
                      c: Tensor, e: Tensor, t_fold: Tensor) -> tuple[Tensor, Tensor]:
    """`newton_step_2d` from ``(mx, my)``, shortened where it would cross the fold
    (``mx^2 + my^2 >= t_fold``) to land halfway to it, so that the iteration stays on the
    sheet where the distortion is invertible."""
    nx, ny, _ = newton_step_2d(mx, my, rx, ry, a, b, c, e)
    r2_old, r2_new = mx * mx + my * my, nx * nx + ny * ny
    crossed = r2_new >= t_fold
    shrink = torch.sqrt(torch.where(
        crossed, 0.5 * (r2_old + t_fold) / torch.where(crossed, r2_new, torch.ones_like(r2_new)),
        torch.ones_like(r2_new)))
    return nx * shrink, ny * shrink


def undistort_2d(xd: Tensor, yd: Tensor, coeffs: Tensor, distort: Callable, radial: Callable,
                 t_limit: Tensor, iterations: int, jacobian: Callable | None = None
                 ) -> tuple[Tensor, Tensor, Tensor]:
    """Invert a distortion of the plane, ``distort(mx, my, coeffs) = (xd, yd)``, as OpenCV's
    ``undistortPoints`` and COLMAP's ``IterativeUndistortion`` do, by 2-D Newton with the 2 x 2
    Jacobian: ``jacobian(mx, my, coeffs) -> (x, y, dx/dmx, dx/dmy, dy/dmx, dy/dmy)`` written
    out (the models' own; tests/test_cameras.py checks them against the complex step), else the
    complex step (exact to rounding, 3-4 times slower: complex arithmetic).

    The start is the inverse of the radial part alone (``radial(r, coeffs) -> (g(r), g'(r))``,
    increasing on ``[0, sqrt(t_limit))``) at ``|(xd, yd)|``, by the safeguarded 1-D Newton of
    `invert_monotone`, so that strong radial distortion does not lead Newton astray; a
    2-D step that would cross the fold (``mx^2 + my^2 >= t_limit``) is shortened to land halfway
    to it. At most ``iterations`` steps, ending early once every lane has converged to
    ``8 eps (1 + |xd| + |yd|)``, or two steps after every lane is within ``64 eps (1 + |xd| +
    |yd|)`` (the rounding of a strongly distorting polynomial, whose terms cancel, can stay
    above the first bound at the root); a lane counts as converged within the second. The root
    is found without gradient; one Newton step with gradient then carries the
    implicit-function-theorem derivative to the pixels and ``coeffs``.

    Returns:
        ``mx, my`` and ``converged`` (non-converged lanes hold 0, finite gradients).
    """
    tol = 8 * torch.finfo(xd.dtype).eps
    if jacobian is None:
        def jacobian(mx, my, c):
            return _complex_step(distort, mx, my, c)
    with torch.no_grad():
        c = coeffs.detach()
        tx, ty = xd.detach(), yd.detach()
        bound = tol * (1 + tx.abs() + ty.abs())
        loose = 8 * bound
        rd = torch.sqrt(tx * tx + ty * ty)
        r_lim = torch.sqrt(t_limit.detach())
        finite = torch.isfinite(r_lim)
        hi = torch.where(finite, r_lim, torch.ones_like(r_lim)) * torch.ones_like(rd)
        hi = torch.where(finite, hi, torch.maximum(hi, rd))
        for _ in range(64):   # a bracket where there is no fold: g grows without bound
            short = ~finite & (radial(hi, c)[0] < rd)
            if not bool(short.any()):
                break
            hi = torch.where(short, 2 * hi, hi)
        # a radius beyond the radial part's range starts at the fold (and will not converge)
        target = torch.minimum(rd, radial(hi, c)[0])
        r0, _ = invert_monotone(lambda r: radial(r, c), target, hi, iterations, tol)
        scale = torch.where(rd > 0, r0 / torch.where(rd > 0, rd, torch.ones_like(rd)),
                            torch.ones_like(rd))
        mx, my = tx * scale, ty * scale
        extra = stalled = 0
        previous = torch.full_like(tx, math.inf)
        fx, fy, a, b, cc, e = jacobian(mx, my, c)
        for _ in range(iterations):
            rx, ry = fx - tx, fy - ty
            res = rx.abs() + ry.abs()
            if bool((res <= bound).all()):
                break
            if bool((res <= loose).all()):
                extra += 1
                if extra > 2:
                    break
            # lanes pinned at the fold (pixels outside the domain) never converge: stop once
            # no unconverged lane has gained 10% for three steps (Newton next to a fold still
            # about halves its error per step)
            progress = ((res > loose) & (res < 0.9 * previous)).any()
            stalled = 0 if bool(progress) else stalled + 1
            if stalled >= 3:
                break
            previous = res
            mx, my = fold_guarded_step(mx, my, rx, ry, a, b, cc, e, t_limit)
            fx, fy, a, b, cc, e = jacobian(mx, my, c)
        converged = ((fx - tx).abs() + (fy - ty).abs()) <= loose
        converged = converged & torch.isfinite(mx) & torch.isfinite(my)
        # non-converged lanes: at 0 with the identity as Jacobian (finite, no gradient step)
        zero, one = torch.zeros_like(mx), torch.ones_like(mx)
        mx, my = torch.where(converged, mx, zero), torch.where(converged, my, zero)
        a, e = torch.where(converged, a, one), torch.where(converged, e, one)
        b, cc = torch.where(converged, b, zero), torch.where(converged, cc, zero)
    fx, fy = distort(mx, my, coeffs)
    rx, ry = fx - xd, fy - yd
    rx = torch.where(converged, rx, torch.zeros_like(rx))
    ry = torch.where(converged, ry, torch.zeros_like(ry))
    mx, my, ok = newton_step_2d(mx, my, rx, ry, a, b, cc, e)
    return mx, my, converged & ok
