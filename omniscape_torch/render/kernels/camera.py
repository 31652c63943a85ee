"""Cameras straight to the atlas grid: pixel centres -> rays -> rotated grid in one kernel.

For per-sample random cameras (``augment.RandomOmniCamera``) building the rays and the grid
eagerly costs more than sampling the images; `camera_grid` runs the whole chain as one
loop. On the CPU, the radially symmetric models (`RADIAL`) go through the C++ op
``torch.ops.omniscape_torch.camera_grid`` (built with the fast sampler, `extension`):
per camera a table of the ray against the distance from the principal point, made from the
model's own unprojection (so the iterative inverses of Kannala-Brandt, Scaramuzza and
distorted unified cost a few thousand Newton solves per camera, not one per pixel), read with
linear interpolation. Nothing compiles at run time, so it is as fast in ``DataLoader`` workers as
in the main process and the same for every mix of models. Elsewhere (another device, or no C++
compiler) the closed-form models compile whole with ``torch.compile``
(`omniscape_torch.cubemap.grid.compiled_kernel`, the grid maths of
`rotated_grid_xy`).
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from ...cameras import Camera
from ...cameras.camera import _check_image_size
from ...cameras.radial import (kannala_brandt_angles, kannala_brandt_tabulate,
                               kannala_brandt_unproject_table_xyz)
from ...cameras.registry import MODELS, get_model
from ...cameras.unified import unified_unproject_undistorted_xyz
from ...cubemap.faces import _check_face_size, _check_pad
from ...cubemap.grid import compiled_kernel, fail, rotated_grid_xy, rotated_rays_to_grid
from . import image as fast
from ._backend import choose

__all__ = ["camera_grid", "camera_rays", "radial_table", "RADIAL", "RADIAL_ENTRIES"]


#: The unprojections compiled whole into the camera kernel: those of the cameras
#: ``augment.RandomOmniCamera`` draws (``unified`` only without lens distortion), closed form,
#: or for ``kannala_brandt`` through a radius -> angle table per camera (``_TABULATED``: the
#: table is built first and passed with the parameters). The others unproject eagerly (the
#: Newton inverses of scaramuzza and distorted unified have data-dependent loops); each entry
#: costs a compilation (~5-10 s) in the tests.
_CLOSED_FORM: dict[str, Callable] = {
    **{name: get_model(name).unproject_xyz
       for name in ("equidistant", "equisolid", "stereographic")},
    "unified": unified_unproject_undistorted_xyz,
    "kannala_brandt": kannala_brandt_unproject_table_xyz,
}
#: Models whose kernel takes its parameters with a table: ``(params (B, P), (H, W)) -> (B, P')``.
_TABULATED: dict[str, Callable] = {"kannala_brandt": kannala_brandt_tabulate}

#: The radially symmetric models: the ray of a pixel depends on its distance from the principal
#: point in normalised coordinates (``(u - cx) / fx, (v - cy) / fy``; scaramuzza: through its
#: affine map; woodscape: ``(u - cx, (v - cy) / aspect_ratio)``, pixels) alone, so one table per
#: camera holds every pixel's ray (``CameraModel.radial``). ``unified`` only without tangential
#: distortion (``p1 = p2 = 0``).
RADIAL = tuple(name for name, model in MODELS.items() if model.radial)
#: Entries of a table of `radial_table` (``tests/test_camera_grid.py`` bounds the error
#: of linear interpolation between them).
RADIAL_ENTRIES = 2048
_SEARCH = 1024   # radii per round of the search for the end of a domain


def _affine(model: str, params: Tensor) -> Tensor:
    """``(B, 6)``: the principal point and the row-major 2 x 2 map ``M`` from pixel offsets to
    the normalised coordinates the model's rays are radially symmetric in."""
    if model == "scaramuzza":
        cx, cy, c, d, e = params[:, :5].unbind(-1)
        det = c - d * e   # scaramuzza_unproject: pu = (c du - e dv) / det, pv = (dv - d du) / det
        return torch.stack((cx, cy, c / det, -e / det, -d / det, 1 / det), -1)
    if model == "woodscape":   # u = cx + rho x / chi, v = cy + aspect_ratio rho y / chi
        cx, cy, aspect = params[:, :3].unbind(-1)
        zero = torch.zeros_like(cx)
        return torch.stack((cx, cy, torch.ones_like(cx), zero, zero, 1 / aspect), -1)
    fx, fy, cx, cy = params[:, :4].unbind(-1)
    zero = torch.zeros_like(fx)
    # the optional skew s (u = fx mx + s my + cx): mx = (du - s dv / fy) / fx
    skew = params[:, -1] if params.shape[-1] > get_model(model).num_params else zero
    return torch.stack((cx, cy, 1 / fx, -skew / (fx * fy), zero, 1 / fy), -1)


