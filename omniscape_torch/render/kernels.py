"""Fused atlas grid of rotated rays: ``rays_to_grid(R @ rays)`` in one pass over the rays.

The eager path, ``cubemap.rays_to_grid(einsum(R, rays), F, pad)``, runs about 25 elementwise
ops, each one a full pass through memory over every ray (30 ms for 1M rays on 2 cores, more
than the bilinear sampling it serves); :func:`rotated_rays_to_grid` computes the same grid in
one fused loop (1.5 ms; ``benchmarks/bench_projection.py``):

    p = R ray                                       # rotation, 9 multiply-adds
    axis = dominant |p_i| (ties: x, then y, then z)  # the face's viewing axis a
    face = the face looking along (axis, sign p_axis); face 0 for the zero ray
    u = c + f (r . p) / |p_axis|,  v = c + f (b . p) / |p_axis|   # f = F / 2, c = (F - 1) / 2
    (gx, gy) = face_uv_to_grid(face, (u, v), F, pad)

written in plain elementwise torch with the face choice as ``torch.where`` over the signed axes
(the tables are derived from ``cubemap.faces``, which alone knows the face order), and compiled
with ``torch.compile`` (inductor) on first use. The operations and their order are those of
``ray_to_face`` and ``face_uv_to_grid``, so the grid is the eager one: bit for bit without a
rotation, and to float32 rounding of the rotated rays with one (``einsum`` may sum its three
products in another order). The face choice and its tie-breaking are the same.

Gradients: a ``torch.autograd.Function`` whose backward is a second compiled kernel,
autograd's own derivative of the same maths (``torch.func.vjp``). Both kernels are
forward-only graphs (compiled without grad mode), so every ``backward`` works
(``retain_graph``, gradcheck), and one kernel serves inputs with or without ``requires_grad``;
double backward (``create_graph=True``) goes through the eager reference.

Compiled functions are cached per (forward or backward, rotation or not, input dtype, grid
dtype, device type, dynamic shapes), each with its own recompilation budget. Inside
``DataLoader`` worker processes nothing is compiled (:func:`in_dataloader_worker`). When
``torch.compile`` is unavailable or fails, the failure is remembered for that key, warned about
once, and the eager reference is used from then on; ``compiled=False`` forces the eager
reference.
"""

from __future__ import annotations

import threading
import types
import warnings
from typing import Callable

import torch
from torch import Tensor

from ..cameras.registry import get_model
from ..cameras.unified import unified_unproject_undistorted_xyz
from ..cubemap.atlas import rays_to_grid
from ..cubemap.faces import (
    _AXIS_SIGN_TO_FACE,
    _R_B_AXES,
    _check_face_size,
    _check_float_tensor,
    _check_pad,
)

__all__ = ["camera_grid", "rotated_rays_to_grid", "rotated_rays_to_grid_reference",
           "compile_failures"]

# Per case 2 * axis + (1 if the dominant component is negative), the face looking that way and
# its (r axis, r sign, b axis, b sign); the zero ray goes to face 0 (as in ``ray_to_face``).
_CASES = tuple((face, *_R_B_AXES[face]) for face in _AXIS_SIGN_TO_FACE)
_ZERO_CASE = (0, *_R_B_AXES[0])


# ------------------------------------------------------------------------------------------
# The maths: plain elementwise torch, traced by torch.compile (and runnable eagerly)
# ------------------------------------------------------------------------------------------

def _grid_math(x: Tensor, y: Tensor, z: Tensor, face_size, pad) -> Tensor:
    """Grid ``(..., 2)`` of cube-frame ray components ``x, y, z (...)``.

    ``ray_to_face`` followed by ``face_uv_to_grid``, same operations in the same order, with
    the gathers replaced by selections. ``face_size`` and ``pad`` may be symbolic ints.
    """
    return torch.stack(_grid_xy(x, y, z, face_size, pad), dim=-1)


