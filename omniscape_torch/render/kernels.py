"""Cameras straight to the atlas grid: pixel centres -> rays -> rotated grid in one kernel.

For per-sample random cameras (``augment.RandomOmniCamera``) building the rays and the grid
eagerly costs more than sampling the images; :func:`camera_grid` runs the whole chain as one
compiled loop (``torch.compile`` through :func:`omniscape_torch.cubemap.grid.compiled_kernel`, the
grid maths of :func:`~omniscape_torch.cubemap.grid.rotated_grid_xy`).
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from ..cameras.radial import kannala_brandt_tabulate, kannala_brandt_unproject_table_xyz
from ..cameras.registry import get_model
from ..cameras.unified import unified_unproject_undistorted_xyz
from ..cubemap.faces import _check_face_size, _check_pad
from ..cubemap.grid import compiled_kernel, fail, rotated_grid_xy, rotated_rays_to_grid

__all__ = ["camera_grid"]


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


def _camera_grid_math(params: Tensor, rotation: Tensor, cone: Tensor, face_size, pad, height,
                      width, dtype: torch.dtype, unproject_xyz: Callable, to_grid_xy: Callable
                      ) -> tuple[Tensor, Tensor]:
    """``params (B, P)``, ``rotation (B, 3, 3)``, ``cone (B, 2)`` (cosines of the half fov
    and of the half blind fov) -> ``grid (B, H, W, 2)`` (invalid pixels at (-2, -2)) and
    ``valid (B, H, W)``: the operations of ``Camera.ray_grid`` and :func:`rotated_rays_to_grid`;
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
                compiled: bool = True) -> tuple[Tensor, Tensor]:
    """Atlas grid of every pixel centre of ``B`` cameras of one model, each with its own
    rotation and field-of-view cone: the whole chain in one compiled kernel, without gradient.

    The same result as ``Camera(model, params, image_size, fov=..., blind_fov=...).ray_grid()``
    followed by :func:`rotated_rays_to_grid` and moving the invalid pixels to (-2, -2) (outside
    the atlas, so that ``grid_sample`` with zero padding reads 0 there), to float32 rounding;
    for per-sample random cameras (``augment.RandomOmniCamera``), where building the rays and
    the grid eagerly costs more than sampling the images. The models of ``_CLOSED_FORM``
    compile whole (a kernel per model, dtypes and device type, any shapes); the others
    unproject eagerly and go through the compiled :func:`rotated_rays_to_grid`. A compilation
    failure is warned about once and the eager path used from then on, as there.

    Forward only: the result carries no gradient to ``params`` or ``rotation`` (for learnable
    intrinsics use :class:`~omniscape_torch.OmniProjection`, whose grid is differentiable);
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
        compiled: False runs the same maths eagerly.

    Returns:
        ``grid (B, H, W, 2)`` in ``dtype`` and ``valid (B, H, W)`` bool.
    """
    unproject = get_model(model).unproject  # raises for an unknown name
    if not isinstance(params, Tensor) or not params.is_floating_point() or params.dim() != 2:
        raise ValueError(f"params: expected a floating tensor (B, P), got "
                         f"{getattr(params, 'shape', type(params).__name__)}")
    batch = params.shape[0]
    kw = dict(dtype=params.dtype, device=params.device)
    try:
        h, w = (int(s) for s in image_size)
    except (TypeError, ValueError):
        raise ValueError(f"image_size: expected (H, W), got {image_size!r}") from None
    if min(h, w) < 1:
        raise ValueError(f"image_size: expected positive sizes, got {(h, w)}")
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
    args = (params.detach(), rotation.detach().to(**kw), torch.stack(cone, -1).to(**kw),
            face_size, pad, h, w, dtype)
    if model == "unified" and bool(params[:, 5:].ne(0).any()):
        fused = None   # lens distortion: Newton undistortion, eagerly
    else:
        fused = _CLOSED_FORM.get(model)
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