def radial_table(model: str, params: Tensor, image_size: tuple[int, int],
                 entries: int = RADIAL_ENTRIES, *, reach: float | None = None
                 ) -> tuple[Tensor, Tensor, Tensor] | None:
    """The per-camera tables of ``torch.ops.omniscape_torch.camera_grid``, in float64, or None
    where a camera's rays are not a function of the radius alone (tangential distortion) or its
    domain is not a disc about the principal point.

    A pixel ``(u, v)`` is at ``m = M (u - cx, v - cy)`` (``affine (B, 6)``: ``cx, cy`` and
    ``M`` row-major), radius ``rho = |m|``; its unit ray is ``(S(rho) m, C(rho))``. ``table
    (B, 2, K)`` holds ``S = sin(theta) / rho`` and ``C = cos(theta)`` from the model's own
    ``unproject`` of points on the ``+x`` axis of ``m``, out to the farthest image corner or
    to the end of the model's domain, whichever comes first (the end by the model's own rule,
    ``CameraModel.domain_end``, else searched on its validity to float64 rounding). Without an end the
    entries are evenly spaced in ``rho``; with one (a fold: there ``theta(rho)`` has a
    square-root singularity, so even spacing would leave angle errors of a texel in the last
    cells) they are evenly spaced in ``w = sqrt(root^2 - rho)``, in which ``theta`` is smooth,
    ``root^2`` the last valid radius. ``limits (B, 5)``: ``scale`` (entries per unit of
    ``rho`` or ``w``), ``root`` (0 for even spacing in ``rho``), ``end`` (``inf`` without one),
    and ``cos(fov / 2) = -2``, ``cos(blind_fov / 2) = 2`` (no cones: `camera_grid` sets
    them). ``reach``: tabulate out to this normalised radius instead of the image's farthest
    corner (``image_size`` unused; the pixels beyond read the last entry: a caller that reads
    such pixels bounds them with ``end``).
    """
    unproject = get_model(model).unproject
    if model not in RADIAL or (model == "unified" and bool(params[:, 7:9].ne(0).any())):
        return None
    p = params.detach().to("cpu", torch.float64)
    batch = p.shape[0]
    affine = _affine(model, p)
    h, w = image_size
    corners = torch.tensor([[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0], [w - 1.0, h - 1.0]],
                           dtype=torch.float64)
    m = affine[:, 2:].view(batch, 1, 2, 2)
    offsets = corners[None] - affine[:, None, :2]                          # (B, 4, 2)
    if reach is None:
        reach = torch.linalg.vector_norm((m @ offsets[..., None])[..., 0], dim=-1).amax(-1)
        reach = reach.clamp_min(1e-12)
    else:
        reach = torch.full((batch,), float(reach), dtype=torch.float64)
    at = (affine, _x_step(m[:, 0]), p)
    # where the domain ends within the reach: the first invalid of an even sampling, then the
    # same between it and the valid point before it, to float64 rounding (an unprojection call
    # per round: for the Newton inverses the calls, not the points, cost)
    lo, hi = torch.zeros_like(reach), reach
    ends = torch.zeros(batch, dtype=torch.bool)
    known = get_model(model).domain_end
    if known is not None:   # the model's own rule (the Newton inverses cost ~10-30 ms a call)
        end = known(p)
        ends = end < reach
        lo = torch.where(ends, end * (1 - 1e-12), reach)
        hi = torch.where(ends, end, reach)
    for round in range(0 if known is not None else 8):
        fractions = torch.linspace(0, 1, _SEARCH, dtype=torch.float64)
        rho = lo[:, None] + fractions * (hi - lo)[:, None]
        valid = _on_axis(unproject, *at, rho)[1]
        first = torch.where(valid.all(-1), _SEARCH, (~valid).int().argmax(-1))   # (B,)
        if round == 0:
            if bool((first == 0).any()) or bool(
                    (valid & (torch.arange(_SEARCH) > first[:, None])).any()):
                return None   # invalid at the axis, or valid again past the end: not a disc
            ends = first < _SEARCH
            if not bool(ends.any()):
                break
        cut = ends & (first < _SEARCH)
        lo = torch.where(cut, rho.gather(1, (first - 1).clamp_min(0)[:, None])[:, 0], lo)
        hi = torch.where(cut, rho.gather(1, first.clamp_max(_SEARCH - 1)[:, None])[:, 0], hi)
        if bool((hi - lo <= 4 * torch.finfo(torch.float64).eps * hi).all()):
            break
    end = torch.where(ends, hi, torch.inf)
    root = torch.where(ends, lo.sqrt(), 0.0)
    steps = torch.linspace(0, 1, entries - 1, dtype=torch.float64)
    rho = torch.where(ends[:, None], lo[:, None] - (root[:, None] * (1 - steps)) ** 2,
                      reach[:, None] * steps)
    rho = torch.cat((rho, rho[:, -1:]), -1)    # entry K - 1 repeats K - 2: t = 0 there
    rho[:, 0] = 1e-6 * rho[:, 1]               # S at the axis: its limit
    if model == "kannala_brandt":   # its inverse by a forward sweep: no Newton per entry
        theta = kannala_brandt_angles(p, rho)
        table = torch.stack((torch.sin(theta) / rho, torch.cos(theta)), 1)
    else:
        rays = _on_axis(unproject, *at, rho)[0]
        table = torch.stack((rays[..., 0] / rho, rays[..., 2]), 1)   # (B, 2, K)
    scale = (entries - 2) / torch.where(ends, root, reach)
    limits = torch.stack((scale, root, end, torch.full_like(end, -2.0),
                          torch.full_like(end, 2.0)), -1)
    return affine, limits, table