def _grid_xy(x: Tensor, y: Tensor, z: Tensor, face_size, pad) -> tuple[Tensor, Tensor]:
    """:func:`_grid_math` as its two components ``(gx, gy)``."""
    f, c, n = face_size / 2.0, (face_size - 1) / 2.0, face_size + 2 * pad  # face_intrinsics
    comps = (x, y, z)
    ax, ay, az = x.detach().abs(), y.detach().abs(), z.detach().abs()
    use_x = (ax >= ay) & (ax >= az)  # ties go to x, then y, then z
    use_y = ~use_x & (ay >= az)
    comp = torch.where(use_x, x, torch.where(use_y, y, z))  # dominant component
    neg = comp.detach() < 0
    zero = comp.detach() == 0  # only the zero ray

    def pick(values: list) -> Tensor:
        """``values[2 * axis + neg]`` per ray."""
        pos = torch.where(use_x, values[0], torch.where(use_y, values[2], values[4]))
        ngt = torch.where(use_x, values[1], torch.where(use_y, values[3], values[5]))
        return torch.where(neg, ngt, pos)

    def signed(axis: int, sign: int) -> Tensor:
        return comps[axis] if sign > 0 else -comps[axis]

    _, ir0, sr0, ib0, sb0 = _ZERO_CASE
    num_r = torch.where(zero, signed(ir0, sr0), pick([signed(k[1], k[2]) for k in _CASES]))
    num_b = torch.where(zero, signed(ib0, sb0), pick([signed(k[3], k[4]) for k in _CASES]))
    face = torch.where(zero, float(_ZERO_CASE[0]), pick([float(k[0]) for k in _CASES]))
    # a . p = |p_axis| > 0 except for the zero ray: made safe before dividing
    depth = torch.where(neg, -comp, comp)
    depth = torch.where(zero, torch.ones_like(depth), depth)
    u = c + f * num_r / depth
    v = c + f * num_b / depth
    row0 = face.to(x.dtype) * n  # a small integer: exact, as ``(face * n).to(dtype)``
    gx = (2 * (u + pad) + 1) / n - 1
    gy = (2 * (v + pad + row0) + 1) / (6 * n) - 1
    return gx, gy


def _fused_plain(rays: Tensor, face_size, pad, dtype: torch.dtype) -> Tensor:
    """``rays (B, H, W, 3)`` -> grid ``(B, H, W, 2)``."""
    rays = rays.to(dtype)
    return _grid_math(rays[..., 0], rays[..., 1], rays[..., 2], face_size, pad)


def _fused_rotated(rays: Tensor, rotation: Tensor, face_size, pad, dtype: torch.dtype) -> Tensor:
    """``rays (Br, H, W, 3)``, ``rotation (Bq, 3, 3)`` -> grid ``(max(Br, Bq), H, W, 2)``."""
    x, y, z = rays[..., 0], rays[..., 1], rays[..., 2]  # [Br, H, W]
    return torch.stack(_rotated_grid_xy(x, y, z, rotation, face_size, pad, dtype), dim=-1)


