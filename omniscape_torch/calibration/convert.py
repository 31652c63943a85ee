"""Model conversion: a camera of another model (or polynomial degree) fitted to an existing one.

`convert` samples the area the source camera images on a regular pixel grid (its valid
pixels, within its field of view: ``fov``, by default the source's own, and within ``mask``, e.g.
the image circle `image_circle` finds in a photograph), unprojects them with the source,
and fits the target's parameters so that ``target.project(R ray)`` lands on the source pixel
(Levenberg-Marquardt, `omniscape_torch.calibration.fit`). A second grid offset by half a step
is held out: the reported errors are measured on it, as pixel distance
``|target.project(R ray) - pixel|`` (RMS: the root of the mean squared distance, and maximum)
and as the angle between the source's ray and ``R^T target.unproject(pixel)``.

Affine terms. OCamCalib fits a 2 x 2 affine map of the sensor (``c, d, e``). Any such map is an
upper-triangular one (focal lengths and a skew) times a rotation about the optical axis, and a
rotation of the image plane about the axis is a rotation of the rays (the lens is radially
symmetric), so the other models represent it exactly with their skew ``s`` (``kannala_brandt``:
OpenCV fisheye's ``alpha = s / fx``; ``unified``: OpenCV omnidir's ``K[0, 1]``) and the
rotation ``R`` between the two camera frames, which the fit returns (``result.rotation``; all
three angles are fitted, so a principal axis that differs is absorbed too). By default both
are fitted where the source has an affine term and the target lacks one (not for a
``scaramuzza`` target, which carries it): ``rotation=None``, ``skew=None``; elsewhere ``R`` is
the identity. Extrinsics compose with it: a point ``X`` in the source camera's frame is
``R X`` in the target's, so a source pose ``X_cam = R_s X_world + t_s`` becomes
``X_cam' = (R R_s) X_world + R t_s``.

The fit minimises the sum of squared distances, then (``minimax`` rounds, Lawson's iteratively
reweighted least squares: each sample's weight times its distance) moves towards the smallest
worst-case error, keeping the round whose largest error on the fitted grid is smallest: a model
that cannot follow the lens exactly spreads its error instead of piling it at the rim.

Samples that the target cannot represent at the solution (outside its domain) are dropped and
the fit is run once more without them; their share of the held-out samples is reported as
``unrepresentable`` (the fraction of the source's area the target cannot cover): the models that
divide by z (``pinhole``, ``fov``, ``opencv``) stop short of 90 degrees, ``division`` with
k > 0 at ``atan(1 / (2 sqrt k))``, so from a wide lens they report the rim they miss.

Held by default: ``CONVERT_FREEZE``, and the target's tangential and thin-prism terms
(``ASYMMETRIC``) where the source lens has none (it is radially symmetric, apart from an
affine term, which the rotation and the skew hold): a symmetric lens needs none of them.

The source's own model (of the same polynomial degree, for ``scaramuzza``), without ``init``,
``freeze`` or a fitted rotation: nothing is fitted; the target is the source's parameters,
exactly, valid over the converted area (``fov``, else the source's), and the errors are measured
on the held-out grid as for any target (zero, to rounding).

Starting values: the target's centre is the source's (``cx, cy``); a ``scaramuzza`` target gets
its polynomial from a linear least-squares fit of ``g(rho) = rho z / |(x, y)|`` to the rays;
the other models their undistorted defaults with the focal length that matches the source's
median radius per unit-focal radius over the samples within 60 degrees of the axis; the skew 0,
the rotation the identity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import torch
from torch import Tensor

from ..cameras import Camera, CameraModel, get_model
from ..cameras._checks import check_one_camera
from .fit import FitResult, solve
from .params import IntrinsicsMap, axis_angle_to_matrix, frozen_indices
from .problem import Problem
from .starts import unit_intrinsics, with_focal

#: Parameters held in a first fit, released in a second from its solution: the unified model's
#: distortion trades off against xi, and from the undistorted start the joint fit can settle in a
#: local minimum that the Geyer-Daniilidis solution avoids.
STAGED = {"unified": ("k1", "k2", "p1", "p2")}

#: Levenberg-Marquardt iterations of a reweighting round (each starts from the previous one).
MINIMAX_ITERATIONS = 25

#: Parameters held by default in a conversion (OCamCalib's ``a1 = 0``; without poses the sensor
#: roll ``e`` is determined, unlike in a calibration). ``opencv``: the rational denominator and
#: the thin prism, as ``cv2.calibrateCamera``'s default flags (k1, k2, p1, p2, k3): with them the
#: numerator and denominator trade off and J^T J is singular (condition number above 1e12 for a
#: radial-tangential source, which k1, k2, p1, p2 already hold exactly); ``freeze=()`` frees them.
CONVERT_FREEZE = {"scaramuzza": ("a1",), "opencv": ("k4", "k5", "k6", "s1", "s2", "s3", "s4")}

#: The tangential and thin-prism terms, the models' only departures from radial symmetry. They
#: are held at 0 by default where the source has none (every other model, or these with the
#: terms 0): a symmetric lens needs none, and freed they trade off against the centre and the
#: rotation (the real OCamCalib camera to fisheye624: the centre moves 17 px and the worst
#: held-out error grows from 0.49 to 0.83 px).
ASYMMETRIC = {"opencv": ("p1", "p2", "s1", "s2", "s3", "s4"),
              "thin_prism_fisheye": ("p1", "p2", "sx1", "sy1"),
              "fisheye624": ("p0", "p1", "s0", "s1", "s2", "s3")}


@dataclass
class ConversionResult:
    """Outcome of `convert`. Errors are measured on the held-out grid, in pixels and
    radians, over the samples the target represents.

    Attributes:
        camera: the target camera (None when the fit left the model's range), its ``fov`` the
            converted area's (without one, twice the largest angle of its samples).
        fit: the `FitResult` of the final fit (``converged``, ``reason``, ``std``...;
            after ``minimax`` rounds, of the weighted problem: its ``rms`` is weighted).
        max_px, rms_px: largest and RMS pixel distance (RMS: root of the mean squared distance).
        max_angle, rms_angle: largest and RMS angle between source and target rays, radians.
        unrepresentable: fraction of the held-out samples outside the target's domain.
        num_params: the target's free parameters (the rotation's three angles not counted).
        num_samples: fitted samples (after dropping the unrepresentable ones).
        rotation: ``(3, 3)`` float64: a point ``X`` of the source camera's frame is ``R X`` in
            the target's (module docstring); the identity where not fitted.
        max_field: the largest angle from the optical axis of the converted area, radians.
    """

    camera: Camera | None
    fit: FitResult
    max_px: float
    rms_px: float
    max_angle: float
    rms_angle: float
    unrepresentable: float
    num_params: int
    num_samples: int
    rotation: Tensor = field(default_factory=lambda: torch.eye(3, dtype=torch.float64))
    max_field: float = math.nan

    @property
    def converged(self) -> bool:
        return self.fit.converged

    def to_dict(self) -> dict:
        """A JSON-ready summary (angles in degrees, as files carry them)."""
        return {"model": self.fit.camera.model.name if self.fit.camera else None,
                "converged": self.converged, "reason": self.fit.reason,
                "max_px": self.max_px, "rms_px": self.rms_px,
                "max_angle_deg": math.degrees(self.max_angle),
                "rms_angle_deg": math.degrees(self.rms_angle),
                "unrepresentable": self.unrepresentable, "num_params": self.num_params,
                "num_samples": self.num_samples, "max_field_deg": math.degrees(self.max_field),
                "rotation": self.rotation.tolist(),
                "params": dict(zip(self.fit.param_names, self.fit.params.tolist()))}


def sample_pixels(camera: Camera, grid: int, offset: float, *, max_field: float | None = None,
                  mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``grid x grid`` pixels spread over the image at ``(i + offset) / grid`` of each side,
    kept where ``camera`` unprojects them, within ``max_field`` radians of the optical axis and
    where ``mask (H, W)`` is true at the nearest pixel: ``(pixels (K, 2), rays (K, 3))`` in
    float64."""
    h, w = camera.image_size
    steps = (torch.arange(grid, dtype=torch.float64) + offset) / grid
    v, u = torch.meshgrid(steps * h - 0.5, steps * w - 0.5, indexing="ij")
    pixels = torch.stack((u, v), -1).reshape(-1, 2)
    double = Camera(camera.model, camera.params.detach().double(), camera.image_size,
                    fov=camera.fov, blind_fov=camera.blind_fov)
    rays, valid = double.unproject(pixels)
    if max_field is not None:
        valid &= rays[:, 2] >= math.cos(max_field)
    if mask is not None:
        col = pixels[:, 0].round().long().clamp(0, w - 1)
        row = pixels[:, 1].round().long().clamp(0, h - 1)
        valid &= mask[row, col]
    return pixels[valid], rays[valid]