def _x_step(m: Tensor) -> Tensor:
    """``(E, 2)``: the pixel offset of a unit step along the ``+x`` axis of the normalised
    coordinates ``m = M (u - cx, v - cy)``, the first column of ``M^-1`` for ``M (E, 2, 2)``.
    An upper-triangular ``M`` (every model but Scaramuzza's: its rows are ``1 / fx`` and a
    skew, then ``1 / fy``) gives ``(1 / M00, 0)``, the very numbers LAPACK's inverse gives, without
    its call (0.1 ms of a one-camera table)."""
    if bool((m[:, 1, 0] == 0).all()):
        return torch.stack((1 / m[:, 0, 0], torch.zeros_like(m[:, 0, 0])), -1)
    return torch.linalg.inv(m)[:, :, 0]


def _on_axis(unproject: Callable, affine: Tensor, step: Tensor, params: Tensor, rho: Tensor
             ) -> tuple[Tensor, Tensor]:
    """The model's rays ``(E, N, 3)`` and validity ``(E, N)`` at radii ``rho (E, N)`` on the
    ``+x`` axis of each camera's normalised coordinates (``step``: `_x_step`)."""
    pixels = affine[:, None, :2] + rho[..., None] * step[:, None]
    return unproject(pixels, params[:, None])


def _camera_grid_math(params: Tensor, rotation: Tensor, cone: Tensor, face_size, pad, height,
                      width, dtype: torch.dtype, unproject_xyz: Callable, to_grid_xy: Callable
                      ) -> tuple[Tensor, Tensor]:
    """``params (B, P)``, ``rotation (B, 3, 3)``, ``cone (B, 2)`` (cosines of the half fov
    and of the half blind fov) -> ``grid (B, H, W, 2)`` (invalid pixels at (-2, -2)) and
    ``valid (B, H, W)``: the operations of ``Camera.ray_grid`` and `rotated_rays_to_grid`;
    the cones of ``Camera.within_fov`` (``theta <= fov / 2``, ``theta > blind_fov / 2``) as
    ``z >= cos(fov / 2)``, ``z < cos(blind_fov / 2)`` on the unit rays (no ``atan2``: a third
    of the kernel's time). Ray and grid components stay apart until the end: compiled, the
    whole chain is one loop that writes nothing but the grid and the mask."""
    kw = dict(dtype=params.dtype, device=params.device)
    u = torch.arange(width, **kw).view(1, 1, width)
    v = torch.arange(height, **kw).view(1, height, 1)
    x, y, z, valid = unproject_xyz(u, v, params[:, None, None])
    valid = valid & (z >= cone[:, None, None, 0]) & (z < cone[:, None, None, 1])
    gx, gy = to_grid_xy(x, y, z, rotation, face_size, pad, dtype)
    return torch.stack((torch.where(valid, gx, -2.0), torch.where(valid, gy, -2.0)), -1), valid


def _camera_kernel(model: str) -> Callable:
    unproject_xyz = _CLOSED_FORM[model]

    def camera_grid_kernel(params, rotation, cone, face_size, pad, height, width, dtype):
        return _camera_grid_math(params, rotation, cone, face_size, pad, height, width, dtype,
                                 unproject_xyz, rotated_grid_xy)

    return camera_grid_kernel