def _rotated_grid_xy(x: Tensor, y: Tensor, z: Tensor, rotation: Tensor, face_size, pad,
                     dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """Ray components ``(Br, H, W)`` rotated by ``rotation (Bq, 3, 3)`` -> ``(gx, gy)``."""
    r = rotation.to(x.dtype)[:, None, None]  # [Bq, 1, 1, 3, 3]
    # in the rays' dtype, summed in einsum's order, then cast (as ``_grid`` does)
    px = (r[..., 0, 0] * x + r[..., 0, 1] * y + r[..., 0, 2] * z).to(dtype)
    py = (r[..., 1, 0] * x + r[..., 1, 1] * y + r[..., 1, 2] * z).to(dtype)
    pz = (r[..., 2, 0] * x + r[..., 2, 1] * y + r[..., 2, 2] * z).to(dtype)
    return _grid_xy(px, py, pz, face_size, pad)


def _vjp_plain(rays: Tensor, grad: Tensor, face_size, pad, dtype: torch.dtype
               ) -> tuple[Tensor]:
    """Gradient of ``(grid * grad).sum()`` w.r.t. ``rays``: autograd's own derivative of the
    fused maths (``torch.func.vjp``), compiled as one forward-only kernel."""
    _, pull = torch.func.vjp(lambda r: _fused_plain(r, face_size, pad, dtype), rays)
    return pull(grad)


def _vjp_rotated(rays: Tensor, rotation: Tensor, grad: Tensor, face_size, pad,
                 dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """Gradients w.r.t. ``rays`` and ``rotation`` (summed over broadcast batches)."""
    _, pull = torch.func.vjp(lambda r, q: _fused_rotated(r, q, face_size, pad, dtype),
                             rays, rotation)
    return pull(grad)


# ------------------------------------------------------------------------------------------
# Compilation cache
# ------------------------------------------------------------------------------------------

#: key -> compiled function, or None after a failure (then ``_FAILURES[key]`` says why).
#: Keys: (kind "grid" or "vjp", rotated, rays dtype, grid dtype, device type, dynamic).
_COMPILED: dict[tuple, Callable | None] = {}
_FAILURES: dict[tuple, str] = {}
_LOCK = threading.Lock()
_TARGETS = {("grid", False): _fused_plain, ("grid", True): _fused_rotated,
            ("vjp", False): _vjp_plain, ("vjp", True): _vjp_rotated}


#: Inductor options of every compiled kernel of the package. ``cpp.dynamic_threads``: the C++
#: kernels take their thread count from OpenMP at run time. Without it inductor bakes the thread
#: count of the compiling process, and decides from the first call's sizes whether to run in
#: parallel at all, into code that is then cached (on disk too) and reused for every size: a
#: kernel first compiled on a small input ran on one thread ever after (measured on a compiled
#: bilinear blend of 16 x 512 x 512 pixels: 65 ms on 1 or 2 threads, 34 ms once parallel).
COMPILE_OPTIONS = {"cpp.dynamic_threads": True}


def _fresh_copy(fn: Callable) -> Callable:
    # Dynamo keeps its compiled graphs (and counts recompilations) per code object: a copy of
    # the code per key gives each (dtype, device, ...) its own cache and recompilation budget.
    return types.FunctionType(fn.__code__.replace(), fn.__globals__, fn.__name__,
                              fn.__defaults__, fn.__closure__)


def _target(key: tuple) -> Callable:
    if key[0] == "camera":
        return _camera_kernel(key[1])
    return _TARGETS[key[:2]]


def in_dataloader_worker() -> bool:
    """True inside a ``DataLoader`` worker process. Compiling there can deadlock (the forked
    worker inherits the parent's inductor compile pool, which does not survive the fork: seen
    as a hung ``DataLoader``), so the fused kernels run eagerly in workers."""
    return torch.utils.data.get_worker_info() is not None


def _compiled_for(key: tuple, stacklevel: int) -> Callable | None:
    if in_dataloader_worker():
        return None   # the eager path, without a warning (see in_dataloader_worker)
    fn = _COMPILED.get(key)
    if fn is not None or key in _COMPILED:
        return fn
    with _LOCK:
        if key not in _COMPILED:
            target = _fresh_copy(_target(key))
            try:
                _COMPILED[key] = torch.compile(target, dynamic=key[-1], fullgraph=True,
                                               options=COMPILE_OPTIONS)
            except Exception as exc:  # torch.compile unsupported here (Python version, ...)
                _fail(key, exc, stacklevel + 1)
        return _COMPILED[key]


def _fail(key: tuple, exc: BaseException, stacklevel: int) -> None:
    """Remember and warn once; ``stacklevel`` makes the warning point at the caller of
    ``rotated_rays_to_grid`` (for a backward kernel, at the autograd engine)."""
    _COMPILED[key] = None
    _FAILURES[key] = f"{type(exc).__name__}: {exc}"
    kind, variant, in_dtype, dtype, device, dynamic = key
    if kind != "camera":
        variant = "rotated" if variant else "plain"
    caller = "camera_grid" if kind == "camera" else "rotated_rays_to_grid"
    first = str(exc).strip().splitlines()[0][:300] if str(exc).strip() else ""
    warnings.warn(
        f"{caller}: torch.compile failed ({kind}, {variant}, {in_dtype} -> {dtype}, {device}, "
        f"dynamic={dynamic}): {type(exc).__name__}: {first}. Using the eager path for these "
        "inputs from now on (see fastgrid.compile_failures()).",
        UserWarning, stacklevel=stacklevel + 1)


def compile_failures() -> dict[tuple, str]:
    """The compilations that failed in this process: ``{(kind "grid" or "vjp", rotated, rays
    dtype, grid dtype, device type, dynamic) or ("camera", model, params dtype, grid dtype,
    device type, dynamic): "Error: message"}``; empty when every compilation worked."""
    return dict(_FAILURES)


def _run(fn: Callable, rays: Tensor, rotation: Tensor | None, *args) -> Tensor:
    # Detached inputs: the kernels are forward-only graphs, one per key whatever requires_grad.
    if rotation is None:
        return fn(rays.detach(), *args)
    return fn(rays.detach(), rotation.detach(), *args)


def _eager_vjp(rays: Tensor, rotation: Tensor | None, grad: Tensor, face_size: int, pad: int,
               dtype: torch.dtype, needs: tuple[bool, bool], create_graph: bool) -> list:
    """Gradients through the eager reference; differentiable when ``create_graph``."""
    if not create_graph:
        rays = rays.detach().requires_grad_(needs[0])
        rotation = None if rotation is None else rotation.detach().requires_grad_(needs[1])
    inputs = [t for t, need in zip((rays, rotation), needs) if need]
    with torch.enable_grad():
        out = _reference(rays, rotation, face_size, pad, dtype)
        grads = iter(torch.autograd.grad(out, inputs, grad, create_graph=create_graph))
    return [next(grads) if need else None for need in needs]


class _FusedGrid(torch.autograd.Function):
    """Compiled forward and compiled backward (each a forward-only kernel, so that any
    ``backward`` works: ``retain_graph``, gradcheck); double backward through the eager
    reference."""

    @staticmethod
    def forward(ctx, rays, rotation, face_size, pad, dtype, key, fwd):
        ctx.save_for_backward(rays, rotation)
        ctx.args = (face_size, pad, dtype, key)
        return _run(fwd, rays, rotation, face_size, pad, dtype)

    @staticmethod
    def backward(ctx, grad):
        rays, rotation = ctx.saved_tensors
        face_size, pad, dtype, key = ctx.args
        needs = tuple(ctx.needs_input_grad[:2])
        tail = (None,) * 5
        if torch.is_grad_enabled():  # create_graph=True: a differentiable backward
            return (*_eager_vjp(rays, rotation, grad, face_size, pad, dtype, needs, True), *tail)
        bwd_key = ("vjp",) + key[1:]
        bwd = _compiled_for(bwd_key, stacklevel=2)
        if bwd is not None:
            try:
                grads = _run(bwd, rays, rotation, grad.contiguous(), face_size, pad, dtype)
                return (*(g if need else None for g, need in zip((*grads, None), needs)),
                        *tail)
            except torch.OutOfMemoryError:
                raise
            except Exception as exc:
                with _LOCK:
                    _fail(bwd_key, exc, stacklevel=2)
        return (*_eager_vjp(rays, rotation, grad, face_size, pad, dtype, needs, False), *tail)


# ------------------------------------------------------------------------------------------
# Public functions
# ------------------------------------------------------------------------------------------

def _check_inputs(rays: Tensor, rotation: Tensor | None, face_size: int, pad: int,
                  dtype: torch.dtype | None) -> tuple[Tensor, Tensor | None, torch.dtype]:
    _check_float_tensor(rays, "rays", last=3)
    _check_face_size(face_size)
    _check_pad(pad)
    if rays.dim() == 3:
        rays = rays.unsqueeze(0)
    if rays.dim() != 4:
        raise ValueError(f"rays must have shape (H, W, 3) or (B, H, W, 3), got "
                         f"{tuple(rays.shape)}")
    if dtype is None:
        dtype = rays.dtype
    elif not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise TypeError(f"dtype must be a floating torch.dtype, got {dtype!r}")
    if rotation is not None:
        _check_float_tensor(rotation, "rotation")
        if rotation.shape == (3, 3):
            rotation = rotation.unsqueeze(0)
        if rotation.dim() != 3 or rotation.shape[1:] != (3, 3):
            raise ValueError(f"rotation must have shape (B, 3, 3) or (3, 3), got "
                             f"{tuple(rotation.shape)}")
        br, bq = rays.shape[0], rotation.shape[0]
        if br != bq and 1 not in (br, bq):
            raise ValueError(f"rays batch {br} and rotation batch {bq} do not broadcast")
        if rotation.device != rays.device:
            raise ValueError(f"rotation is on {rotation.device}, rays on {rays.device}")
    return rays, rotation, dtype


def _reference(rays: Tensor, rotation: Tensor | None, face_size: int, pad: int,
               dtype: torch.dtype) -> Tensor:
    if rotation is not None:
        rays = torch.einsum("bij,bhwj->bhwi", rotation.to(rays.dtype), rays)
    return rays_to_grid(rays.to(dtype), face_size, pad)


def rotated_rays_to_grid_reference(rays: Tensor, rotation: Tensor | None, face_size: int,
                                   pad: int, *, dtype: torch.dtype | None = None) -> Tensor:
    """The eager definition: ``cubemap.rays_to_grid(einsum(R, rays).to(dtype), F, pad)``.

    Same arguments and result as :func:`rotated_rays_to_grid`; this is its fallback and its
    test oracle.
    """
    rays, rotation, dtype = _check_inputs(rays, rotation, face_size, pad, dtype)
    return _reference(rays, rotation, face_size, pad, dtype)


def rotated_rays_to_grid(rays: Tensor, rotation: Tensor | None, face_size: int, pad: int, *,
                         dtype: torch.dtype | None = None, compiled: bool = True,
                         dynamic: bool = True) -> Tensor:
    """Atlas grid (``grid_sample``, ``align_corners=False``) of rotated rays, fused.

    Equal to ``cubemap.rays_to_grid(einsum("bij,bhwj->bhwi", R, rays).to(dtype), F, pad)``:
    the rotation in the rays' dtype, the face lookup in ``dtype``, the same face choice and
    tie-breaking (ties to x, then y, then z; the zero ray to the centre of face 0, to be masked
    by the caller). Without a rotation the grid is identical bit for bit; with one, to the
    rounding of the rotated rays.

    The first call per (rotation or not, dtypes, device type) compiles the fused kernel with
    ``torch.compile`` (seconds; inductor also caches it on disk); later calls reuse it for any
    ``H``, ``W``, ``B``, ``F`` and ``pad`` (``dynamic=True``). Gradients flow to ``rays`` and
    ``rotation`` through a second compiled kernel (compiled on the first backward), and are
    recorded only when ``torch.is_grad_enabled()``; double backward runs eagerly. Inside a
    caller's ``torch.compile`` the maths is traced into the caller's graph.

    Args:
        rays: ``(H, W, 3)`` or ``(B, H, W, 3)`` camera-frame directions (need not be unit).
        rotation: ``(B, 3, 3)`` or ``(3, 3)`` camera -> cube frame, or None. Batches of rays
            and rotations broadcast (either may be 1).
        face_size: ``F``, texels per cube face side.
        pad: atlas border ``p``.
        dtype: floating dtype of the grid (default: the rays' dtype).
        compiled: False forces the eager reference (:func:`rotated_rays_to_grid_reference`).
        dynamic: compile for dynamic shapes (one kernel for all sizes); False specialises on
            each shape (recompiles when it changes).

    Returns:
        ``(B', H, W, 2)`` grid in ``dtype``, ``B'`` the broadcast batch (1 for ``(H, W, 3)``
        rays without rotation).
    """
    rays, rotation, dtype = _check_inputs(rays, rotation, face_size, pad, dtype)
    if not compiled:
        return _reference(rays, rotation, face_size, pad, dtype)
    if torch.compiler.is_compiling():  # already inside a compiled region: fuse into it
        if rotation is None:
            return _fused_plain(rays, face_size, pad, dtype)
        return _fused_rotated(rays, rotation, face_size, pad, dtype)
    key = ("grid", rotation is not None, rays.dtype, dtype, rays.device.type, bool(dynamic))
    fwd = _compiled_for(key, stacklevel=2)
    if fwd is None:
        return _reference(rays, rotation, face_size, pad, dtype)
    needs_grad = torch.is_grad_enabled() and (
        rays.requires_grad or (rotation is not None and rotation.requires_grad))
    try:
        if needs_grad:
            return _FusedGrid.apply(rays, rotation, face_size, pad, dtype, key, fwd)
        return _run(fwd, rays, rotation, face_size, pad, dtype)
    except torch.OutOfMemoryError:
        raise
    except Exception as exc:  # inductor, a missing compiler, triton, ...
        with _LOCK:
            _fail(key, exc, stacklevel=2)
        return _reference(rays, rotation, face_size, pad, dtype)


# ------------------------------------------------------------------------------------------
# Cameras: pixel centres -> rays -> rotated atlas grid, in one kernel (forward only)
# ------------------------------------------------------------------------------------------

#: The closed-form unprojections compiled whole into the camera kernel: those of the cameras
#: ``augment.RandomOmniCamera`` draws (``unified`` only without lens distortion). The others
#: unproject eagerly (the Newton inverses of kannala_brandt, scaramuzza and distorted unified
#: have data-dependent loops); each entry costs a compilation (~5-10 s) in the tests.
_CLOSED_FORM: dict[str, Callable] = {
    **{name: get_model(name).unproject_xyz
       for name in ("equidistant", "equisolid", "stereographic")},
    "unified": unified_unproject_undistorted_xyz,
}


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
                                 unproject_xyz, _rotated_grid_xy)

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
            kernel = _compiled_for(key, stacklevel=2)
            if kernel is not None:
                try:
                    return kernel(*args)
                except torch.OutOfMemoryError:
                    raise
                except Exception as exc:
                    with _LOCK:
                        _fail(key, exc, stacklevel=2)

        def unproject_xyz(u, v, p):   # any model, through its own unproject
            rays, ok = unproject(torch.stack(torch.broadcast_tensors(u, v), -1), p)
            return (*rays.unbind(-1), ok)

        def to_grid_xy(x, y, z, rot, f, p, dt):
            rays = torch.stack((x, y, z), -1)
            return rotated_rays_to_grid(rays, rot, f, p, dtype=dt, compiled=compiled).unbind(-1)

        return _camera_grid_math(*args, unproject_xyz, to_grid_xy)
