"""How large a cubemap a camera needs, and which of its faces a simulator must render.

Both answers come from the camera's rays in the cube frame, ``ray_cube = R @ ray_cam``
(``DESIGN.md``: ``R = I`` is a camera looking forward, along the "front" face).

Face size (`required_face_size`). A face is a pinhole with ``f = F / 2`` texels per unit
of its normalised image plane: a cube-frame direction ``d`` lands at
``(x, y) = ((r . d) / (a . d), (b . d) / (a . d))``, texel ``(u, v) = c + f (x, y)``, on the face
whose axis ``a`` is its dominant signed axis (``r``, ``b`` the face's image right and down).
At a camera pixel, the chain rule gives the ``2 x 2`` map from a step of camera pixels to a step
on that face's normalised plane::

    G = d(x, y) / d(u, v)_cam = [ (r - x a)^T ] (R J) / (a . d),     J = d ray_cam / d(u, v)
                                [ (b - y a)^T ]

(``J``, ``3 x 2``, radians per pixel). A step ``e`` of camera pixels covers ``f |G e|`` texels;
the face's texels are no coarser than the camera's pixels *in every direction* iff
``f sigma_min(G) >= 1``, that is::

    F >= 2 / sigma_min(G)                                   (criterion="anisotropic", default)

at every valid pixel; `required_face_size` returns the ceiling of its maximum. A pinhole
camera identical to a face gives ``G = I / f`` everywhere and needs exactly that face's ``F``.

A simpler, isotropic bound compares the face's coarsest density with the camera's finest one.
At a direction ``phi`` from its axis (``cos phi = a . d``) a face samples ``f / cos phi``
texels per radian tangentially and ``f / cos^2 phi`` radially, so at least ``f / cos phi`` in
every direction; the camera's finest density is ``1 / s_min(J)`` (``Camera.pixels_per_radian``).
Requiring the first to exceed the second gives::

    F >= 2 cos(phi) / s_min(J)                              (criterion="isotropic")

Since ``sigma_min(G) >= s_min(J) / cos(phi)``, the isotropic bound is never below the anisotropic
one, and at most ``1 / cos phi <= sqrt(3)`` times it (it asks for ``F / cos phi`` at the corners of
a camera identical to a face).

Visible faces (`visible_faces`): the faces whose texels the layer reads (bilinear sampling
of the padded atlas at the pixel centres, the border resampled from the neighbours through the
border plan), plus the faces the pixels' footprints enter between centres (their corners).

Both are planning steps, not layers: they run in float64 on the CPU, without gradients, whatever
the camera's dtype and device.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import torch
from torch import Tensor

from ..cameras._base import broadcast_shapes
from ..cameras._checks import not_a_camera
from ..cameras.camera import Camera
from ..cubemap.faces import FACES, _check_face_size, _check_pad, face_axes, ray_to_face
from ..cubemap.padding import border_taps
from ..cubemap.rotation import check_rotation

__all__ = ["MEMORY_PER_PIXEL", "PROCESS_MEMORY", "available_memory", "face_size_map",
           "needed_face_names", "required_face_size", "visible_faces"]

CRITERIA = ("anisotropic", "isotropic")

#: Memory of a process that renders, before its images: Python, torch, the package (bytes;
#: measured 340-460 MB, with headroom for the allocator: a frame of tests/test_dataset.py peaks
#: at 0.6-0.8 GB against an estimate of 1.2 GB); and the peak bytes per pixel of an image
#: rendered through the layer (rays, grid, RGB, depth, labels and mask, their encoding;
#: measured 110 on the built-in town's dataset, tests/test_dataset.py).
PROCESS_MEMORY, MEMORY_PER_PIXEL = 700e6, 160


# --------------------------------------------------------------------------------------------
# Entry checks and shared helpers
# --------------------------------------------------------------------------------------------

def _check_camera(camera: object) -> Camera:
    if not isinstance(camera, Camera):
        raise not_a_camera("camera", camera)
    return camera


#: Peak bytes per camera pixel of `face_size_map` (its float64 rays, shifted rays and Jacobians;
#: measured 725, `visible_faces` 480) and those it keeps per further camera of a batch.
PLANNING_BYTES_PER_PIXEL, PLANNING_BYTES_KEPT = 800, 96


def _check_planning_memory(camera: Camera) -> None:
    """Refuse, before allocating, a camera whose per-pixel planning cannot fit in memory."""
    h, w = camera.image_size
    cameras = math.prod(camera.batch_shape)
    need = h * w * (PLANNING_BYTES_PER_PIXEL + PLANNING_BYTES_KEPT * (cameras - 1))
    available = available_memory()
    if need > available:
        raise MemoryError(
            f"camera: image_size {tuple(camera.image_size)}: planning its cube faces needs about "
            f"{need / 1e9:,.1f} GB (float64 rays and their Jacobians at each of its {h * w:,} "
            f"pixels), {available / 1e9:,.1f} GB are available; use a smaller image_size")


def _check_rotation(rotation: object) -> Tensor:
    """``rotation`` as a float64 ``(*Br, 3, 3)`` CPU tensor (identity for None), checked by
    `check_rotation`."""
    if rotation is None:
        return torch.eye(3, dtype=torch.float64)
    return check_rotation(rotation).detach().to(device="cpu", dtype=torch.float64)


def _pairs(camera: Camera, rotation: Tensor) -> tuple[torch.Size, list[tuple[int, int]]]:
    """Broadcast the camera batch against the rotation batch: the output batch shape and, per
    output element, (flat camera index, flat rotation index)."""
    cam_batch, rot_batch = camera.batch_shape, rotation.shape[:-2]
    try:
        shape = broadcast_shapes(cam_batch, rot_batch)
    except RuntimeError:
        raise ValueError(f"rotation: batch shape {tuple(rot_batch)} does not broadcast with the "
                         f"camera batch {tuple(cam_batch)}") from None
    ci = torch.arange(math.prod(cam_batch)).reshape(cam_batch).expand(shape).reshape(-1)
    ri = torch.arange(math.prod(rot_batch)).reshape(rot_batch).expand(shape).reshape(-1)
    return shape, list(zip(ci.tolist(), ri.tolist()))


def _params64(camera: Camera) -> Tensor:
    """``(N, P)`` float64 CPU parameters, one row per camera of the batch."""
    params = camera.params.detach().to(device="cpu", dtype=torch.float64)
    return params.reshape(-1, params.shape[-1])


def _pixel_grid(h: int, w: int, offset: float = 0.0) -> Tensor:
    """``(h, w, 2)`` float64 pixels ``(u, v) = (j + offset, i + offset)``."""
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64) + offset,
                          torch.arange(w, dtype=torch.float64) + offset, indexing="ij")
    return torch.stack((u, v), dim=-1)


def _centre_rays(camera: Camera, params: Tensor) -> tuple[Tensor, Tensor]:
    """Unit rays ``(H, W, 3)`` of the pixel centres of one camera and their validity (model
    domain, image, ``fov`` and ``blind_fov``), in float64."""
    grid = _pixel_grid(*camera.image_size)
    rays, valid = camera.model.unproject(grid, params)
    return rays, valid & camera.in_image(grid) & camera.within_fov(rays)


def _check_positive_number(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise TypeError(f"{name}: expected a finite number, got {value!r}")
    if value <= 0:
        raise ValueError(f"{name}: expected > 0, got {value}")
    return float(value)


# --------------------------------------------------------------------------------------------
# Face size
# --------------------------------------------------------------------------------------------

def face_size_map(camera: Camera, rotation: Tensor | None = None, *,
                  criterion: str = "anisotropic", step: float = 1e-2) -> Tensor:
    """Face size needed at every pixel (before the maximum and the ceiling).

    See the module docstring for the two criteria: ``2 / sigma_min(G)`` (anisotropic) and
    ``2 cos(phi) / s_min(J)`` (isotropic), ``J = d ray / d(u, v)`` by fourth-order central
    differences of ``unproject`` with steps of ``step`` and ``2 step`` pixels, in float64
    (relative truncation error about ``(step / f)^4``, rounding about ``f * 2e-16 / step``:
    below 1e-10 for focals from 5 to 1e4 pixels), ``phi`` the angle between the cube-frame ray
    and the axis of the face it hits.

    Args:
        camera: a ``Camera`` (one, or a batch ``(*Bc)``).
        rotation: ``None`` (identity), ``(3, 3)`` or ``(*Br, 3, 3)`` camera-to-cube rotations,
            broadcasting with the camera batch; or ``"any"``: the largest size over every
            attitude, ``2 / s_min(J)`` (the pixel's ray at a face's centre, where both criteria
            agree and a face is coarsest; ``sigma_min(G) >= s_min(J) / cos(phi)`` everywhere
            else).
        criterion: ``"anisotropic"`` (exact, default) or ``"isotropic"`` (upper bound).
        step: finite-difference step in pixels.

    Returns:
        ``(*S, H, W)`` float64 face size in texels, ``S`` the broadcast batch shape; 0 where the
        pixel is invalid (outside the model, the image, ``fov``; an invalid neighbour at
        ``+- step`` or ``+- 2 step``; or a singular Jacobian).
    """
    _check_camera(camera)
    _check_planning_memory(camera)
    if criterion not in CRITERIA:
        raise ValueError(f"criterion: expected one of {CRITERIA}, got {criterion!r}")
    step = _check_positive_number(step, "step")
    any_rotation = isinstance(rotation, str) and rotation == "any"
    rot = _check_rotation(None if any_rotation else rotation)
    shape, pairs = _pairs(camera, rot)
    rot = rot.reshape(-1, 3, 3)
    params_all = _params64(camera)
    axes = face_axes(torch.float64)  # [6, (a, b, r), 3]
    h, w = camera.image_size
    grid = _pixel_grid(h, w)
    cache: dict[int, tuple[Tensor, Tensor, Tensor]] = {}
    out = []
    for ci, ri in pairs:
        if ci not in cache:
            params = params_all[ci]
            rays, valid = _centre_rays(camera, params)
            columns = []
            for axis in (0, 1):
                # Fourth-order central differences: (-X(2h) + 8 X(h) - 8 X(-h) + X(-2h)) / 12h.
                column = torch.zeros_like(rays)
                for shift, coef in ((2, -1.0), (1, 8.0), (-1, -8.0), (-2, 1.0)):
                    offset = torch.zeros(2, dtype=torch.float64)
                    offset[axis] = shift * step
                    ray, ok = camera.model.unproject(grid + offset, params)
                    column = column + coef * ray
                    valid = valid & ok
                columns.append(column / (12 * step))
            cache[ci] = (rays, torch.stack(columns, dim=-1), valid)  # [H, W, 3], [H, W, 3, 2]
        rays, jac, valid = cache[ci]
        r = rot[ri]
        d = rays @ r.T  # [H, W, 3] cube frame, unit
        jac_cube = r @ jac  # [H, W, 3, 2]
        face, _ = ray_to_face(d, 1)
        ax = axes[face]  # [H, W, 3, 3]
        a, b, right = ax[..., 0, :], ax[..., 1, :], ax[..., 2, :]
        depth = (a * d).sum(-1)  # cos(phi) > 0
        depth = torch.where(valid & (depth > 0), depth, torch.ones_like(depth))
        if any_rotation:    # each ray at a face's centre: G = J in the face's basis
            s_min, _ = _singular_values(jac[..., 0], jac[..., 1])
            ok = valid & (s_min > 0)
            size = 2 / torch.where(ok, s_min, torch.ones_like(s_min))
        elif criterion == "isotropic":
            s_min, _ = _singular_values(jac_cube[..., 0], jac_cube[..., 1])  # rad / px
            ok = valid & (s_min > 0)
            size = 2 * depth / torch.where(ok, s_min, torch.ones_like(s_min))
        else:
            x = (right * d).sum(-1, keepdim=True) / depth.unsqueeze(-1)
            y = (b * d).sum(-1, keepdim=True) / depth.unsqueeze(-1)
            gx = (right - x * a) / depth.unsqueeze(-1)  # d x / d ray, [H, W, 3]
            gy = (b - y * a) / depth.unsqueeze(-1)
            col_u = torch.stack(((gx * jac_cube[..., 0]).sum(-1),
                                 (gy * jac_cube[..., 0]).sum(-1)), -1)  # [H, W, 2]
            col_v = torch.stack(((gx * jac_cube[..., 1]).sum(-1),
                                 (gy * jac_cube[..., 1]).sum(-1)), -1)
            s_min, _ = _singular_values(col_u, col_v)  # face units per px
            ok = valid & (s_min > 0)
            size = 2 / torch.where(ok, s_min, torch.ones_like(s_min))
        out.append(torch.where(ok, size, torch.zeros_like(size)))
    return torch.stack(out).reshape(shape + (h, w))


def _singular_values(col0: Tensor, col1: Tensor) -> tuple[Tensor, Tensor]:
    """``(s_min, s_max)`` of the ``n x 2`` matrices with columns ``col0``, ``col1`` (``(..., n)``).

    ``s_max`` from the larger eigenvalue of the Gram matrix, ``s_min = sqrt(det Gram) / s_max``
    (no cancellation for nearly isotropic matrices).
    """
    g00 = (col0 * col0).sum(-1)
    g01 = (col0 * col1).sum(-1)
    g11 = (col1 * col1).sum(-1)
    mean, dev = 0.5 * (g00 + g11), torch.sqrt((0.5 * (g00 - g11)) ** 2 + g01 * g01)
    s_max = torch.sqrt(mean + dev)
    det = (g00 * g11 - g01 * g01).clamp(min=0)
    s_min = torch.where(s_max > 0, torch.sqrt(det) / torch.where(s_max > 0, s_max,
                                                                  torch.ones_like(s_max)),
                        torch.zeros_like(s_max))
    return s_min, s_max


def required_face_size(camera: Camera, rotation: Tensor | None = None, *,
                       supersample: float = 1, criterion: str = "anisotropic",
                       step: float = 1e-2, rtol: float = 1e-8) -> int:
    """Smallest cube face size whose texels are no coarser than the camera's pixels.

    ``F = ceil(supersample * max_pixels F_pixel)``, with ``F_pixel = 2 / sigma_min(G)`` for
    ``criterion="anisotropic"``: in every direction a step of one camera pixel covers at least
    one texel of the face that the pixel's ray hits (``G`` the ``2 x 2`` map from camera pixels to
    that face's normalised plane; module docstring). ``criterion="isotropic"`` uses the simpler
    bound ``F_pixel = 2 cos(phi) * finest``: a face of ``f = F / 2`` samples at least
    ``f / cos(phi)`` texels per radian at a ray ``phi`` from its axis (tangential ``f / cos phi``,
    radial ``f / cos^2 phi``), and ``finest`` is the camera's largest density there
    (``Camera.pixels_per_radian()[0]``); it is never smaller than the anisotropic size and at
    most ``sqrt(3)`` times it.

    Analytic cases (tests/test_sizing.py): a pinhole identical to a face of size ``F`` needs
    exactly ``F`` (``G = I / f``; the isotropic bound asks ``ceil(F / cos phi)`` of its corner
    pixel); an equidistant lens of focal ``f`` needs ``2 f`` at its centre (``F >= 2 f`` for a
    field of view within the front face) and ``2 f theta`` at a ray ``theta`` from its axis on a
    side face's axis plane, so a forward fisheye of 180 degrees or more needs about twice its
    image-circle radius in pixels (1021 for a 1024 x 1024, 190-degree equidistant image circle).

    Args:
        camera: a ``Camera``, or a batch of cameras (the maximum over the batch).
        rotation: ``None`` (identity: looking along the front face), ``(3, 3)`` or a batch
            ``(*Br, 3, 3)`` of camera-to-cube rotations ``ray_cube = R @ ray_cam``, broadcasting
            with the camera batch (the maximum over all); or ``"any"``, the maximum over every
            attitude (twice the camera's finest pixels per radian: a size that holds whatever
            the ride, `face_size_map`).
        supersample: texels per camera pixel to ask for (> 0), e.g. 2 for 2x supersampling.
        criterion: ``"anisotropic"`` (default) or ``"isotropic"``.
        step: finite-difference step of the Jacobian, in pixels.
        rtol: relative slack before the ceiling, absorbing the Jacobian's rounding (a camera
            identical to a face of 512 gives 512.000000001, which must not become 513).

    Returns:
        ``F`` as a Python int >= 1.

    Raises:
        TypeError: ``camera`` is not a ``Camera``; ``rotation`` not a floating tensor.
        ValueError: ``rotation`` not rotations of a broadcastable batch; no valid pixel;
            ``supersample``/``step``/``rtol`` out of range; unknown ``criterion``.
        MemoryError: the camera's pixels cannot be planned in the memory available (the
            message gives ``image_size`` and the memory needed), before anything is allocated.
    """
    supersample = _check_positive_number(supersample, "supersample")
    if isinstance(rtol, bool) or not isinstance(rtol, (int, float)) or not 0 <= rtol < 1:
        raise ValueError(f"rtol: expected a number in [0, 1), got {rtol!r}")
    sizes = face_size_map(camera, rotation, criterion=criterion, step=step)
    if not bool((sizes > 0).any()):
        raise ValueError("camera: no valid pixel (model domain, image, fov), no face size")
    need = float(sizes.max()) * supersample
    return max(1, math.ceil(need * (1 - rtol)))


# --------------------------------------------------------------------------------------------
# Visible faces
# --------------------------------------------------------------------------------------------

def visible_faces(camera: Camera, rotation: Tensor | None = None, *, pad: int = 1,
                  face_size: int | None = None, eps: float = 1e-6) -> Tensor:
    """Which cube faces a simulator must render for this camera and attitude.

    A face is needed if the layer reads one of its texels, or if the pixels' footprints enter
    it:

    1. Reads at the pixel centres (exact for the layer's sampling). The ray of every valid
       pixel centre hits face ``k`` at ``uv`` in ``[-0.5, F - 0.5]``. A separable kernel of
       radius ``pad`` texels reads the texels ``t`` with ``|t - uv| < pad`` on each axis of the
       padded face ``k`` (``pad = 1``: bilinear, the 2 x 2 neighbours; ``pad = 2``: torch's
       bicubic, 4 x 4). Interior texels are face ``k``; a border texel is read from the faces
       of its sources in ``border_plan(F, pad)`` (the neighbour across the seam, and near
       corners the third face). With bilinear sampling a centre reads the border only if it
       lies within half a texel of the face's edge (``uv < 0`` or ``uv > F - 1``): the outermost
       centres of a pinhole identical to a face, at ``uv = 0`` and ``F - 1``, read that face
       alone. The nearest-texel border of labels reads a subset of these faces.
    2. The footprints. Rays through the corners of the valid pixels (pixel centre +- 0.5)
       count for the face that they hit strictly inside (farther than ``eps`` texels from its
       edges): a face entered between the centres must be rendered, but a corner lying on a
       seam (the corners of a pinhole identical to a face) enters neither face beyond it.
       Corners outside the model's domain are skipped. Corners do not add border reads.

    Kernel taps at ``pad - eps`` texels or farther (bilinear weight below ``eps``) and border
    sources weighing less than ``eps`` are ignored (rounding of rays that land on texel
    centres). Exact for bilinear sampling; for bicubic, taps at a distance of exactly one texel
    (weight 0 in the Keys kernel) still count, a superset. ``pad = 0`` means nearest sampling
    without a border: only the faces hit by the centres and the corners.

    Args:
        camera: a ``Camera`` (or a batch ``(*Bc)``).
        rotation: ``None``, ``(3, 3)`` or ``(*Br, 3, 3)`` camera-to-cube rotations
            (``ray_cube = R @ ray_cam``) broadcasting with the camera batch.
        pad: the sampler's reach in texels, the atlas border (1 bilinear, 2 bicubic).
        face_size: ``F``; default ``required_face_size(camera, rotation)``. The answer depends
            on ``F`` only through the half-texel strips along the seams.
        eps: negligible weight, and distance to a seam in texels.

    Returns:
        ``(*S, 6)`` bool, faces in ``FACES`` order; ``S`` the broadcast batch shape of the camera
        and the rotations (``(6,)`` for one camera and one rotation).

    Raises:
        MemoryError: as `required_face_size`, before anything is allocated.

    Examples:
        >>> import math, omniscape_torch as ot
        >>> from omniscape_torch.cameras.presets import fisheye
        >>> needed = visible_faces(fisheye((64, 64), fov=math.radians(190)))
        >>> [f for f, n in zip(ot.cubemap.FACES, needed.tolist()) if n]
        ['front', 'left', 'right', 'up', 'down']
    """
    _check_camera(camera)
    _check_planning_memory(camera)
    _check_pad(pad)
    if isinstance(eps, bool) or not isinstance(eps, (int, float)) or not 0 < eps < 0.5:
        raise ValueError(f"eps: expected a number in (0, 0.5), got {eps!r}")
    if face_size is None:
        face_size = required_face_size(camera, rotation)
    else:
        _check_face_size(face_size)
    rot = _check_rotation(rotation)
    shape, pairs = _pairs(camera, rot)
    rot = rot.reshape(-1, 3, 3)
    params_all = _params64(camera)
    size = face_size
    n = size + 2 * pad
    h, w = camera.image_size

    border_faces = None
    if pad > 0:
        dst_index, border_faces = _border_faces(size, pad, eps)  # [N], [N, 6]

    corner_grid = _pixel_grid(h + 1, w + 1, -0.5)  # [H + 1, W + 1, 2]
    cache: dict[int, tuple[Tensor, Tensor]] = {}
    out = []
    for ci, ri in pairs:
        if ci not in cache:
            params = params_all[ci]
            rays, valid = _centre_rays(camera, params)
            corner_rays, corner_ok = camera.model.unproject(corner_grid, params)
            # A corner belongs to the footprint if any of its (up to) four pixels is valid.
            v = torch.nn.functional.pad(valid, (1, 1, 1, 1))
            near_valid = v[:-1, :-1] | v[:-1, 1:] | v[1:, :-1] | v[1:, 1:]
            cache[ci] = (rays[valid], corner_rays[near_valid & corner_ok])
        rays, corner_rays = cache[ci]
        r = rot[ri]
        needed = torch.zeros(6, dtype=torch.bool)

        if rays.shape[0]:
            face, uv = ray_to_face(rays @ r.T, size)  # [M], [M, 2]
            if pad == 0:
                needed[face] = True
            else:
                touched = torch.zeros(6, n, n, dtype=torch.bool)
                base = torch.floor(uv).long()
                for du in range(-pad + 1, pad + 1):
                    tu = base[:, 0] + du
                    keep_u = (tu - uv[:, 0]).abs() < pad - eps
                    for dv in range(-pad + 1, pad + 1):
                        tv = base[:, 1] + dv
                        keep = keep_u & ((tv - uv[:, 1]).abs() < pad - eps)
                        touched[face[keep], tv[keep] + pad, tu[keep] + pad] = True
                needed |= touched[:, pad:pad + size, pad:pad + size].flatten(1).any(1)
                read = touched.flatten()[dst_index]  # [N] border texels read
                needed |= border_faces[read].any(0)

        if corner_rays.shape[0]:
            face, uv = ray_to_face(corner_rays @ r.T, size)
            inside = ((uv > -0.5 + eps) & (uv < size - 0.5 - eps)).all(-1)
            needed[face[inside]] = True
        out.append(needed)
    return torch.stack(out).reshape(shape + (6,))


def _border_faces(size: int, pad: int, eps: float, tol: float = 1e-12, max_iter: int = 200
                  ) -> tuple[Tensor, Tensor]:
    """The border texels of a cube padded by `pad` (`(N,)` padded flat indices, the border
    plan's order) and the faces each reads with a weight above `eps` (`(N, 6)` bool).

    The faces' weights of `border_plan(size, pad)`, from its own system `B = W_i X + W_b B`
    solved per face rather than per texel: the face masses `M (N, 6)` are the fixed point of
    `M = W_i onehot(face) + W_b M` (a few products of `(N, 4)` taps, where the plan's expansion
    of every texel's weights takes seconds on a busy machine), normalised like the plan's rows.
    """
    taps = border_taps(size, pad)
    n = size + 2 * pad
    face = taps.tap_col // (n * n)  # [N, 4]
    pos = taps.border_pos[taps.tap_col]  # [N, 4]: the tap's border texel, -1 inside
    on_border = pos >= 0
    zero = torch.zeros_like(taps.tap_w)
    inner = torch.zeros(len(taps.dst), 6, dtype=torch.float64).scatter_add_(
        1, face, torch.where(on_border, zero, taps.tap_w))  # [N, 6]
    w_border, pos = torch.where(on_border, taps.tap_w, zero), pos.clamp(min=0)
    mass = inner
    for _ in range(max_iter):
        step = inner + (w_border.unsqueeze(-1) * mass[pos]).sum(1)  # [N, 6]
        done = float((step - mass).abs().max()) < tol if len(step) else True
        mass = step
        if done:
            break
    return taps.dst, mass / mass.sum(1, keepdim=True) > eps


def needed_face_names(needed: Tensor) -> list[str]:
    """Names (``FACES`` order) of the True entries of one ``(6,)`` mask from
    `visible_faces`."""
    if not isinstance(needed, Tensor) or needed.shape != (6,):
        raise ValueError(f"needed: expected a (6,) tensor, got {getattr(needed, 'shape', needed)}")
    return [name for name, flag in zip(FACES, needed.tolist()) if flag]


# --------------------------------------------------------------------------------------------
# Memory
# --------------------------------------------------------------------------------------------

def available_memory() -> int:
    """Bytes this process may still allocate: the kernel's ``MemAvailable``, or less under a
    cgroup (container) limit; physical memory where neither can be read."""
    limits = []
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    limits.append(int(line.split()[1]) * 1024)
    except OSError:
        pass
    for limit_file, usage_file in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                                   ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                                    "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            limit = Path(limit_file).read_text().strip()
            usage = Path(usage_file).read_text().strip()
        except OSError:
            continue
        if limit.isdigit() and usage.isdigit() and int(limit) < 2 ** 60:
            limits.append(int(limit) - int(usage))
    if not limits:
        try:
            limits.append(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
        except (ValueError, OSError):  # pragma: no cover - no way to tell: do not refuse
            return 2 ** 62
    return max(0, min(limits))
