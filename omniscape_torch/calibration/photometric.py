"""Photometric calibration: fit a camera's intrinsics (and attitude) so that the projection
layer's rendering of a cubemap matches a target omnidirectional image.

    z (focal, centre, attitude) --> params, R --> OmniProjection(cubemap) --> image
        loss(image, target) over the target's valid area --> Adam on z, coarse to fine

This is calibration by gradient descent through the layer (``DESIGN.md``): the gradients reach
the intrinsics through the ray grid and ``grid_sample``. It needs a cubemap of the place where the
target was taken (a simulator's, or the built-in scene's) and recovers the focal lengths and the
principal point of a model whose parameters start with ``fx, fy, cx, cy`` (every registered model
but ``scaramuzza``); the other parameters (distortion, mirror ``xi``) are held at their values.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import Tensor

from ..cameras import Camera
from ..cameras._checks import check_one_camera
from ..cubemap import check_cubemap
from ..render.layer import OmniProjection

__all__ = ["PHOTOMETRIC_LOSSES", "PhotometricResult", "fit_photometric", "photometric_error"]

#: Loss choices of `fit_photometric`.
PHOTOMETRIC_LOSSES = ("charbonnier", "l2", "zncc")
#: Width of the Charbonnier loss, in intensity units (images in [0, 1]).
CHARBONNIER_EPS = 0.01
#: Steps per window of the stationarity test: the last window's mean parameters are the result.
STATIONARY_WINDOW = 10


@dataclass
class PhotometricResult:
    """Outcome of `fit_photometric`.

    Attributes:
        camera: the fitted camera (fixed, not learnable), with ``camera_init``'s model, image size,
            ``fov`` and ``blind_fov``.
        rotation: ``(3, 3)`` fitted camera-to-cube rotation (the initial one when the attitude is
            not fitted).
        loss: the loss at every step, coarsest level first.
        level_steps: the number of steps of each level, coarsest first (to split ``loss``).
        converged: True only when the final photometric error is at most ``error_tol``, the
            parameters drift by at most ``step_tol`` pixels, and the camera covers the compared
            area.
        reason: why ``converged`` is what it is, in words.
        error: final photometric error at full resolution (`photometric_error`).
        initial_error: the same for the initial guess.
        coverage: fraction of the compared pixels that the fitted camera sees.
        drift: largest difference between the mean parameters of the last two windows of
            ``STATIONARY_WINDOW`` steps, in full-resolution pixels (see ``_Parametrisation``).
    """

    camera: Camera
    rotation: Tensor
    loss: list[float] = field(repr=False)
    level_steps: list[int]
    converged: bool
    reason: str
    error: float
    initial_error: float
    coverage: float
    drift: float


def photometric_error(image: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """``1 - ZNCC`` between ``image`` and ``target`` over ``mask``, averaged over channels.

    Zero-mean normalised cross-correlation is invariant to gain and offset per channel, so the
    error is comparable across scenes and exposures: 0 for a perfect match, about 1 for unrelated
    images. A constant channel counts as uncorrelated.

    Args:
        image: ``(B, C, H, W)`` floating.
        target: ``(B, C, H, W)`` floating.
        mask: ``(B, 1, H, W)`` bool, the pixels compared.

    Returns:
        ``()`` tensor, differentiable with respect to ``image``.
    """
    w = mask.to(image.dtype)
    n = w.sum().clamp(min=1)
    dims = (0, 2, 3)
    mi = (image * w).sum(dims, keepdim=True) / n
    mt = (target * w).sum(dims, keepdim=True) / n
    a, b = (image - mi) * w, (target - mt) * w
    cov = (a * b).sum(dims)
    var = (a * a).sum(dims) * (b * b).sum(dims)
    # the small floor keeps a constant channel (zero variance) finite, with zero correlation
    zncc = cov / torch.sqrt(var + torch.finfo(image.dtype).tiny ** 0.5)
    return 1 - zncc.mean()


def _loss(image: Tensor, target: Tensor, mask: Tensor, kind: str) -> Tensor:
    if kind == "zncc":
        return photometric_error(image, target, mask)
    r = (image - target) * mask
    per_pixel = (r * r if kind == "l2"
                 else torch.sqrt(r * r + CHARBONNIER_EPS ** 2) - CHARBONNIER_EPS)
    return per_pixel.sum() / (mask.sum() * image.shape[1]).clamp(min=1)


def _skew(w: Tensor) -> Tensor:
    zero = torch.zeros_like(w[0])
    return torch.stack([torch.stack([zero, -w[2], w[1]]), torch.stack([w[2], zero, -w[0]]),
                        torch.stack([-w[1], w[0], zero])])


def _pool(t: Tensor, k: int) -> Tensor:
    return t if k == 1 else F.avg_pool2d(t, k)


def _pyramid_level(cube: Tensor, target: Tensor, mask: Tensor, k: int
                   ) -> tuple[Tensor, Tensor, Tensor]:
    """Cube, target and mask reduced ``k`` times: cube faces and target averaged over ``k x k``
    blocks (the target over its valid pixels only), mask kept where the whole block is valid."""
    b, _, c, f, _ = cube.shape
    cube_k = _pool(cube.reshape(b * 6, c, f, f), k).reshape(b, 6, c, f // k, f // k)
    w = mask.to(target.dtype)
    count = _pool(w, k)
    target_k = _pool(target * w, k) / count.clamp(min=1 / (k * k))
    return cube_k, target_k, count > 1 - 1e-6


class _Parametrisation:
    """``z`` (7 numbers, full-resolution pixels) -> camera params and rotation.

    ``z[0:2]``: ``log(fx / fx0) * r``, ``log(fy / fy0) * r`` with ``r = min(H, W) / 2``, so one unit
    moves a pixel at radius ``r`` by about one pixel; ``z[2:4]``: the principal point's offset in
    pixels; ``z[4:7]``: the attitude increment ``omega * f0`` (axis-angle in the camera frame,
    ``R = R0 expm([omega]x)``, ``f0`` the mean initial focal), one unit moving the image centre by
    about a pixel. In these units one Adam learning rate suits every parameter.
    """

    def __init__(self, params: Tensor, rotation: Tensor, image_size: tuple[int, int]):
        self.params0 = params
        self.rotation0 = rotation
        self.radius = min(image_size) / 2
        self.focal0 = float(params[:2].mean())

    def params(self, z: Tensor, scale: int) -> Tensor:
        """Params at a pyramid level ``scale`` times coarser: focal ``/ scale``, centre
        ``(c + 0.5) / scale - 0.5`` (pixel centres at integers), other parameters unchanged."""
        p0 = self.params0
        focal = p0[:2] * torch.exp(z[:2] / self.radius)
        centre = (p0[2:4] + z[2:4] + 0.5) / scale - 0.5
        return torch.cat([focal / scale, centre, p0[4:]])

    def rotation(self, z: Tensor) -> Tensor:
        return self.rotation0 @ torch.linalg.matrix_exp(_skew(z[4:7] / self.focal0))


def fit_photometric(cubemap: Tensor, target: Tensor, camera_init: Camera, *,
                    rotation: Tensor | None = None, fit_attitude: bool = False,
                    mask: Tensor | None = None, levels: int = 3, loss: str = "charbonnier",
                    steps: int = 40, lr: float = 0.5,
                    error_tol: float = 0.1, step_tol: float = 0.2,
                    progress: bool = True) -> PhotometricResult:
    """Fit the focal lengths, principal point and optionally the attitude of ``camera_init`` so
    that ``OmniProjection`` renders ``cubemap`` like ``target``.

    Design (the figures come from ``benchmarks/photometric_convergence.py``):

    * **Coarse to fine.** ``levels`` pyramid levels, the coarsest first; level ``l`` halves the
      image ``l`` times (the target averaged over its valid pixels) and the cube faces as well
      (2 x 2 averaging, the same blur as the target's), so a coarse level sees the scene at a
      matching resolution and its loss is smooth over a wider range of parameters. Each level
      starts from the previous level's result; level ``l`` runs ``steps * 2^l`` Adam steps: a
      coarse step costs ``4^l`` times less and the coarse levels do the long travel from a
      distant guess.
    * **Loss.** ``"charbonnier"`` (default): ``sqrt(r^2 + eps^2) - eps`` with ``eps = 0.01``, a
      smooth L1 that does not let the few aliased pixels of an exact ray cast (thin poles, lane
      markings) dominate the way ``"l2"`` does; ``"zncc"``: ``1 - ZNCC`` per channel
      (`photometric_error`), invariant to gain and offset, for a target with another
      exposure than the cube's. Measured (128 x 128 targets, faces of 64, guesses 20 % and
      15 px off): median final focal error 0.17 % / 0.07 % (fisheye / catadioptric) with
      Charbonnier, 0.36 % / 0.31 % with L2, 0.22 % / 0.17 % with ZNCC; L2 also ends
      jittering more (its fits fail the drift test).
    * **Valid area.** Pixels are compared over a fixed set, the target's valid area (``mask``)
      at each level, normalised by its size; the fitted camera renders without its ``fov`` limit
      so that it can cover that set, and where it cannot (the model's domain ends) it renders 0,
      which the loss penalises like any other mismatch (with zero gradient). A guess cannot
      lower its loss by shrinking the compared area, and the field-of-view edge of the target
      counts the same at every step.
    * **Parametrisation.** Log focal lengths, principal-point offset in pixels, attitude as an
      axis-angle increment in the camera frame, all scaled to about one full-resolution pixel of
      image motion per unit (see ``_Parametrisation``), so one learning rate fits all.
    * **Optimiser.** Adam: its steps are about ``lr`` whatever the scale of the gradient, which
      changes with the level and the loss; the loss is only piecewise smooth (bilinear sampling,
      the valid set), where the curvature model and line search of LBFGS are unreliable (a
      reason, not a measurement: LBFGS is not benchmarked). ``lr`` is in pixels of the current
      level (``lr * 2^l`` full-resolution pixels), decayed linearly to a tenth over each level.
    * **Result and convergence.** Adam ends jittering around the optimum by about its step, so
      the result is the mean of the last ``STATIONARY_WINDOW`` iterates, and ``drift``, its
      difference from the mean of the window before, says whether the parameters still move.
      Converged means: at full resolution ``error <= error_tol`` (``1 - ZNCC``; the default 0.1
      separates the built-in scene's fits from its wrong minima), ``drift <= step_tol``
      pixels, and the fitted camera covers at least 99 % of the compared pixels. Otherwise
      ``converged`` is False and ``reason`` says which test failed: a bad start is reported, not
      returned as a fit.

    Deterministic: no randomness.

    Args:
        cubemap: ``(1, 6, C, F, F)`` or ``(6, C, F, F)`` floating cubemap at the camera's position.
        target: ``(1, C, H, W)`` or ``(C, H, W)``, same dtype, ``(H, W)`` the camera's image size.
        camera_init: the initial guess, one camera of a model whose parameters start with
            ``fx, fy, cx, cy``.
        rotation: ``(3, 3)`` initial camera-to-cube rotation (default identity).
        fit_attitude: also fit the rotation.
        mask: ``(H, W)``, ``(1, H, W)`` or ``(1, 1, H, W)`` bool: the target's valid pixels
            (default all).
        levels: pyramid levels; ``H``, ``W`` and ``F`` must be divisible by ``2^(levels - 1)``.
        loss: one of `PHOTOMETRIC_LOSSES`.
        steps: Adam steps of the finest level (``steps * 2^l`` at level ``l``), at least
            ``2 * STATIONARY_WINDOW``.
        lr: Adam learning rate, in pixels of the current level.
        error_tol: largest final ``1 - ZNCC`` of a converged fit.
        step_tol: largest ``drift`` (full-resolution pixels) of a converged fit.
        progress: show a tqdm progress bar over all steps.

    Returns:
        A `PhotometricResult`.

    Raises:
        TypeError: a wrong type or dtype. ValueError: a wrong shape, size or option.

    Shapes:
        cubemap ``(1, 6, C, F, F)``; target ``(1, C, H, W)``; mask ``(1, 1, H, W)``.
    """
    cube, target, mask, rotation = _check_inputs(cubemap, target, camera_init, rotation, mask,
                                                 levels)
    if loss not in PHOTOMETRIC_LOSSES:
        raise ValueError(f"loss: expected one of {PHOTOMETRIC_LOSSES}, got {loss!r}")
    for name, value, lo in (("steps", steps, 2 * STATIONARY_WINDOW), ("levels", levels, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < lo:
            raise ValueError(f"{name}: expected an int >= {lo}, got {value!r}")
    for name, value in (("lr", lr), ("error_tol", error_tol), ("step_tol", step_tol)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
            raise ValueError(f"{name}: expected a positive number, got {value!r}")

    param = _Parametrisation(camera_init.params.detach(), rotation, camera_init.image_size)
    z = torch.zeros(7, dtype=param.params0.dtype, device=param.params0.device,
                    requires_grad=True)
    history: list[float] = []
    level_steps: list[int] = []
    path: list[Tensor] = []  # the iterates of the current level
    finite = True

    from tqdm import tqdm
    bar = tqdm(total=steps * (2 ** levels - 1), disable=not progress, file=sys.stderr,
               desc="photometric")
    for level in reversed(range(levels)):
        k = 2 ** level
        cube_k, target_k, mask_k = _pyramid_level(cube, target, mask, k)
        size_k = (target_k.shape[-2], target_k.shape[-1])
        project = _projector(camera_init, param.params(z.detach(), k), size_k, cube_k.shape[-1])
        base = lr * k
        opt = torch.optim.Adam([z], lr=base)
        path = []
        n = steps * k
        for i in range(n):
            for group in opt.param_groups:
                group["lr"] = base * (1 - 0.9 * i / (n - 1))
            image, _ = _render(project, cube_k, param, z, k, fit_attitude)
            value = _loss(image, target_k, mask_k, loss)
            finite = bool(torch.isfinite(value))
            if not finite:
                break
            opt.zero_grad()
            value.backward()
            opt.step()
            path.append(z.detach().clone())
            history.append(float(value.detach()))
            bar.update(1)
        level_steps.append(len(path))
        if not finite:
            break
    bar.close()

    w = STATIONARY_WINDOW
    if finite:
        # Adam jitters around the optimum by about its step: the mean of the last window is the
        # estimate, its difference from the window before measures the drift
        recent, previous = torch.stack(path[-w:]).mean(0), torch.stack(path[-2 * w:-w]).mean(0)
        z_final, drift = recent, float((recent - previous).abs().max())
    else:
        z_final, drift = z.detach(), math.inf
    initial_error, _ = _evaluate(camera_init, cube, target, mask, param, torch.zeros_like(z))
    error, coverage = _evaluate(camera_init, cube, target, mask, param, z_final)
    if not (finite and math.isfinite(error)):
        reason = f"the loss became non-finite after {len(history)} steps"
    elif error > error_tol:
        reason = f"photometric error 1 - ZNCC = {error:.3g} > error_tol = {error_tol}"
    elif drift > step_tol:
        reason = (f"not stationary: the mean parameters of the last two windows of {w} steps "
                  f"differ by {drift:.3g} px > step_tol = {step_tol}")
    elif coverage < 0.99:
        reason = f"the fitted camera sees only {coverage:.1%} of the compared pixels"
    else:
        reason = (f"converged: 1 - ZNCC = {error:.3g} (initially {initial_error:.3g}), drift "
                  f"{drift:.3g} px")
    camera = Camera(camera_init.model, param.params(z_final, 1), camera_init.image_size,
                    fov=camera_init.fov, blind_fov=camera_init.blind_fov)
    return PhotometricResult(camera=camera, rotation=param.rotation(z_final),
                             loss=history, level_steps=level_steps,
                             converged=reason.startswith("converged"), reason=reason,
                             error=error, initial_error=initial_error, coverage=coverage,
                             drift=drift)


def _projector(camera_init: Camera, params: Tensor, size: tuple[int, int],
               face_size: int) -> OmniProjection:
    """A layer for one pyramid level; the camera has no ``fov`` limit (see the valid area)."""
    camera = Camera(camera_init.model, params.detach(), size)
    return OmniProjection(camera, face_size, fused_grid=False)


def _render(project: OmniProjection, cube: Tensor, param: _Parametrisation, z: Tensor,
            scale: int, fit_attitude: bool) -> tuple[Tensor, Tensor]:
    """The layer's image and valid mask with the parameters of ``z`` (differentiable)."""
    rotation = param.rotation(z) if fit_attitude else param.rotation0
    params = param.params(z, scale).to(project.camera.params.dtype)
    return torch.func.functional_call(project, {"camera.params": params}, (cube,),
                                      {"rotation": rotation.to(cube.dtype)})


@torch.no_grad()
def _evaluate(camera_init: Camera, cube: Tensor, target: Tensor, mask: Tensor,
              param: _Parametrisation, z: Tensor) -> tuple[float, float]:
    """Full-resolution ``(1 - ZNCC, coverage)`` of the parameters ``z``. A fresh layer each
    time: without gradients the layer caches its rays under the address of the params tensor,
    which a later, different params tensor can reuse."""
    project = _projector(camera_init, param.params0, camera_init.image_size, cube.shape[-1])
    image, valid = _render(project, cube, param, z, 1, True)
    error = float(photometric_error(image, target, mask))
    coverage = float((valid & mask).sum() / mask.sum().clamp(min=1))
    return error, coverage


def _check_inputs(cubemap, target, camera, rotation, mask, levels):
    """Validate and normalise the inputs of `fit_photometric`."""
    check_one_camera(camera, "camera_init")
    if camera.param_names[:4] != ("fx", "fy", "cx", "cy"):
        raise ValueError(f"camera_init: the {camera.model.name!r} model's parameters do not "
                         f"start with fx, fy, cx, cy")
    if isinstance(cubemap, Tensor) and cubemap.dim() == 4:
        cubemap = cubemap.unsqueeze(0)
    cube = check_cubemap(cubemap, "cubemap")
    if cube.shape[0] != 1:
        raise ValueError(f"cubemap: expected one cubemap (1, 6, C, F, F), got "
                         f"{tuple(cube.shape)}")
    if not cube.is_floating_point():
        raise TypeError(f"cubemap: expected a floating-point tensor, got {cube.dtype}")
    if not isinstance(target, Tensor):
        raise TypeError(f"target: expected a tensor (1, C, H, W), got {type(target).__name__}")
    if target.dim() == 3:
        target = target.unsqueeze(0)
    h, w = camera.image_size
    c = cube.shape[2]
    if target.shape != (1, c, h, w):
        raise ValueError(f"target: expected shape (1, {c}, {h}, {w}) (the cube's channels, the "
                         f"camera's image size), got {tuple(target.shape)}")
    if target.dtype != cube.dtype:
        raise TypeError(f"target: expected the cubemap's dtype {cube.dtype}, got {target.dtype}")
    if target.device != cube.device or camera.params.device != cube.device:
        raise ValueError("target, camera_init: expected on the cubemap's device "
                         f"{cube.device}")
    if isinstance(levels, int) and not isinstance(levels, bool) and levels >= 1:
        k = 2 ** (levels - 1)
        if h % k or w % k or cube.shape[-1] % k:
            raise ValueError(f"levels: {levels} levels need H, W and F "
                             f"divisible by {k}, got H={h}, W={w}, F={cube.shape[-1]}")
    if rotation is None:
        rotation = torch.eye(3, dtype=camera.params.dtype, device=cube.device)
    elif not isinstance(rotation, Tensor) or not rotation.is_floating_point():
        raise TypeError(f"rotation: expected a floating-point (3, 3) tensor, got "
                        f"{getattr(rotation, 'dtype', type(rotation).__name__)}")
    elif rotation.shape != (3, 3):
        raise ValueError(f"rotation: expected shape (3, 3), got {tuple(rotation.shape)}")
    rotation = rotation.detach().to(camera.params.dtype)
    if mask is None:
        mask = torch.ones(1, 1, h, w, dtype=torch.bool, device=cube.device)
    elif not isinstance(mask, Tensor) or mask.dtype != torch.bool:
        raise TypeError(f"mask: expected a bool tensor, got "
                        f"{getattr(mask, 'dtype', type(mask).__name__)}")
    else:
        if mask.shape[-2:] != (h, w) or mask.numel() != h * w:
            raise ValueError(f"mask: expected shape ({h}, {w}), (1, {h}, {w}) or "
                             f"(1, 1, {h}, {w}), got {tuple(mask.shape)}")
        mask = mask.reshape(1, 1, h, w)
    if not bool(mask.any()):
        raise ValueError("mask: no valid pixel to compare")
    return cube, target, mask, rotation
