"""The one map from rays to the atlas grid, eager or compiled from the same source.

`grid_xy` is the maths: ``ray_to_face`` followed by ``face_uv_to_grid``, the same
operations in the same order, with the face table's gathers written as selections so that
``torch.compile`` fuses it into one loop. `rays_to_grid` runs it eagerly (every caller
of the package that needs a grid of cube-frame rays), `rotated_rays_to_grid` compiled,
with a rotation folded in. Run eagerly, ``rays_to_grid(einsum(R, rays), F, pad)`` is about 25
elementwise ops, each one a full pass through memory over every ray (30 ms for 1M rays on 2
cores, more than the bilinear sampling it serves); compiled, one loop (1.5 ms;
``benchmarks/bench_projection.py``). The fast sampler's C++ kernel computes the same grid
point inside its sampling pass (``render/csrc/sample_rays.h``: bit for bit for nearest
sampling; bilinear taps come from the face pixel ``(u, v)`` below without the normalised grid,
to float rounding of the same point):

    p = R ray                                       # rotation, 9 multiply-adds
    axis = dominant |p_i| (ties: x, then y, then z)  # the face's viewing axis a
    face = the face looking along (axis, sign p_axis); face 0 for the zero ray
    u = c + f (r . p) / |p_axis|,  v = c + f (b . p) / |p_axis|   # f = F / 2, c = (F - 1) / 2
    (gx, gy) = face_uv_to_grid(face, (u, v), F, pad)

written in plain elementwise torch with the face choice as ``torch.where`` over the signed axes
(the tables are derived from ``cubemap.faces``, which alone knows the face order), and compiled
with ``torch.compile`` (inductor) on first use. The operations and their order are those of
``ray_to_face`` and ``face_uv_to_grid`` (which stay as the definitions the tests compare
with), so the grid is theirs: bit for bit without a rotation, and to float32 rounding of the
rotated rays with one (``einsum`` may sum its three products in another order). The face
choice and its tie-breaking are the same.

Gradients: a ``torch.autograd.Function`` whose backward is a second compiled kernel,
autograd's own derivative of the same maths (``torch.func.vjp``). Both kernels are
forward-only graphs (compiled without grad mode), so every ``backward`` works
(``retain_graph``, gradcheck), and one kernel serves inputs with or without ``requires_grad``;
double backward (``create_graph=True``) goes through the eager reference.

Compiled functions are cached per (forward or backward, rotation or not, input dtype, grid
dtype, device type, dynamic shapes), each with its own recompilation budget. Inside
``DataLoader`` worker processes nothing is compiled (`in_dataloader_worker`). When
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

from .faces import (
    _AXIS_SIGN_TO_FACE,
    _R_B_AXES,
    _check_face_size,
    _check_float_tensor,
    _check_pad,
)

__all__ = ["grid_xy", "rays_to_grid", "rotated_grid_xy", "rotated_rays_to_grid",
           "rotated_rays_to_grid_reference", "compile_failures", "compiled_kernel", "fail",
           "in_dataloader_worker"]

# Per case 2 * axis + (1 if the dominant component is negative), the face looking that way and
# its (r axis, r sign, b axis, b sign); the zero ray goes to face 0 (as in ``ray_to_face``).
_CASES = tuple((face, *_R_B_AXES[face]) for face in _AXIS_SIGN_TO_FACE)
_ZERO_CASE = (0, *_R_B_AXES[0])


# ------------------------------------------------------------------------------------------
# The maths: plain elementwise torch, traced by torch.compile (and runnable eagerly)
# ------------------------------------------------------------------------------------------

def rays_to_grid(rays: Tensor, face_size: int, pad: int) -> Tensor:
    """``grid_sample`` coordinates (``align_corners=False``) in the atlas of cube-frame rays.

    ``ray_to_face`` followed by ``face_uv_to_grid`` (`grid_xy`, eagerly). Zero rays map
    to the centre of face 0; mask them.

    Args:
        rays: ``(..., 3)`` directions in the cube frame (need not be unit), floating.
        face_size: ``F``.
        pad: atlas border ``p``.

    Returns:
        ``(..., 2)`` grid, dtype of ``rays``; differentiable with respect to ``rays``.
    """
    _check_float_tensor(rays, "rays", last=3)
    _check_face_size(face_size)
    _check_pad(pad)
    return torch.stack(grid_xy(rays[..., 0], rays[..., 1], rays[..., 2], face_size, pad), -1)


def grid_xy(x: Tensor, y: Tensor, z: Tensor, face_size, pad) -> tuple[Tensor, Tensor]:
    """The atlas grid ``(gx, gy)`` of cube-frame ray components ``x, y, z (...)``.

    ``ray_to_face`` followed by ``face_uv_to_grid``, same operations in the same order, with
    the gathers replaced by selections. ``face_size`` and ``pad`` may be symbolic ints.
    """
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
    return torch.stack(grid_xy(rays[..., 0], rays[..., 1], rays[..., 2], face_size, pad), -1)


def _fused_rotated(rays: Tensor, rotation: Tensor, face_size, pad, dtype: torch.dtype) -> Tensor:
    """``rays (Br, H, W, 3)``, ``rotation (Bq, 3, 3)`` -> grid ``(max(Br, Bq), H, W, 2)``."""
    x, y, z = rays[..., 0], rays[..., 1], rays[..., 2]  # [Br, H, W]
    return torch.stack(rotated_grid_xy(x, y, z, rotation, face_size, pad, dtype), dim=-1)


def rotated_grid_xy(x: Tensor, y: Tensor, z: Tensor, rotation: Tensor, face_size, pad,
                    dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """`grid_xy` of camera-frame ray components ``(Br, H, W)`` rotated by ``rotation
    (Bq, 3, 3)`` (in the rays' dtype, summed in ``einsum``'s order, then cast to ``dtype``)."""
    r = rotation.to(x.dtype)[:, None, None]  # [Bq, 1, 1, 3, 3]
    # in the rays' dtype, summed in einsum's order, then cast (as ``_grid`` does)
    px = (r[..., 0, 0] * x + r[..., 0, 1] * y + r[..., 0, 2] * z).to(dtype)
    py = (r[..., 1, 0] * x + r[..., 1, 1] * y + r[..., 1, 2] * z).to(dtype)
    pz = (r[..., 2, 0] * x + r[..., 2, 1] * y + r[..., 2, 2] * z).to(dtype)
    return grid_xy(px, py, pz, face_size, pad)


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
_LOCK = threading.RLock()   # compiled_kernel() records a failure while holding it
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


def in_dataloader_worker() -> bool:
    """True inside a ``DataLoader`` worker process. Compiling there can deadlock (the forked
    worker inherits the parent's inductor compile pool, which does not survive the fork: seen
    as a hung ``DataLoader``), so the fused kernels run eagerly in workers."""
    return torch.utils.data.get_worker_info() is not None


def compiled_kernel(key: tuple, target: Callable, stacklevel: int = 1) -> Callable | None:
    """``torch.compile(target)`` (full graph, ``dynamic=key[-1]``), once per ``key``; None
    inside ``DataLoader`` workers (`in_dataloader_worker`) and after a failure, which is
    remembered and warned about once (`fail`). ``key``: ``(kind, variant, input dtype,
    output dtype, device type, dynamic)``."""
    if in_dataloader_worker():
        return None   # the eager path, without a warning (see in_dataloader_worker)
    fn = _COMPILED.get(key)
    if fn is not None or key in _COMPILED:
        return fn
    with _LOCK:
        if key not in _COMPILED:
            try:
                _COMPILED[key] = torch.compile(_fresh_copy(target), dynamic=key[-1],
                                               fullgraph=True, options=COMPILE_OPTIONS)
            except Exception as exc:  # torch.compile unsupported here (Python version, ...)
                fail(key, exc, stacklevel + 1)
        return _COMPILED[key]


def fail(key: tuple, exc: BaseException, stacklevel: int) -> None:
    """Remember a failed compilation of ``key`` and warn once; ``stacklevel`` makes the warning
    point at the caller of ``rotated_rays_to_grid`` or ``camera_grid`` (for a backward kernel,
    at the autograd engine)."""
    with _LOCK:
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
        "inputs from now on (see cubemap.grid.compile_failures()).",
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
        bwd = compiled_kernel(bwd_key, _TARGETS["vjp", key[1]], stacklevel=2)
        if bwd is not None:
            try:
                grads = _run(bwd, rays, rotation, grad.contiguous(), face_size, pad, dtype)
                return (*(g if need else None for g, need in zip((*grads, None), needs)),
                        *tail)
            except torch.OutOfMemoryError:
                raise
            except Exception as exc:
                fail(bwd_key, exc, stacklevel=2)
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

    Same arguments and result as `rotated_rays_to_grid`; this is its fallback and its
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
        compiled: False forces the eager reference (`rotated_rays_to_grid_reference`).
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
    fwd = compiled_kernel(key, _TARGETS[key[:2]], stacklevel=2)
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
        fail(key, exc, stacklevel=2)
        return _reference(rays, rotation, face_size, pad, dtype)


