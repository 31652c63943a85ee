"""Model conversion: a camera of another model (or polynomial degree) fitted to an existing one.

:func:`convert` samples the source camera's valid area on a regular pixel grid, unprojects it
with the source, and fits the target's parameters so that ``target.project(ray)`` lands on the
source pixel (Levenberg-Marquardt, :mod:`omniscape_torch.calibration.fit`, no poses). A second
grid offset by half a step is held out: the reported errors are measured on it, as pixel error
``|target.project(ray) - pixel|`` and angular error between the source's ray and
``target.unproject(pixel)``.

Samples that the target cannot represent at the solution (outside its domain) are dropped and
the fit is run once more without them; their share of the held-out samples is reported as
``unrepresentable`` (the fraction of the source's valid area the target cannot cover).

Starting values: the target's centre is the source's (``cx, cy``); a ``scaramuzza`` target gets
its polynomial from a linear least-squares fit of ``g(rho) = rho z / |(x, y)|`` to the rays;
the other models their undistorted defaults with the focal length that matches the source's
median radius per unit-focal radius over the samples within 60 degrees of the axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from ..cameras import Camera, CameraModel, get_model
from .fit import DEFAULT_DISTORTION, FitResult, Problem, solve
from .params import IntrinsicsMap, frozen_indices

#: Parameters held in a first fit, released in a second from its solution: the unified model's
#: distortion trades off against xi, and from the undistorted start the joint fit can settle in a
#: local minimum that the Geyer-Daniilidis solution avoids.
STAGED = {"unified": ("k1", "k2", "p1", "p2")}

#: Parameters held by default in a conversion (OCamCalib's ``a1 = 0``; without poses the sensor
#: roll ``e`` is determined, unlike in a calibration).
CONVERT_FREEZE = {"scaramuzza": ("a1",)}


@dataclass
class ConversionResult:
    """Outcome of :func:`convert`. Errors are measured on the held-out grid, in pixels and
    radians, over the samples the target represents.

    Attributes:
        camera: the target camera (None when the fit left the model's range).
        fit: the :class:`FitResult` of the final fit (``converged``, ``reason``, ``std``...).
        max_px, rms_px: largest and RMS pixel error (RMS of the distance, per sample).
        max_angle, rms_angle: largest and RMS angle between source and target rays, radians.
        unrepresentable: fraction of the held-out samples outside the target's domain.
        num_params: the target's free parameters.
        num_samples: fitted samples (after dropping the unrepresentable ones).
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
                "num_samples": self.num_samples,
                "params": dict(zip(self.fit.param_names, self.fit.params.tolist()))}


def sample_pixels(camera: Camera, grid: int, offset: float) -> tuple[Tensor, Tensor]:
    """``grid x grid`` pixels spread over the image at ``(i + offset) / grid`` of each side,
    kept where ``camera`` unprojects them: ``(pixels (K, 2), rays (K, 3))`` in float64."""
    h, w = camera.image_size
    steps = (torch.arange(grid, dtype=torch.float64) + offset) / grid
    v, u = torch.meshgrid(steps * h - 0.5, steps * w - 0.5, indexing="ij")
    pixels = torch.stack((u, v), -1).reshape(-1, 2)
    double = Camera(camera.model, camera.params.detach().double(), camera.image_size,
                    fov=camera.fov, blind_fov=camera.blind_fov)
    rays, valid = double.unproject(pixels)
    return pixels[valid], rays[valid]


def _source_center(camera: Camera) -> tuple[Tensor, Tensor]:
    """Centre ``(2,)`` and the sensor-to-image affine ``(2, 2)`` of the source."""
    p = camera.params.detach().double()
    if camera.model.name == "scaramuzza":
        cx, cy, c, d, e = p[:5].tolist()
        return p[:2], torch.tensor([[1.0, e], [d, c]], dtype=torch.float64)
    return p[2:4], torch.eye(2, dtype=torch.float64)


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
        sol = torch.linalg.lstsq(cols, -g[:, None]).solution[:, 0]
        poly = torch.zeros(degree + 1, dtype=torch.float64)
        for j, i in enumerate(powers):
            poly[i] = sol[j] * s ** (1 - i)
        return torch.cat((center, affine[1, 1:], affine[1, :1], affine[0, 1:], poly))
    unit = torch.tensor([1.0, 1.0, 0.0, 0.0, *DEFAULT_DISTORTION.get(target.name, ())],
                        dtype=torch.float64)
    theta = torch.atan2(rxy, rays[:, 2])
    limit = min(math.radians(60), 0.9 * float(target.max_angle(unit)))
    use = off_axis & (theta > math.radians(2)) & (theta < limit)
    if not bool(use.any()):
        raise ValueError("camera: no valid sample between 2 and 60 degrees off the axis to start "
                         "the conversion from")
    unit_px, _ = target.project(rays[use], unit)
    ratio = (pixels[use] - center).norm(dim=-1) / unit_px.norm(dim=-1)
    focal = float(ratio.median())
    return torch.cat((torch.tensor([focal, focal], dtype=torch.float64), center, unit[4:]))


