"""The starts of a fit (initialisation): where Levenberg-Marquardt begins, and which start
`fit` goes on from.

OCamCalib's linear solution for ``scaramuzza``
(`omniscape_torch.calibration.linear.scaramuzza_linear`). The other models try several
starts and keep the best (``method="lm"``, no ``init``): the linear solution converted to the
model (its rays at the observed pixels fitted by the model, centre held at the image centre,
the unified model's ``k1, k2, p1, p2`` at 0), and the undistorted defaults whose focal length
puts a ray at ``fov / 2`` on the inscribed image circle (`default_intrinsics`) for the
model's default field of view, ``START_FOVS`` (120, 180 and 230 degrees, those the model can
see) and the caller's ``fov``; each view's pose comes from a planar homography on the
unprojected rays (`omniscape_torch.calibration.linear.planar_pose`). A short
Levenberg-Marquardt run (``START_ITERATIONS``, on at most ``START_POINTS`` points of each view)
from every start ranks them by cost (fewest observations outside the model's domain first),
all the starts' problems evaluated together (`rank_starts`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..cameras import CameraModel, get_model
from ..cameras.camera import _check_image_size
from .linear import planar_pose, scaramuzza_linear
from .lm import MAX_LAMBDA, levenberg_marquardt, normal_equations, robust_cost
from .params import IntrinsicsMap, transform
from .problem import COST_FLOOR, Problem, view_index

#: Default full field of view of `default_intrinsics`, radians.
DEFAULT_FOV = {"pinhole": math.radians(90), "fov": math.radians(90),
               "division": math.radians(90), "opencv": math.radians(90)}

#: Full fields of view (radians) of the default starts of `fit`, besides the model's
#: ``DEFAULT_FOV`` (else pi) and the caller's ``fov``; those the model cannot see are skipped.
START_FOVS = (math.radians(120), math.radians(180), math.radians(230))

#: Levenberg-Marquardt iterations of the short run that ranks each start.
START_ITERATIONS = 4

#: Points per view (evenly spaced in the view's order) of that short run: it ranks basins, it
#: does not need every point.
START_POINTS = 24

#: Undistorted starting values of the models' non-focal parameters (unified xi = 1 and its
#: equivalents: a parabolic mirror, the middle of the fisheye range).
DEFAULT_DISTORTION = {"kannala_brandt": (0.0, 0.0, 0.0, 0.0), "unified": (1.0, 0.0, 0.0, 0.0, 0.0),
                      "eucm": (0.5, 1.0), "double_sphere": (0.0, 0.5),
                      # fov: COLMAP's start (omega = 0 is a pinhole, where d/d omega vanishes)
                      "fov": (1e-2,), "division": (0.0,), "opencv": (0.0,) * 12,
                      "thin_prism_fisheye": (0.0,) * 8, "fisheye624": (0.0,) * 12}


def unit_intrinsics(model: CameraModel) -> Tensor:
    """``(P,)`` float64: the camera of focal length 1 at the origin with the undistorted defaults
    (``DEFAULT_DISTORTION``); ``woodscape``: ``cx = cy = 0``, ``aspect_ratio = k1 = 1``, the
    rest 0 (its focal length is ``k1``)."""
    if model.name == "woodscape":
        return torch.tensor([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    return torch.tensor([1.0, 1.0, 0.0, 0.0, *DEFAULT_DISTORTION.get(model.name, ())],
                        dtype=torch.float64)


def with_focal(model: CameraModel, unit: Tensor, focal: float, centre: Tensor) -> Tensor:
    """``unit`` (``unit_intrinsics``) at the focal length ``focal`` (pixels) and the
    principal point ``centre (2,)``; ``woodscape``'s polynomial is in pixels: every
    coefficient scales."""
    centre = torch.as_tensor(centre, dtype=torch.float64)
    if model.name == "woodscape":
        return torch.cat((centre, unit[2:3], focal * unit[3:]))
    return torch.cat((torch.tensor([focal, focal], dtype=torch.float64), centre, unit[4:]))


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
    unit = unit_intrinsics(model)
    theta = min(0.5 * fov, 0.999 * float(model.max_angle(unit)))
    ray = torch.tensor([math.sin(theta), 0.0, math.cos(theta)], dtype=torch.float64)
    radius = float(model.project(ray, unit)[0][0])
    focal = 0.5 * min(h, w) / radius
    return with_focal(model, unit, focal,
                      torch.tensor([(w - 1) / 2, (h - 1) / 2], dtype=torch.float64))


def initial_poses(model: CameraModel, params: Tensor, points: list[Tensor],
                   pixels: list[Tensor]) -> Tensor:
    """``(V, 6)`` poses from a planar homography on the rays of ``params`` (one unprojection,
    one batched solve per group of views of the same size)."""
    rays, valid = model.unproject(torch.cat(pixels), params)
    sizes = [len(p) for p in pixels]
    rays, valid = rays.split(sizes), valid.split(sizes)
    for i, ok in enumerate(valid):
        if int(ok.sum()) < 4:
            raise ValueError(f"view {i}: fewer than 4 pixels are inside the initial camera's "
                             f"domain; pass init (or fov) closer to the camera")
    poses = torch.zeros(len(points), 6, dtype=torch.float64)
    for size in set(sizes):
        group = [i for i, n in enumerate(sizes) if n == size]
        poses[group] = planar_pose(torch.stack([points[i] for i in group]),
                                   torch.stack([rays[i] for i in group]),
                                   torch.stack([valid[i] for i in group]))
    return poses


def default_fov(model: CameraModel) -> float:
    """The full field of view (radians) of `default_intrinsics` without one: ``DEFAULT_FOV``,
    else pi."""
    return DEFAULT_FOV.get(model.name, math.pi)


def default_starts(model: CameraModel, image_size: tuple[int, int], fov: float | None,
                    points: list[Tensor], pixels: list[Tensor], frozen: list[int]
                    ) -> list[tuple[str, Tensor]]:
    """``(label, params)`` of every start of a non-polynomial model (module docstring)."""
    starts = []
    linear = linear_start(model, image_size, points, pixels, frozen)
    if linear is not None:
        starts.append(("linear", linear))
    unit = default_intrinsics(model, (2, 2), math.radians(90))
    limit = 2 * float(model.max_angle(unit))
    fovs: list[float] = []
    for f in [default_fov(model)] + ([] if fov is None else [fov]) + [
            f for f in START_FOVS if f < limit]:
        if all(abs(f - g) > 1e-9 for g in fovs):
            fovs.append(f)
            starts.append((f"fov {math.degrees(f):g}", default_intrinsics(model, image_size, f)))
    return starts


def linear_start(model: CameraModel, image_size: tuple[int, int], points: list[Tensor],
                  pixels: list[Tensor], frozen: list[int]) -> Tensor | None:
    """OCamCalib's linear solution converted to ``model``: its rays at (at most 200 of) the
    observed pixels, fitted by the model with the centre at the image centre, the focal length
    from the median ratio of radii, the unified model's ``k1, k2, p1, p2`` and ``frozen`` held
    at their defaults. None where the linear solution fails or is not a camera."""
    try:
        linear, _ = scaramuzza_linear(points, pixels, image_size, 4)
    except (ValueError, RuntimeError):  # not planar, not a camera, a singular system
        return None
    pix = torch.cat(pixels)
    pix = pix[torch.linspace(0, len(pix) - 1, min(len(pix), 200)).round().long()]
    poly = get_model("scaramuzza")
    rays, valid = poly.unproject(pix, linear)
    if int(valid.sum()) < 8:
        return None
    rays, pix = rays[valid], pix[valid]
    theta = torch.atan2(rays[:, :2].norm(dim=-1), rays[:, 2])
    start = default_intrinsics(model, image_size, min(2 * float(theta.max()), 2 * math.pi))
    unit = unit_intrinsics(model)   # start's, at focal 1 about the origin
    near, ok = model.project(rays, unit)
    centre = start[list(model.groups["center"])]
    radius = (pix - centre).norm(dim=-1)
    ratio = radius / near.norm(dim=-1).clamp(min=1e-12)
    ok = ok & torch.isfinite(ratio) & (near.norm(dim=-1) > 1e-6)
    if int(ok.sum()) < 8:
        return None
    start = with_focal(model, unit, float(ratio[ok].median()), centre)
    names = model.names_for(start.shape[-1])
    hold = set(frozen) | set(model.groups["center"])
    if model.name == "unified":
        hold |= {names.index(n) for n in ("k1", "k2", "p1", "p2")}
    intrinsics = IntrinsicsMap(model, start, image_size, sorted(hold))
    if not intrinsics.free:
        return start
    problem = Problem(intrinsics, rays, pix, torch.zeros(len(pix), dtype=torch.long),
                      torch.zeros(0, 6, dtype=torch.float64))
    state = levenberg_marquardt(problem.evaluate, problem.z0(), max_iterations=10,
                                cost_floor=COST_FLOOR * len(pix))
    params = intrinsics.natural(state.z).detach()
    try:
        model.validate_params(params)
    except ValueError:
        return None
    return params if math.isfinite(state.cost) else None


def rank_starts(model: CameraModel, starts: list[tuple[str, Tensor]],
                 image_size: tuple[int, int], frozen: list[int], points: list[Tensor],
                 pixels: list[Tensor], poses: Tensor | None, loss: str, loss_scale: float
                 ) -> list[tuple[str, Tensor, Tensor]]:
    """``(label, params, poses)`` at the end of a short Levenberg-Marquardt run
    (``START_ITERATIONS`` on at most ``START_POINTS`` points per view) from every start, the
    fewest invalid observations first, then the lowest cost."""
    picks = [torch.linspace(0, len(p) - 1, min(len(p), START_POINTS)).round().long()
             for p in points]
    sub_points = [p[i] for p, i in zip(points, picks)]
    sub_pixels = [q[i] for q, i in zip(pixels, picks)]
    if 2 * sum(len(p) for p in sub_points) <= (len(starts[0][1]) - len(frozen)
                                               + 6 * len(points)):
        sub_points, sub_pixels = points, pixels
    view = view_index(sub_points)
    problems, labels, errors = [], [], []
    for label, params0 in starts:
        try:
            poses0 = poses if poses is not None else initial_poses(model, params0, sub_points,
                                                                     sub_pixels)
        except ValueError as err:
            errors.append(f"{label}: {err}")
            continue
        problems.append(Problem(IntrinsicsMap(model, params0, image_size, frozen),
                                torch.cat(sub_points), torch.cat(sub_pixels), view, poses0))
        labels.append(label)
    ranked = []
    for label, problem, (z, cost) in zip(labels, problems, _short_runs(
            problems, loss, loss_scale, START_ITERATIONS)):
        if not math.isfinite(cost):
            errors.append(f"{label}: the cost is not finite")
            continue
        key = (int((~problem.residuals(z)[1]).sum()), cost)
        params = problem.intrinsics.natural(z[:problem.num_intrinsics]).detach()
        ranked.append((key, label, params, problem.poses(z).detach()))
    if not ranked:
        raise ValueError("no start sees 4 points of every view (" + "; ".join(errors) + "); pass "
                         "init (or fov) closer to the camera")
    ranked.sort(key=lambda item: item[0])
    return [item[1:] for item in ranked]


def _evaluate_stack(problems: list[Problem], zs: list[Tensor], jacobian: bool
                    ) -> list[tuple[Tensor, Tensor | None]]:
    """`Problem.evaluate` of several problems of one model (with views) in one call of
    its projection and two backward passes: the fixed cost of a call dominates small ones."""
    model = problems[0].model
    if not jacobian:
        with torch.no_grad():
            params = torch.cat([pr.intrinsics.natural(z[:pr.num_intrinsics]).expand(
                len(pr.points), -1) for pr, z in zip(problems, zs)])
            poses = torch.cat([pr.poses(z)[pr.view] for pr, z in zip(problems, zs)])
            points = torch.cat([pr.points for pr in problems])
            res = model.project(transform(poses, points), params)[0]
        return [(pr._weighted(r - pr.pixels), None) for pr, r in zip(
            problems, res.split([len(pr.points) for pr in problems]))]
    leaves = [pr.leaves(z) for pr, z in zip(problems, zs)]
    points = torch.cat([pr.points for pr in problems])
    projected = model.project(transform(torch.cat([lv[1] for lv in leaves]), points),
                              torch.cat([lv[0] for lv in leaves]))[0]
    res = [pr._weighted(r - pr.pixels) for pr, r in zip(
        problems, projected.split([len(pr.points) for pr in problems]))]
    inputs = [x for lv in leaves for x in lv]
    stacked = torch.cat(res)
    grads = [torch.autograd.grad(stacked[:, k].sum(), inputs, retain_graph=k == 0)
             for k in range(2)]
    return [(r.detach(), pr.assemble(z, [g[2 * i:2 * i + 2] for g in grads]))
            for i, (pr, z, r) in enumerate(zip(problems, zs, res))]


def _short_runs(problems: list[Problem], loss: str, loss_scale: float, iterations: int
                ) -> list[tuple[Tensor, float]]:
    """Levenberg-Marquardt from the start of every problem, all evaluated together
    (`_evaluate_stack`): ``iterations`` accepted steps each at most, Marquardt's damping
    as in `omniscape_torch.calibration.lm` (divided by 10 after an accepted step,
    multiplied by 10 after a rejected one). Returns ``(z, cost)`` per problem."""
    if not problems:
        return []
    zs = [pr.z0() for pr in problems]
    systems = [normal_equations(r, j, loss, loss_scale)
               for r, j in _evaluate_stack(problems, zs, True)]
    lam = [1e-3] * len(problems)
    steps = [0] * len(problems)
    active = list(range(len(problems)))
    for _ in range(3 * iterations):
        trials = {}
        for i in active:
            a, g, _ = systems[i]
            diag = torch.diagonal(a).clamp(min=1e-300 + 1e-12 * float(torch.diagonal(a).max()))
            factor, info = torch.linalg.cholesky_ex(a + lam[i] * torch.diag(diag))
            delta = torch.cholesky_solve(-g[:, None], factor)[:, 0] if int(info) == 0 else None
            if delta is None or not bool(torch.isfinite(delta).all()):
                lam[i] *= 10
            else:
                trials[i] = zs[i] + delta
        moved = []
        if trials:
            keys = list(trials)
            for i, (r, _) in zip(keys, _evaluate_stack([problems[i] for i in keys],
                                                       [trials[i] for i in keys], False)):
                cost = float(robust_cost(r, loss, loss_scale)[0])
                if math.isfinite(cost) and cost < float(systems[i][2]):
                    zs[i], lam[i] = trials[i], max(lam[i] / 10, 1e-15)
                    steps[i] += 1
                    moved.append(i)
                else:
                    lam[i] *= 10
        if moved:
            for i, (r, j) in zip(moved, _evaluate_stack([problems[i] for i in moved],
                                                        [zs[i] for i in moved], True)):
                systems[i] = normal_equations(r, j, loss, loss_scale)
        active = [i for i in active if steps[i] < iterations and lam[i] <= MAX_LAMBDA]
        if not active:
            break
    return [(z, float(system[2])) for z, system in zip(zs, systems)]