def camera_grid(model: str, params: Tensor, image_size: tuple[int, int], face_size: int,
                pad: int, *, rotation: Tensor | None = None, fov: Tensor | None = None,
                blind_fov: Tensor | None = None, dtype: torch.dtype | None = None,
                compiled: bool = True, lazy: bool = False, backend: str = "auto"
                ) -> tuple[Tensor, Tensor] | fast.CameraGrid:
    """Atlas grid of every pixel centre of ``B`` cameras of one model, each with its own
    rotation and field-of-view cone: the whole chain in one compiled kernel, without gradient.

    The same result as ``Camera(model, params, image_size, fov=..., blind_fov=...).ray_grid()``
    followed by `rotated_rays_to_grid` and moving the invalid pixels to (-2, -2) (outside
    the atlas, so that ``grid_sample`` with zero padding reads 0 there), to float32 rounding;
    for per-sample random cameras (``augment.RandomOmniCamera``), where building the rays and
    the grid eagerly costs more than sampling the images. On the CPU (float32 or float64 grids,
    the fast sampler built) the models of `RADIAL` go through their tables
    (`radial_table`, within 0.005 texel of the exact chain at 1024 px), one C++ pass,
    nothing compiled at run time. Elsewhere the models of ``_CLOSED_FORM`` compile whole (a
    kernel per model, dtypes and device type, any shapes); the others unproject eagerly and go
    through the compiled `rotated_rays_to_grid`. A compilation failure is warned about
    once and the eager path used from then on, as there.

    Forward only: the result carries no gradient to ``params`` or ``rotation`` (for learnable
    intrinsics use `OmniProjection`, whose grid is differentiable);
    images sampled with it still pass gradients to the cubemap.

    Args:
        model: a registered camera model name.
        params: ``(B, P)`` parameters, one row per camera (``P`` of ``model``).
        image_size: ``(H, W)``.
        face_size: ``F``, texels per cube face side.
        pad: atlas border ``p``.
        rotation: ``(B, 3, 3)`` camera -> cube frame, or None (identity).
        fov: ``(B,)`` full field of view per camera (radians), or None (the model's domain).
        blind_fov: ``(B,)`` full angle of a central blind cone per camera (0: none), or None.
        dtype: floating dtype of the grid (default: that of ``params``).
        compiled: False runs the exact chain eagerly (no table, no compiled kernel).
        lazy: where the cameras go through their tables, return them as a
            `CameraGrid` (its ``valid`` computed, the grid
            not built: the fast sampler computes it inside its sampling pass,
            ``OmniProjection.render(grid=...)`` takes it); elsewhere the tuple below all the
            same.
        backend: the tables and the C++ op (``"cpp"``; float32 or float64 grids of a model of
            `RADIAL`), or the torch kernels (``"torch"``), or the C++ op where it runs
            (``"auto"``).

    Returns:
        ``grid (B, H, W, 2)`` in ``dtype`` and ``valid (B, H, W)`` bool (or, ``lazy``, a
        ``CameraGrid``).
    """
    unproject = get_model(model).unproject  # raises for an unknown name
    if not isinstance(params, Tensor) or not params.is_floating_point() or params.dim() != 2:
        raise ValueError(f"params: expected a floating tensor (B, P), got "
                         f"{getattr(params, 'shape', type(params).__name__)}")
    batch = params.shape[0]
    kw = dict(dtype=params.dtype, device=params.device)
    h, w = _check_image_size(image_size)
    _check_face_size(face_size)
    _check_pad(pad)
    dtype = params.dtype if dtype is None else dtype
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise TypeError(f"dtype: expected a floating torch.dtype, got {dtype!r}")
    if rotation is None:
        rotation = torch.eye(3, **kw).expand(batch, 3, 3)
    elif not isinstance(rotation, Tensor) or rotation.shape != (batch, 3, 3):
        raise ValueError(f"rotation: expected a tensor ({batch}, 3, 3), got "
                         f"{getattr(rotation, 'shape', type(rotation).__name__)}")
    cone = []   # cosines of the half angles, in float64; beyond [-1, 1] where there is none
    for name, angle, default in (("fov", fov, -2.0), ("blind_fov", blind_fov, 2.0)):
        if angle is None:
            cone.append(torch.full((batch,), default, dtype=torch.float64))
        elif not isinstance(angle, Tensor) or angle.shape != (batch,):
            raise ValueError(f"{name}: expected a tensor ({batch},) of angles, got "
                             f"{getattr(angle, 'shape', type(angle).__name__)}")
        else:   # a blind cone of angle 0 is empty (the axis pixel stays valid)
            cosine = torch.cos(0.5 * angle.detach().to("cpu", torch.float64))
            cone.append(cosine if name == "fov" else torch.where(angle.cpu() > 0, cosine, 2.0))
    cones = torch.stack(cone, -1)
    args = (params.detach(), rotation.detach().to(**kw), cones.to(**kw),
            face_size, pad, h, w, dtype)
    if model == "unified" and bool(params[:, 5:].ne(0).any()):
        fused = None   # lens distortion: Newton undistortion, eagerly
    else:
        fused = _CLOSED_FORM.get(model)
    tables = None
    if compiled and dtype in (torch.float32, torch.float64) and choose(
            backend, params.detach(), what="camera_grid") is not None:
        tables = radial_table(model, params, (h, w))
    if tables is not None:
        affine, limits, table = tables
        limits[:, 3:] = cones
        make = fast.CameraGrid if lazy else fast.camera_grid
        return make(affine, limits, table, rotation.detach(), face_size, pad, (h, w), dtype)
    with torch.no_grad():
        if compiled and fused is not None:
            key = ("camera", model, params.dtype, dtype, params.device.type, True)
            kernel = compiled_kernel(key, _camera_kernel(model), stacklevel=2)
            if kernel is not None:
                tabulate = _TABULATED.get(model)
                try:
                    if tabulate is None:
                        return kernel(*args)
                    return kernel(tabulate(args[0], (h, w)), *args[1:])
                except torch.OutOfMemoryError:
                    raise
                except Exception as exc:
                    fail(key, exc, stacklevel=2)

        def unproject_xyz(u, v, p):   # any model, through its own unproject
            rays, ok = unproject(torch.stack(torch.broadcast_tensors(u, v), -1), p)
            return (*rays.unbind(-1), ok)

        def to_grid_xy(x, y, z, rot, f, p, dt):
            rays = torch.stack((x, y, z), -1)
            return rotated_rays_to_grid(rays, rot, f, p, dtype=dt, compiled=compiled).unbind(-1)

        return _camera_grid_math(*args, unproject_xyz, to_grid_xy)