def convert(camera: Camera, to_model: str | CameraModel, *, degree: int = 4, grid: int = 48,
            init=None, freeze: Sequence[str] | None = None, max_iterations: int = 200,
            progress: bool | None = False) -> ConversionResult:
    """Fit a camera of ``to_model`` to ``camera`` over its whole valid area (module docstring).

    Args:
        camera: the source: one camera of any model (its ``fov`` limits the area).
        to_model: the target model name (not ``equirectangular``).
        degree: polynomial degree of a ``scaramuzza`` target.
        grid: samples per image side of the fitted grid (and of the held-out grid).
        init: starting target parameters ``(P,)`` (default: module docstring).
        freeze: groups or names held at their start (default ``CONVERT_FREEZE``).
        max_iterations: Levenberg-Marquardt iterations per fit.
        progress: show a tqdm bar (``None``: when stderr is a terminal).

    Returns:
        A :class:`ConversionResult`; check ``converged``.

    Raises:
        ValueError, TypeError: not one camera, unknown model, too few valid samples.
    """
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected an ot.Camera, got {type(camera).__name__}")
    if camera.batch_shape != ():
        raise ValueError(f"camera: expected one camera, got a batch of shape "
                         f"{tuple(camera.batch_shape)}")
    target = get_model(to_model)
    if target.name == "equirectangular":
        raise ValueError("to_model: equirectangular is a panorama projection, not a lens model")
    if isinstance(degree, bool) or not isinstance(degree, int) or degree < 1:
        raise ValueError(f"degree: expected an integer >= 1, got {degree!r}")
    if isinstance(grid, bool) or not isinstance(grid, int) or grid < 4:
        raise ValueError(f"grid: expected an integer >= 4, got {grid!r}")
    pixels, rays = sample_pixels(camera, grid, 0.25)
    held_pixels, held_rays = sample_pixels(camera, grid, 0.75)
    if init is None:
        params0 = _initial_params(target, camera, degree, pixels, rays)
    else:
        params0 = torch.as_tensor(init, dtype=torch.float64).reshape(-1)
        target.validate_params(params0, "init")
    names = target.names_for(params0.shape[-1])
    frozen = frozen_indices(target, names, CONVERT_FREEZE.get(target.name, ()) if freeze is None
                            else freeze)
    if 2 * len(pixels) <= params0.shape[-1] - len(frozen):
        raise ValueError(f"camera: only {len(pixels)} valid samples; raise grid")

    def run(start: Tensor, keep: Tensor, held: list[int]) -> FitResult:
        intrinsics = IntrinsicsMap(target, start, camera.image_size, held)
        problem = Problem(intrinsics, rays[keep], pixels[keep],
                          torch.zeros(int(keep.sum()), dtype=torch.long),
                          torch.zeros(0, 6, dtype=torch.float64))
        return solve(problem, "lm", loss="linear", loss_scale=1.0,
                     max_iterations=max_iterations, optimality_tol=1e-6, max_condition=1e12,
                     max_std=1.0, progress=progress, sizes=[int(keep.sum())],
                     image_size=camera.image_size)

    keep = torch.ones(len(pixels), dtype=torch.bool)
    staged = [i for i in frozen_indices(target, names, STAGED.get(target.name, ()))
              if i not in frozen]
    if staged:
        first = run(params0, keep, frozen + staged)
        params0 = first.params if first.camera is not None else params0
    result = run(params0, keep, frozen)
    if result.num_invalid and result.camera is not None:
        keep = target.project(rays, result.params)[1]
        result = run(result.params, keep, frozen)

    out = result.camera
    nan = math.nan
    if out is None:
        return ConversionResult(None, result, nan, nan, nan, nan, nan,
                                len(result.free_names), int(keep.sum()))
    projected, ok_p = target.project(held_rays, result.params)
    back, ok_u = target.unproject(held_pixels, result.params)
    ok = ok_p & ok_u
    px = (projected - held_pixels).norm(dim=-1)[ok]
    cross = torch.linalg.cross(back, held_rays).norm(dim=-1)
    angle = torch.atan2(cross, (back * held_rays).sum(-1))[ok]
    if not bool(ok.any()):
        return ConversionResult(out, result, nan, nan, nan, nan, 1.0, len(result.free_names),
                                int(keep.sum()))
    return ConversionResult(
        out, result, max_px=float(px.max()), rms_px=float(torch.sqrt((px * px).mean())),
        max_angle=float(angle.max()), rms_angle=float(torch.sqrt((angle * angle).mean())),
        unrepresentable=float(1 - ok.double().mean()), num_params=len(result.free_names),
        num_samples=int(keep.sum()))