def _rings(image, camera: Camera) -> tuple[Tensor, int, Tensor, Tensor]:
    """What `image_circle` and `blind_cone` read of ``image``: its grey levels
    after a 5 x 5 box blur ``(H, W)``, the step of the pixels whose rays they ring (every
    step-th: about 200k, as a fisheye's ray grid is their cost), and those pixels' rays and
    validity through ``camera``."""
    img = torch.as_tensor(image).double()
    h, w = camera.image_size
    if img.dim() == 3:
        img = img.mean(0) if img.shape[1:] == (h, w) else img.mean(-1)
    if tuple(img.shape) != (h, w):
        raise ValueError(f"image: expected an image of the camera's size {(h, w)}, got shape "
                         f"{tuple(torch.as_tensor(image).shape)}")
    blurred = torch.nn.functional.avg_pool2d(img[None, None], 5, 1, 2,
                                             count_include_pad=False)[0, 0]
    step = max(math.ceil(math.sqrt(h * w / 200_000)), 1)
    source = Camera(camera.model, camera.params.detach().double(), (h, w))
    with torch.no_grad():
        rays, valid = source.unproject(source.pixel_grid()[::step, ::step])
    return blurred, step, rays, valid


def image_circle(image, camera: Camera) -> float:
    """The field of view (full angle, radians) of the image circle of a fisheye photograph.

    The unlit border's level is the median of the four corner patches (1/32 of each side), the
    lit level the median of the disc about the principal point (radius 1/8 of the shorter
    side); a pixel is lit above a quarter of the way from the first to the second (after a
    5 x 5 box blur). Ring by ring (1 degree wide) about the optical axis, the circle ends at the
    first ring where fewer than half of ``camera``'s valid pixels are lit; ``2 pi`` where none is
    or where the corners are lit (their level above a quarter of the way from the image's 1st to
    its 99th percentile: a full-frame lens, whose circle lies beyond the sensor; or a uniform
    image). ``0`` where
    the circle cannot be measured: the disc about the axis no brighter than the corners, or the
    innermost ring unlit (a catadioptric image's dark centre); callers fall back (``fit
    --images``: the corners' reach) or ask for ``--fov``.

    Args:
        image: ``(H, W)``, ``(H, W, C)`` or ``(C, H, W)`` array or tensor, any dtype.
        camera: the camera that took it (its ``image_size`` is the image's).
    """
    h, w = camera.image_size
    blurred, step, rays, valid = _rings(image, camera)
    ch, cw = max(h // 32, 1), max(w // 32, 1)
    corners = torch.cat([blurred[:ch, :cw], blurred[:ch, -cw:], blurred[-ch:, :cw],
                         blurred[-ch:, -cw:]], 0)
    sub = blurred[::step, ::step]
    angle = torch.rad2deg(torch.acos(rays[..., 2].double().clamp(-1, 1)))
    row, col = torch.nonzero(valid & (angle == angle[valid].min()))[0].tolist()
    near = torch.hypot(torch.arange(0, h, step, dtype=torch.float64)[:, None] - row * step,
                       torch.arange(0, w, step, dtype=torch.float64) - col * step) < min(h, w) / 8
    dark, bright = corners.median(), sub[near].median()
    lo, hi = torch.quantile(blurred.flatten()[::max(h * w // 200_000, 1)],
                            torch.tensor([0.01, 0.99], dtype=torch.float64)).tolist()
    if hi <= lo or float(dark) > lo + 0.25 * (hi - lo):
        return 2 * math.pi   # lit to the sensor's corners (or uniform): no circle within it
    if bright <= dark:
        return 0.0
    lit = sub > dark + 0.25 * (bright - dark)
    ring = angle[valid].floor().long()
    count = torch.bincount(ring, minlength=181)
    share = torch.bincount(ring, lit[valid].double(), minlength=181) / count.clamp_min(1)
    unlit = ((share < 0.5) & (count > 0)).nonzero()
    return 2 * math.pi if len(unlit) == 0 else 2 * math.radians(float(unlit[0, 0]))


def blind_cone(image, camera: Camera) -> float:
    """The blind cone (full angle, radians) of a catadioptric photograph: the dark disc about
    the optical axis where the camera sees its own reflection in the mirror.

    Over rings of 1 degree about the axis (``camera``'s valid pixels, every step-th as in
    `image_circle`, after a 5 x 5 box blur), the cone ends at the first ring whose median
    is above halfway from the innermost ring's median to the lit level (the 90th percentile of
    the rings' medians). ``0`` where the innermost ring is itself lit (a fisheye) or no ring is.
    Give it the mean of several views (``fit --images`` does), so that a dark square of the
    board is not taken for the camera; ``fit`` also keeps the cone below the corners' nearest
    angle to the axis.

    Args:
        image: ``(H, W)``, ``(H, W, C)`` or ``(C, H, W)`` array or tensor, any dtype.
        camera: the camera that took it (its ``image_size`` is the image's).
    """
    blurred, step, rays, valid = _rings(image, camera)
    blurred = blurred[::step, ::step]
    if not bool(valid.any()):
        return 0.0
    ring = torch.rad2deg(torch.acos(rays[..., 2].clamp(-1, 1)))[valid].floor().long()
    levels = blurred[valid]
    rings = torch.unique(ring)
    medians = torch.stack([levels[ring == r].median() for r in rings])
    inner, lit = float(medians[0]), float(torch.quantile(medians, 0.9))
    if lit <= inner or rings[0] > 2:
        return 0.0
    bright = (medians > inner + 0.5 * (lit - inner)).nonzero()
    if len(bright) == 0 or int(bright[0, 0]) == 0:
        return 0.0
    return 2 * math.radians(float(rings[int(bright[0, 0])]))


def without_affine(camera: Camera) -> Camera:
    """A ``scaramuzza`` camera with its affine term removed (``c = 1, d = e = 0``): the part of
    a conversion's error that the lens model, not the affine term, causes (module docstring)."""
    if camera.model.name != "scaramuzza":
        raise ValueError(f"camera: expected a scaramuzza camera, got {camera.model.name}")
    p = camera.params.detach().double().clone()
    p[2:5] = torch.tensor([1.0, 0.0, 0.0], dtype=p.dtype)
    return Camera("scaramuzza", p, camera.image_size, fov=camera.fov, blind_fov=camera.blind_fov)


def _has_affine(camera: Camera) -> bool:
    """Whether the source's pixel grid is sheared or turned (not a diagonal map)."""
    p = camera.params.detach()
    if camera.model.name == "scaramuzza":
        return bool(p[3:5].ne(0).any())
    optional = camera.model.optional
    return bool(optional) and p.shape[-1] > camera.model.num_params and bool(p[-1].ne(0))


def _symmetric(camera: Camera) -> bool:
    """Whether the source's lens is radially symmetric (no tangential or thin-prism term)."""
    names = ASYMMETRIC.get(camera.model.name, ())
    p = camera.params.detach()
    return not any(bool(p[camera.model.param_names.index(n)] != 0) for n in names)


def _source_center(camera: Camera) -> tuple[Tensor, Tensor]:
    """Centre ``(2,)`` and the sensor-to-image affine ``(2, 2)`` of the source."""
    p = camera.params.detach().double()
    if camera.model.name == "scaramuzza":
        cx, cy, c, d, e = p[:5].tolist()
        return p[:2], torch.tensor([[1.0, e], [d, c]], dtype=torch.float64)
    return p[list(camera.model.groups["center"])], torch.eye(2, dtype=torch.float64)


def _initial_params(target: CameraModel, source: Camera, degree: int, pixels: Tensor,
                    rays: Tensor) -> Tensor:
    center, affine = _source_center(source)
    rxy = rays[:, :2].norm(dim=-1)
    off_axis = rxy > 1e-9
    if target.name == "scaramuzza":
        sensor = torch.linalg.solve(affine, (pixels - center).T).T
        rho = sensor.norm(dim=-1)[off_axis]
        g = rho * rays[off_axis, 2] / rxy[off_axis]
        s = 0.5 * math.hypot(*source.image_size)
        powers = [0] + list(range(2, degree + 1))
        cols = torch.stack([s * (rho / s) ** i for i in powers], -1)
        sol = torch.linalg.lstsq(cols, -g[:, None], driver="gelsd").solution[:, 0]
        poly = torch.zeros(degree + 1, dtype=torch.float64)
        for j, i in enumerate(powers):
            poly[i] = sol[j] * s ** (1 - i)
        return torch.cat((center, affine[1, 1:], affine[1, :1], affine[0, 1:], poly))
    unit = unit_intrinsics(target)
    theta = torch.atan2(rxy, rays[:, 2])
    limit = min(math.radians(60), 0.9 * float(target.max_angle(unit)))
    use = off_axis & (theta > math.radians(2)) & (theta < limit)
    if not bool(use.any()):
        raise ValueError("camera: no valid sample between 2 and 60 degrees off the axis to start "
                         "the conversion from")
    unit_px, _ = target.project(rays[use], unit)
    ratio = (pixels[use] - center).norm(dim=-1) / unit_px.norm(dim=-1)
    return with_focal(target, unit, float(ratio.median()), center)


def convert(camera: Camera, to_model: str | CameraModel, *, degree: int = 4, grid: int = 48,
            fov: float | None = None, mask: Tensor | None = None, rotation: bool | None = None,
            skew: bool | None = None, minimax: int = 4, init=None,
            freeze: Sequence[str] | None = None, max_iterations: int = 200,
            progress: bool | None = False) -> ConversionResult:
    """Fit a camera of ``to_model`` to the area ``camera`` images (module docstring).

    Args:
        camera: the source: one camera of any model.
        to_model: the target model name (not ``equirectangular``).
        degree: polynomial degree of a ``scaramuzza`` target.
        grid: samples per image side of the fitted grid (and of the held-out grid).
        fov: full field of view of the converted area, radians (default: the source's
            ``fov``, else its whole valid area); `image_circle` measures a photograph's.
        mask: ``(H, W)`` bool, the pixels to convert (e.g. inside the image circle).
        rotation: fit the rotation between the camera frames (None: where the source has an
            affine term and the target is not ``scaramuzza``).
        skew: give the target its optional skew ``s`` (None: under the same condition, for the
            models that have one).
        minimax: reweighting rounds towards the smallest worst-case error (0: least squares).
        init: starting target parameters ``(P,)`` (default: module docstring).
        freeze: groups or names held at their start (default ``CONVERT_FREEZE``, and the
            target's ``ASYMMETRIC`` terms where the source has none).
        max_iterations: Levenberg-Marquardt iterations per fit.
        progress: show a tqdm bar (``None``: when stderr is a terminal).

    Returns:
        A `ConversionResult`; check ``converged``.

    Raises:
        ValueError, TypeError: not one camera, unknown model, too few valid samples.
    """
    check_one_camera(camera)
    target = get_model(to_model)
    if target.name == "equirectangular":
        raise ValueError("to_model: equirectangular is a panorama projection, not a lens model")
    if isinstance(degree, bool) or not isinstance(degree, int) or degree < 1:
        raise ValueError(f"degree: expected an integer >= 1, got {degree!r}")
    if isinstance(grid, bool) or not isinstance(grid, int) or grid < 4:
        raise ValueError(f"grid: expected an integer >= 4, got {grid!r}")
    if isinstance(minimax, bool) or not isinstance(minimax, int) or minimax < 0:
        raise ValueError(f"minimax: expected an integer >= 0, got {minimax!r}")
    if fov is None:
        fov = camera.fov
    elif not (isinstance(fov, (int, float)) and 0 < fov <= 2 * math.pi):
        raise ValueError(f"fov: expected an angle in (0, 2 pi] radians, got {fov!r}")
    if mask is not None:
        mask = torch.as_tensor(mask)
        if mask.dtype != torch.bool or tuple(mask.shape) != tuple(camera.image_size):
            raise ValueError(f"mask: expected a bool tensor of the image's shape "
                             f"{tuple(camera.image_size)}, got {mask.dtype} of shape "
                             f"{tuple(mask.shape)}")
    field = None if fov is None or fov >= 2 * math.pi else fov / 2
    pixels, rays = sample_pixels(camera, grid, 0.25, max_field=field, mask=mask)
    held_pixels, held_rays = sample_pixels(camera, grid, 0.75, max_field=field, mask=mask)
    if init is None and freeze is None and not rotation and _same_model(camera, target, degree):
        out = Camera(target, camera.params.detach().double().clone(), camera.image_size,
                     fov=fov, blind_fov=camera.blind_fov)
        return _held_out(out, _unchanged(out), held_pixels, held_rays, len(pixels),
                         torch.eye(3, dtype=torch.float64))
    affine = _has_affine(camera) and target.name != "scaramuzza"
    rotate = affine if rotation is None else bool(rotation)
    skewed = (affine if skew is None else bool(skew)) and bool(target.optional)
    if init is None:
        params0 = _initial_params(target, camera, degree, pixels, rays)
        if skewed:
            params0 = torch.cat((params0, params0.new_zeros(len(target.optional))))
    else:
        params0 = torch.as_tensor(init, dtype=torch.float64).reshape(-1)
        target.validate_params(params0, "init")
    names = target.names_for(params0.shape[-1])
    if freeze is None:
        freeze = CONVERT_FREEZE.get(target.name, ())
        if _symmetric(camera):
            freeze = tuple(freeze) + ASYMMETRIC.get(target.name, ())
    frozen = frozen_indices(target, names, freeze)
    if 2 * len(pixels) <= params0.shape[-1] - len(frozen) + 3 * rotate:
        raise ValueError(f"camera: only {len(pixels)} valid samples in the converted area; "
                         f"raise grid or widen fov/mask")
    views = torch.zeros(1 if rotate else 0, 6, dtype=torch.float64)

    def run(start: Tensor, poses: Tensor, keep: Tensor, held: list[int],
            weights: Tensor | None = None, iterations: int = max_iterations) -> FitResult:
        intrinsics = IntrinsicsMap(target, start, camera.image_size, held)
        n = int(keep.sum())
        problem = Problem(intrinsics, rays[keep], pixels[keep],
                          torch.zeros(n, dtype=torch.long), poses, rotation_only=True,
                          weights=weights)
        return solve(problem, "lm", loss="linear", loss_scale=1.0,
                     max_iterations=iterations, optimality_tol=1e-6, max_condition=1e12,
                     max_std=1.0, progress=progress, sizes=[n], image_size=camera.image_size)

    keep = torch.ones(len(pixels), dtype=torch.bool)
    staged = [i for i in frozen_indices(target, names, STAGED.get(target.name, ()))
              if i not in frozen]
    if staged:
        first = run(params0, views, keep, frozen + staged)
        if first.camera is not None:
            params0, views = first.params, first.poses
    result = run(params0, views, keep, frozen)
    if result.num_invalid and result.camera is not None:
        keep = target.project(_turn(rays, result.poses), result.params)[1]
        result = run(result.params, result.poses, keep, frozen)
    result = _minimax(result, lambda r, w: run(r.params, r.poses, keep, frozen, w,
                                               min(max_iterations, MINIMAX_ITERATIONS)),
                      rays[keep], pixels[keep], minimax)

    turn = (axis_angle_to_matrix(result.poses[0, :3]) if rotate
            else torch.eye(3, dtype=torch.float64))
    out = result.camera
    if out is not None:   # valid where it was fitted: the area's fov, else the samples' reach
        reach = float(torch.acos(torch.cat((rays, held_rays))[:, 2].clamp(-1, 1)).max())
        out = Camera(target, result.params, camera.image_size,
                     fov=fov if fov is not None else min(2 * reach, 2 * math.pi),
                     blind_fov=camera.blind_fov)
    return _held_out(out, result, held_pixels, held_rays, int(keep.sum()), turn)


def _same_model(camera: Camera, target: CameraModel, degree: int) -> bool:
    """Whether ``target`` is the source's own model (of polynomial degree ``degree``, for
    ``scaramuzza``: its coefficients ``a0..a_degree`` after ``cx, cy, c, d, e``)."""
    if target.name != camera.model.name:
        return False
    return target.name != "scaramuzza" or camera.params.shape[-1] == 6 + degree


def _unchanged(camera: Camera) -> FitResult:
    """The `FitResult` of a conversion to the source's own model: nothing fitted."""
    p = camera.params.shape[-1]
    zeros = torch.zeros(p, p, dtype=torch.float64)
    return FitResult(camera, camera.params, camera.param_names, (), torch.zeros(0, 6,
                     dtype=torch.float64), 0.0, True, "the source's own model: its parameters, "
                     "exactly (nothing fitted)", 0, "none", zeros, zeros[0], [], 0, 0.0,
                     math.nan, 0, 0, 0.0)


def _held_out(out: Camera | None, result: FitResult, held_pixels: Tensor, held_rays: Tensor,
              num_samples: int, turn: Tensor) -> ConversionResult:
    """The `ConversionResult` of ``out``: its errors on the held-out grid."""
    nan = math.nan
    max_field = float(torch.acos(held_rays[:, 2].clamp(-1, 1)).max()) if len(held_rays) else nan
    if out is None:
        return ConversionResult(None, result, nan, nan, nan, nan, nan,
                                len(result.free_names), num_samples, turn, max_field)
    target = out.model
    turned = held_rays @ turn.T
    projected, ok_p = target.project(turned, result.params)
    back, ok_u = target.unproject(held_pixels, result.params)
    ok = ok_p & ok_u
    px = (projected - held_pixels).norm(dim=-1)[ok]
    cross = torch.linalg.cross(back, turned).norm(dim=-1)
    angle = torch.atan2(cross, (back * turned).sum(-1))[ok]
    if not bool(ok.any()):
        return ConversionResult(out, result, nan, nan, nan, nan, 1.0, len(result.free_names),
                                num_samples, turn, max_field)
    return ConversionResult(
        out, result, max_px=float(px.max()), rms_px=float(torch.sqrt((px * px).mean())),
        max_angle=float(angle.max()), rms_angle=float(torch.sqrt((angle * angle).mean())),
        unrepresentable=float(1 - ok.double().mean()), num_params=len(result.free_names),
        num_samples=num_samples, rotation=turn, max_field=max_field)


def _turn(rays: Tensor, poses: Tensor) -> Tensor:
    """``rays`` rotated by the fit's one view (unchanged without one)."""
    return rays if poses.shape[0] == 0 else rays @ axis_angle_to_matrix(poses[0, :3]).T


def _minimax(result: FitResult, refit, rays: Tensor, pixels: Tensor, rounds: int) -> FitResult:
    """Lawson's reweighting from the least-squares ``result`` over the samples ``rays, pixels``:
    each sample's weight times its distance, renormalised, and ``refit(start, weights)``; the
    converged round with the smallest largest distance is kept (the least-squares one if none
    beats it)."""
    def distances(r: FitResult) -> Tensor | None:
        projected, ok = r.camera.model.project(_turn(rays, r.poses), r.params)
        return (projected - pixels).norm(dim=-1) if bool(ok.all()) else None

    if result.camera is None or not result.converged or distances(result) is None:
        return result
    best, best_worst = result, float(distances(result).max())
    weights, current = torch.ones(len(pixels), dtype=torch.float64), result
    for _ in range(rounds):
        weights = weights * distances(current).clamp_min(1e-12)
        weights = weights / weights.mean()
        current = refit(current, weights)
        d = distances(current) if current.camera is not None else None
        if d is None:
            break
        if current.converged and float(d.max()) < best_worst:
            best, best_worst = current, float(d.max())
    return best