def camera_rays(model: str, params: Tensor, image_size: tuple[int, int], *,
                fov: Tensor | None = None, dtype: torch.dtype | None = None,
                backend: str = "auto") -> tuple[Tensor, Tensor]:
    """Unit rays ``(B, H, W, 3)`` and validity ``(B, H, W)`` of every pixel centre of ``B``
    cameras of one model, each within its own field of view ``fov (B,)`` (radians; None: the
    model's domain), without gradient: on the CPU through the cameras' tables
    (`radial_table`, the C++ op ``camera_rays``; as `camera_grid` reads them),
    elsewhere (another device, no table, no fast sampler) ``Camera.ray_grid`` and the cones
    ``z >= cos(fov / 2)``.

    Args:
        model: a registered camera model name.
        params: ``(B, P)`` parameters, one row per camera.
        image_size: ``(H, W)``.
        fov: ``(B,)`` full fields of view, or None.
        dtype: floating dtype of the rays (default: that of ``params``).
        backend: the tables and the C++ op, or ``Camera.ray_grid`` (``_backend``).
    """
    if not isinstance(params, Tensor) or not params.is_floating_point() or params.dim() != 2:
        raise ValueError(f"params: expected a floating tensor (B, P), got "
                         f"{getattr(params, 'shape', type(params).__name__)}")
    dtype = params.dtype if dtype is None else dtype
    h, w = image_size
    batch = params.shape[0]
    if fov is not None and (not isinstance(fov, Tensor) or fov.shape != (batch,)):
        raise ValueError(f"fov: expected a tensor ({batch},) of angles, got "
                         f"{getattr(fov, 'shape', type(fov).__name__)}")
    cosine = (torch.full((batch,), -2.0, dtype=torch.float64) if fov is None
              else torch.cos(0.5 * fov.detach().to("cpu", torch.float64)))
    with torch.no_grad():
        tables = (radial_table(model, params, (h, w)) if dtype in (torch.float32, torch.float64)
                  and choose(backend, params.detach(), what="camera_rays") is not None else None)
        if tables is not None:
            affine, limits, table = tables
            limits[:, 3] = cosine
            return fast.camera_rays(affine, limits, table, (h, w), dtype)
        rays, valid = Camera(model, params.detach(), (h, w)).ray_grid()
        if rays.dim() == 3:
            rays, valid = rays.unsqueeze(0), valid.unsqueeze(0)
        rays = rays.to(dtype)
        valid = valid & (rays[..., 2] >= cosine.to(rays)[:, None, None])
        return rays, valid
