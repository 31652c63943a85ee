"""Forward-only fast sampling of a cube through an atlas grid: the paper's lookup table.

``OmniProjection``'s reference path pads the cube into an atlas (a copy of every texel) and
calls ``grid_sample``. Without gradients the same image is computed here with no atlas at all:

    grid (B', H, W, 2) --> per pixel the flat offset of its top-left tap in the cube
        (B, 6, C, F, F) and its two bilinear fractions (nearest: the offset of its texel)
    image = 4 taps per channel gathered from the cube and blended

For a frozen camera the offsets and fractions are a lookup table, built once
(:func:`build_lut`) and read on every call; for a grid used once they are computed in the
sampling pass itself and never stored; for camera rays under a new rotation per call
(:func:`sample_rays`) so is the grid, from the rays.

A pixel whose taps are not all interior texels of one face ("edge" pixels: within a texel of
a seam, about 1% of them) reads the atlas border, which the cube does not hold: its taps read a
virtual atlas, the cube's interior plus its ring of border texels, each computed from the
border plan exactly as :func:`~omniscape_torch.cubemap.cubemap_to_atlas` computes them. Pixels
whose taps all lie outside the atlas (the invalid ones, grid ``(-2, -2)``) read 0, as with zero
padding (or ``fill``).

The pixel coordinates are those of ``grid_sample`` (``align_corners=False``) bit for bit:
PyTorch's CPU kernel unnormalises with a fused multiply-add, ``x = fma(gx + 1, W / 2, -0.5)``,
which is reproduced by computing it in float64 and rounding once (exact for float32 grids);
the weights are then identical and the blend differs from ``grid_sample`` by float32 rounding
(one or two ulps: ``grid_sample`` blends with fused multiply-adds too). Nearest sampling
gathers one texel, exact for any dtype (integer labels).

The per-pixel loops are C++ (``csrc/fastsample.cpp``, built on first use by
:mod:`omniscape_torch.native`): one pass per call computes every pixel's taps (or reads them
from the table), blends the interior pixels and reads the edge pixels' taps through the ring,
straight into the output. The torch maths below is their specification and, where no C++
compiler is found, the fallback (eager, a warning once; see :func:`compile_failures`).

CPU only; other devices keep ``grid_sample``. Timings: ``benchmarks/bench_projection.py``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
from torch import Tensor

from . import memory, extension as native
from ..cubemap.atlas import atlas_to_faces
from ..cubemap.padding import border_plan, check_cubemap
from ..cubemap.grid import _CASES, _ZERO_CASE, rotated_rays_to_grid
from ..cubemap.grid import _check_inputs as _check_rays
from .reference import unnormalize

__all__ = ["CubeLUT", "build_lut", "sample_cube", "sample_rays", "reads_rays", "sample_atlas",
           "compile_failures", "holds", "MODES", "BORDERS"]

MODES = ("nearest", "bilinear")
#: How the atlas border is filled: resampled from the neighbours with the ``"bilinear"`` or
#: ``"nearest"`` border plan, ``"copied"`` from the face's own edge texels, or no border
#: (``pad = 0``).
BORDERS = ("bilinear", "nearest", "copied")
#: Codes of the lookup table's ``base`` for pixels that do not read 4 interior texels.
_OUTSIDE, _EDGE = -1, -2
#: The integer dtype of a lookup table's entries per grid dtype: as wide as the fractions.
_ENTRY = {torch.float32: torch.int32, torch.float64: torch.int64}


@dataclass(frozen=True)
class CubeLUT:
    """Lookup table of a grid for one cube layout (see :func:`build_lut`).

    Attributes:
        mode: ``"nearest"`` or ``"bilinear"``.
        face_size: ``F``. pad: the atlas border ``p`` the grid was made for.
        face_stride: elements between faces of one channel in the cube (``C F F`` for a
            contiguous cube).
        table: ``(B', P, 3)``, ``P = H W``: per pixel the entry the C++ kernel reads, its
            code (``base``) and the bits of its two fractions (``frac``) side by side; int32
            for a float32 grid, int64 for a float64 one.
        grid: ``(B', P, 2)`` the grid (the edge pixels are resampled from it).
        size: ``(H, W)``.
    """

    mode: str
    face_size: int
    pad: int
    face_stride: int
    table: Tensor
    grid: Tensor
    size: tuple[int, int]

    @property
    def base(self) -> Tensor:
        """``(B', P)``: per pixel the offset of the top-left tap (nearest: the texel) within
        one sample of the cube, or -1 (all taps outside the atlas: 0) or -2 (an edge pixel)."""
        return self.table[..., 0]

    @property
    def frac(self) -> Tensor:
        """``(2, B', P)`` in the grid's dtype: the bilinear fractions ``(x - floor x, y - floor
        y)`` (unused for nearest)."""
        return self.table[..., 1:].view(self.grid.dtype).permute(2, 0, 1)


def _table(base: Tensor, fx: Tensor, fy: Tensor) -> Tensor:
    """The entries ``(B', P, 3)`` of :class:`CubeLUT` from codes and fractions (float32 or
    float64)."""
    entry = _ENTRY[fx.dtype]
    return torch.stack((base.to(entry), fx.view(entry), fy.view(entry)), -1)


# ------------------------------------------------------------------------------------------
# The maths: the specification of the C++ kernels, and their fallback
# ------------------------------------------------------------------------------------------

def _lut_math(grid: Tensor, face_size, pad, face_stride, bilinear: bool):
    """``grid (B', P, 2)`` -> ``base (B', P)`` int32 and fractions ``x - x0``, ``y - y0``."""
    n = face_size + 2 * pad
    x = unnormalize(grid[..., 0], n)
    y = unnormalize(grid[..., 1], 6 * n)
    x0 = torch.floor(x) if bilinear else torch.round(x)  # round: half to even, as grid_sample
    y0 = torch.floor(y) if bilinear else torch.round(y)
    span = 1 if bilinear else 0
    # beyond the atlas by more than a texel (or NaN): outside; keeps the int casts small
    near = (x0 >= -2) & (x0 <= n + 1) & (y0 >= -2) & (y0 <= 6 * n + 1)
    j = torch.where(near, x0, -2.0).to(torch.int32)
    r = torch.where(near, y0, -2.0).to(torch.int32)
    k = torch.floor((r.to(torch.float32) + 0.5) / n).to(torch.int32)  # face of row r
    i = r - k * n
    interior = ((k >= 0) & (k < 6) & (i >= pad) & (i + span < pad + face_size)
                & (j >= pad) & (j + span < pad + face_size))
    outside = (j + span < 0) | (j >= n) | (r + span < 0) | (r >= 6 * n)
    code = torch.where(outside, _OUTSIDE, _EDGE).to(torch.int32)
    base = torch.where(interior, k * face_stride + (i - pad) * face_size + (j - pad), code)
    return base, x - x0, y - y0


def _blend_math(src: Tensor, base: Tensor, fx: Tensor, fy: Tensor, batch: int,
                batch_stride, chan_stride, chans: int, face_size, fill: int = 0) -> Tensor:
    """Bilinear blend of ``chans`` channels: ``(batch, chans, P)``; ``fill`` where
    ``base < 0``.

    ``src`` is the flat cube; tap offsets are ``b * batch_stride + c * chan_stride + base +
    (0, 1, F, F + 1)``. Weights and their order are ``grid_sample``'s (nw, ne, sw, se).
    """
    ok = base >= 0
    off = (torch.arange(batch, device=src.device)[:, None] * batch_stride
           + torch.where(ok, base, 0))  # [B, P] int64
    e, s = 1 - fx, 1 - fy
    taps = ((0, s * e), (1, s * fx), (face_size, fy * e), (face_size + 1, fy * fx))
    outs = []
    for c in range(chans):
        acc = None
        for shift, weight in taps:
            term = src[off + (c * chan_stride + shift)] * weight
            acc = term if acc is None else acc + term
        outs.append(torch.where(ok, acc, fill))
    return torch.stack(outs, 1)


def _gather_math(src: Tensor, base: Tensor, batch: int, batch_stride, chan_stride,
                 chans: int, fill: int = 0) -> Tensor:
    """Nearest: the texel at ``base`` of ``chans`` channels, ``(batch, chans, P)``, any dtype
    (exact); ``fill`` where ``base < 0``."""
    ok = base >= 0
    off = (torch.arange(batch, device=src.device)[:, None] * batch_stride
           + torch.where(ok, base, 0))
    fill = torch.tensor(fill, device=src.device).to(src.dtype)
    return torch.stack([torch.where(ok, src[off + c * chan_stride], fill)
                        for c in range(chans)], 1)


def compile_failures() -> dict[tuple, str]:
    """Why the fast sampler runs its eager torch maths in this process:
    ``{("native", "c++"): "Error: message"}`` when the C++ kernels could not be built
    (:mod:`omniscape_torch.native`); empty when they work (or were not needed yet)."""
    return {} if native.failure() is None else {("native", "c++"): native.failure()}


# ------------------------------------------------------------------------------------------
# The border ring (the padded texels) and the edge pixels
# ------------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=16)
def _ring_plan(face_size: int, pad: int, border: str, dtype: torch.dtype
               ) -> tuple[Tensor, Tensor | None]:
    """Sources of the ring texels, in ``border_plan`` order (row-major over ``(6, n, n)``):
    ``src (N, K)`` flat indices into ``(6, F, F)`` and ``weight (N, K)`` in ``dtype``, or None
    for one tap."""
    if border != "copied":
        plan = border_plan(face_size, pad, border)
        return plan.src_index, (None if border == "nearest" else plan.weight.to(dtype))
    n = face_size + 2 * pad
    t = torch.arange(n)
    inside = (t >= pad) & (t < pad + face_size)
    ring = ~(inside[:, None] & inside[None, :])
    i, j = torch.nonzero(ring, as_tuple=True)
    face = torch.arange(6).repeat_interleave(i.numel())
    src_i, src_j = ((x - pad).clamp(0, face_size - 1).repeat(6) for x in (i, j))
    return ((face * face_size + src_i) * face_size + src_j).unsqueeze(1), None


def _ring_position(k: Tensor, i: Tensor, j: Tensor, face_size: int, pad: int) -> Tensor:
    """Index among the ring texels (row-major over ``(6, n, n)``) of padded texel ``(k, i, j)``."""
    n, f = face_size + 2 * pad, face_size
    top = i * n + j
    middle = pad * n + (i - pad) * 2 * pad + torch.where(j < pad, j, j - f)
    bottom = pad * n + f * 2 * pad + (i - pad - f) * n + j
    pos = torch.where(i < pad, top, torch.where(i < pad + f, middle, bottom))
    return k * (n * n - f * f) + pos


@functools.lru_cache(maxsize=16)
def _ring_offsets(face_size: int, pad: int, border: str, dtype: torch.dtype, face_stride: int
                  ) -> tuple[Tensor, Tensor | None]:
    """:func:`_ring_plan` as offsets within one sample and channel of a cube of
    ``face_stride``; no ring (one dummy texel) without a border. Weights are None for one-tap
    plans and for integer cubes (nearest)."""
    if pad == 0:
        return torch.zeros(1, 1, dtype=torch.long), None
    ring_dtype = dtype if dtype.is_floating_point else torch.float64
    src, weight = _ring_plan(face_size, pad, border, ring_dtype)
    f2 = face_size * face_size
    offsets = torch.div(src, f2, rounding_mode="floor") * face_stride + src % f2
    if weight is None or not dtype.is_floating_point:
        return offsets, None
    # each row's nonzero weights first, in their order (the kernel stops at a row's first zero)
    order = torch.sort((weight == 0).to(torch.uint8), dim=1, stable=True).indices
    return offsets.gather(1, order), weight.gather(1, order)


def _ring_math(src: Tensor, ring_src: Tensor, ring_weight: Tensor | None, batch: int,
               batch_stride, chan_stride, chans: int) -> Tensor:
    """The ring texels ``(batch, chans, N)`` of ``chans`` channels from the flat cube: ring
    texel ``t`` reads the cube at ``ring_src[t] (K,)`` (offsets within one sample and channel)
    with ``ring_weight[t]``, or its one texel where ``ring_weight`` is None (exact, any
    dtype)."""
    start = torch.arange(batch, device=src.device)[:, None, None] * batch_stride
    outs = []
    for c in range(chans):
        taps = src[start + c * chan_stride + ring_src]  # [B, N, K]
        outs.append(taps[..., 0] if ring_weight is None else (taps * ring_weight).sum(-1))
    return torch.stack(outs, 1)


def _edge_math(src: Tensor, ring: Tensor, grid: Tensor, sample: Tensor, batch_stride,
               chan_stride, chans: int, face_size, pad, face_stride, bilinear: bool) -> Tensor:
    """Values ``(E, chans)`` of the pixels at ``grid (E, 2)`` of samples ``sample (E,)``, read
    from the virtual atlas: a tap on an interior texel from the cube, on a border texel from
    ``ring (B, chans, N)`` (:func:`_ring_math`), outside the atlas 0. Taps and weights are
    those of :func:`_lut_math` and :func:`_blend_math`."""
    f, p = face_size, pad
    n = f + 2 * p
    x = unnormalize(grid[:, 0], n)
    y = unnormalize(grid[:, 1], 6 * n)
    x0 = torch.floor(x) if bilinear else torch.round(x)
    y0 = torch.floor(y) if bilinear else torch.round(y)
    if bilinear:
        fx, fy = x - x0, y - y0
        e, s = 1 - fx, 1 - fy
        taps = ((0, 0, s * e), (1, 0, s * fx), (0, 1, fy * e), (1, 1, fy * fx))
    else:
        taps = ((0, 0, None),)
    j0, r0 = x0.to(torch.int64), y0.to(torch.int64)  # within two texels of the atlas
    read = []   # per tap: inside the atlas, interior, cube offset, ring offset, weight
    for dx, dy, weight in taps:
        j, r = j0 + dx, r0 + dy
        inside = (j >= 0) & (j < n) & (r >= 0) & (r < 6 * n)
        j, r = j.clamp(0, n - 1), r.clamp(0, 6 * n - 1)
        k = torch.div(r, n, rounding_mode="floor")
        i = r - k * n
        interior = (i >= p) & (i < p + f) & (j >= p) & (j < p + f)
        texel = k * face_stride + ((i - p) * f + (j - p)).clamp(0, f * f - 1)
        ring_at = _ring_position(k, i, j, f, p).clamp(0, ring.shape[-1] - 1)
        read.append((inside, interior, texel, ring_at, weight))
    at = sample * batch_stride
    ring_at0 = sample * ring.stride(0)
    flat_ring = ring.reshape(-1)
    zero = torch.zeros((), dtype=src.dtype, device=src.device)
    outs = []
    for c in range(chans):
        acc = None
        for inside, interior, texel, ring_at, weight in read:
            value = torch.where(interior, src[at + c * chan_stride + texel],
                                flat_ring[ring_at0 + c * ring.stride(1) + ring_at])
            value = torch.where(inside, value, zero)
            term = value if weight is None else value * weight
            acc = term if acc is None else acc + term
        outs.append(acc)
    return torch.stack(outs, 1)


# ------------------------------------------------------------------------------------------
# Public functions
# ------------------------------------------------------------------------------------------

def _check_grid(grid: Tensor, batch: int | None = None) -> None:
    """A floating ``(B', H, W, 2)`` grid, ``B'`` in ``(1, batch)`` when ``batch`` is given."""
    if not isinstance(grid, Tensor) or not grid.is_floating_point():
        raise TypeError(f"grid: expected a floating tensor (B, H, W, 2), got "
                        f"{getattr(grid, 'dtype', type(grid).__name__)}")
    if grid.dim() != 4 or grid.shape[-1] != 2 or (
            batch is not None and grid.shape[0] not in (1, batch)):
        raise ValueError(f"grid: expected shape ({'B' if batch is None else f'1 or {batch}'}, "
                         f"H, W, 2), got {tuple(grid.shape)}")


def _check_offsets(face_stride: int) -> None:
    if 6 * face_stride >= 2 ** 31:
        raise ValueError(f"cube too large for int32 offsets: face stride {face_stride}")


def _check_mode(mode: str, border: str) -> None:
    if mode not in MODES:
        raise ValueError(f"mode: expected one of {MODES}, got {mode!r}")
    if border not in BORDERS:
        raise ValueError(f"border: expected one of {BORDERS}, got {border!r}")


def build_lut(grid: Tensor, face_size: int, pad: int, mode: str = "bilinear", *,
              channels: int) -> CubeLUT:
    """Lookup table of an atlas ``grid`` for contiguous cubes ``(B, 6, channels, F, F)``.

    Build it once for a frozen camera and pass it to :func:`sample_cube` on every call.

    Args:
        grid: ``(B', H, W, 2)`` atlas grid (``cubemap.rays_to_grid``, ``align_corners=False``),
            float32 or float64 (the dtype the cube is sampled in).
        face_size: ``F``. pad: the atlas border ``p`` of the grid.
        mode: ``"nearest"`` or ``"bilinear"``.
        channels: ``C`` of the cubes it will sample.

    Returns:
        The :class:`CubeLUT`.
    """
    _check_grid(grid)
    _check_mode(mode, "bilinear")
    if isinstance(channels, bool) or not isinstance(channels, int) or channels < 1:
        raise ValueError(f"channels: expected a positive int, got {channels!r}")
    face_stride = channels * face_size * face_size
    _check_offsets(face_stride)
    flat = grid.reshape(grid.shape[0], -1, 2).contiguous()
    bilinear = mode == "bilinear"
    kernel = native.function(f"os_lut_{_SUFFIX[flat.dtype]}")
    if kernel is not None:
        table = torch.empty((*flat.shape[:2], 3), dtype=_ENTRY[flat.dtype])
        kernel(flat.data_ptr(), flat.shape[0] * flat.shape[1], face_size, pad, face_stride,
               bilinear, table.data_ptr(), native.threads())
    else:
        table = _table(*_lut_math(flat, face_size, pad, face_stride, bilinear))
    return CubeLUT(mode, face_size, pad, face_stride, table, flat, tuple(grid.shape[1:3]))


_SUFFIX = {torch.float32: "f32", torch.float64: "f64"}


def _kernel(kind: str, dtype: torch.dtype, grid_dtype: torch.dtype):
    """The C++ kernel ``os_sample_{kind}`` for cubes of ``dtype`` (a floating cube is sampled
    with a grid of its dtype; any other is copied by element size), or None."""
    if dtype.is_floating_point:
        suffix = _SUFFIX.get(dtype)
    else:
        size = torch.empty((), dtype=dtype).element_size()
        suffix = f"{size}_{_SUFFIX[grid_dtype]}" if size in (1, 2, 4, 8) else None
    return None if suffix is None else native.function(f"os_sample_{kind}_{suffix}")


def _tail(faces: Tensor, mode: str, pad: int, border: str, out: Tensor, fill: int,
          width: int) -> tuple:
    """The kernels' arguments after their grid: ring, layout, fill, planes, out, threads."""
    batch, _, chans, f, _ = faces.shape
    sb, sk, sc, _, _ = faces.stride()
    ring_src, ring_weight = _ring_offsets(f, pad, border, faces.dtype, sk)
    return (ring_src.data_ptr(), None if ring_weight is None else ring_weight.data_ptr(),
            ring_src.shape[1], f, pad, sk, mode == "bilinear", fill, batch, chans, out.shape[-1],
            width, sb, sc, out.stride(0), out.stride(1), out.data_ptr(), native.threads())


def _flat(faces: Tensor) -> Tensor:
    """The elements ``faces`` spans, as one flat view (the kernels' ``src``)."""
    _check_offsets(faces.stride(1))
    span = sum((n - 1) * stride for n, stride in zip(faces.shape, faces.stride())) + 1
    return faces.as_strided((span,), (1,))


def _sample(faces: Tensor, grid: Tensor, mode: str, pad: int, border: str,
            lut: CubeLUT | None, out: Tensor, valid: Tensor | None, fill: int) -> None:
    """Sample ``faces (B, 6, C, F, F)`` (any strides with unit texel stride in a face row) into
    ``out (B, C, P = H W)`` (unit pixel stride); the pixels outside the atlas (without ``lut``,
    also those where ``valid (1 or B', P)`` is False) read ``fill``."""
    batch, _, _, f, _ = faces.shape
    sk = faces.stride(1)
    if lut is not None and ((lut.mode, lut.face_size, lut.pad, lut.face_stride) != (
            mode, f, pad, sk) or lut.base.shape[0] not in (1, batch)):
        raise ValueError(f"lut: built for (mode, F, pad, face stride, batch) = "
                         f"{(lut.mode, lut.face_size, lut.pad, lut.face_stride, lut.base.shape[0])}"
                         f", the call needs {(mode, f, pad, sk, batch)}")
    src = _flat(faces)
    bilinear = mode == "bilinear"
    floating = faces.is_floating_point()
    width = (grid.shape[2] if lut is None else lut.size[1])
    points = (grid.reshape(grid.shape[0], -1, 2) if lut is None else lut.grid).contiguous()
    if floating:
        points = points.to(faces.dtype)   # a float cube is sampled with a grid of its dtype
    kernel = _kernel("grid" if lut is None else "lut", faces.dtype, points.dtype)
    if kernel is None:
        return _sample_eager(src, faces, points, bilinear, pad, border, lut, out, valid, fill)
    tail = _tail(faces, mode, pad, border, out, fill, width)
    pixels = out.shape[-1]
    if lut is None:
        mask = None if valid is None else valid.contiguous()
        kernel(src.data_ptr(), points.data_ptr(), 0 if points.shape[0] == 1 else 2 * pixels,
               None if mask is None else mask.data_ptr(),
               0 if mask is None or mask.shape[0] == 1 else pixels, *tail)
    else:
        table = lut.table
        if table.dtype != _ENTRY[points.dtype]:   # a table of another grid dtype: converted
            frac = lut.frac.to(points.dtype)
            table = _table(lut.base, frac[0], frac[1])
        kernel(src.data_ptr(), table.data_ptr(), points.data_ptr(),
               0 if table.shape[0] == 1 else pixels, *tail)


@functools.lru_cache(maxsize=1)
def _check_face_table() -> None:
    """The C++ kernel's copy of the face table must be ``cubemap.faces``' (via fastgrid)."""
    table = torch.zeros(35, dtype=torch.int32)
    native.function("os_face_cases")(table.data_ptr())
    expected = [v for case in (*_CASES, _ZERO_CASE) for v in case]
    if table.tolist() != expected:
        raise RuntimeError(f"csrc/fastsample.cpp: its face table {table.tolist()} is not "
                           f"cubemap.faces' {expected}; update kCases")


def _rays_kernel(dtype: torch.dtype, rays_dtype: torch.dtype):
    """The C++ kernel that samples a cube of (working) ``dtype`` through rays of
    ``rays_dtype``, or None: it computes the grid in the rays' dtype, which must be the grid's
    (the cube's floating dtype, float32 for other cubes)."""
    grid_dtype = dtype if dtype.is_floating_point else torch.float32
    kernel = _kernel("rays", dtype, grid_dtype) if rays_dtype == grid_dtype else None
    if kernel is not None:
        _check_face_table()
    return kernel


def reads_rays(dtype: torch.dtype, rays_dtype: torch.dtype) -> bool:
    """Whether :func:`sample_rays` samples a cube of ``dtype`` through rays of ``rays_dtype``
    without building their grid first."""
    half = dtype.is_floating_point and dtype not in (torch.float32, torch.float64)
    return _rays_kernel(torch.float32 if half else dtype, rays_dtype) is not None


def _sample_rays(faces: Tensor, rays: Tensor, rotation: Tensor | None, mode: str, pad: int,
                 border: str, out: Tensor, valid: Tensor | None, fill: int) -> None:
    """:func:`_sample` of the grid of ``rays (Br, H, W, 3)`` rotated by ``rotation (Bq, 3, 3)``:
    computed in the sampling pass where the C++ kernel runs (:func:`_rays_kernel`), else built
    first."""
    kernel = _rays_kernel(faces.dtype, rays.dtype)
    if kernel is None:   # without a C++ compiler nothing compiles: the eager grid then
        grid_dtype = faces.dtype if faces.is_floating_point() else torch.float32
        grid = rotated_rays_to_grid(rays, rotation, faces.shape[-1], pad, dtype=grid_dtype,
                                    compiled=native.library() is not None)
        return _sample(faces, grid, mode, pad, border, None, out, valid, fill)
    rays = rays.contiguous()
    rot = None if rotation is None else rotation.to(rays.dtype).contiguous()
    mask = None if valid is None else valid.contiguous()
    pixels = out.shape[-1]
    kernel(_flat(faces).data_ptr(), rays.data_ptr(), 0 if rays.shape[0] == 1 else 3 * pixels,
           None if rot is None else rot.data_ptr(), 0 if rot is None or rot.shape[0] == 1 else 9,
           None if mask is None else mask.data_ptr(),
           0 if mask is None or mask.shape[0] == 1 else pixels,
           *_tail(faces, mode, pad, border, out, fill, rays.shape[2]))


def _sample_eager(src: Tensor, faces: Tensor, points: Tensor, bilinear: bool, pad: int,
                  border: str, lut: CubeLUT | None, out: Tensor, valid: Tensor | None,
                  fill: int) -> None:
    """:func:`_sample` in torch: every pixel's taps, then the edge pixels through the ring."""
    batch, _, chans, f, _ = faces.shape
    sb, sk, sc, _, _ = faces.stride()
    if lut is None:
        if valid is not None:   # invalid pixels outside the atlas: they read 0
            points = torch.where(valid.unsqueeze(-1), points, -2.0)
        base, fx, fy = _lut_math(points, f, pad, sk, bilinear)
    else:
        base = lut.base
        fx, fy = lut.frac.to(faces.dtype) if bilinear else (None, None)
    out.copy_(_blend_math(src, base, fx, fy, batch, sb, sc, chans, f, fill) if bilinear else
              _gather_math(src, base, batch, sb, sc, chans, fill))
    edge = torch.nonzero(base == _EDGE)
    if not edge.numel():
        return
    sample, pixel = edge.unbind(1)
    if base.shape[0] == 1 and batch > 1:  # one grid for the whole batch
        pixel = pixel.repeat(batch)
        sample = torch.arange(batch).repeat_interleave(edge.shape[0])
    at = points[edge[:, 0], edge[:, 1]].repeat(len(sample) // len(edge), 1)
    ring_src, ring_weight = _ring_offsets(f, pad, border, faces.dtype, sk)
    ring = _ring_math(src, ring_src, ring_weight, batch, sb, sc, chans)
    out[sample, :, pixel] = _edge_math(src, ring, at, sample, sb, sc, chans, f, pad, sk,
                                       bilinear)


def sample_cube(cubemap: Tensor, grid: Tensor, mode: str = "bilinear", *, pad: int,
                border: str = "bilinear", lut: CubeLUT | None = None,
                out: Tensor | None = None, valid: Tensor | None = None, fill: int = 0
                ) -> Tensor:
    """``grid_sample`` of the padded atlas of a cube, without building the atlas; forward only.

    Equal, to float32 rounding, to ``F.grid_sample(cubemap_to_atlas(cubemap, pad, border),
    grid, mode, padding_mode="zeros", align_corners=False)`` (``border="copied"``: every face
    padded with its own edge texels; ``pad=0``: no border). Nearest sampling is exact for any
    dtype (integer labels). Nothing is recorded for autograd: use ``grid_sample`` where a
    gradient is needed.

    Args:
        cubemap: ``(B, 6, C, F, F)`` on the CPU: float32 or float64 (half precision is sampled
            in float32), or any dtype for ``"nearest"``.
        grid: ``(B' in {1, B}, H, W, 2)`` atlas grid (``cubemap.rays_to_grid``), floating.
        mode: ``"nearest"`` or ``"bilinear"``.
        pad: the atlas border ``p`` the grid was made for.
        border: ``"bilinear"`` or ``"nearest"`` (the border resampled from the neighbouring
            faces with that ``cubemap.border_plan``), or ``"copied"``.
        lut: a :func:`build_lut` of ``grid`` for this layout (a frozen camera), else built here.
        out: ``(B, C, H, W)`` in the cubemap's dtype to write the image into (any batch and
            channel strides, each ``H x W`` plane contiguous), e.g. part of a larger batch.
        valid: ``(1 or B', H, W)`` bool, without ``lut``: the pixels where it is False read
            ``fill``, as if their grid pointed outside the atlas (so the caller need not move
            them there first).
        fill: the value of the pixels whose taps all lie outside the atlas (``grid_sample``'s
            zero padding: 0), e.g. the ignore index of labels; an int that the cubemap's dtype
            holds.

    Returns:
        ``(B, C, H, W)`` in the cubemap's dtype (``out`` when given); ``fill`` where every tap
        is outside the atlas.
    """
    check_cubemap(cubemap)
    _check_grid(grid, cubemap.shape[0])
    if grid.device.type != "cpu":
        raise ValueError(f"grid: the fast path runs on the CPU, got {grid.device}")
    if valid is not None and lut is not None:
        raise ValueError("valid: only without lut (build the table from a grid whose "
                         "invalid pixels lie outside the atlas)")

    def sample(work: Tensor, into: Tensor, mask: Tensor | None) -> None:
        points = grid.to(work.dtype) if work.is_floating_point() else grid
        _sample(work, points, mode, pad, border, lut, into, mask, fill)

    return _run(cubemap, grid.shape[0], tuple(grid.shape[1:3]), mode, border, out, valid, fill,
                sample)


def sample_rays(cubemap: Tensor, rays: Tensor, rotation: Tensor | None = None,
                mode: str = "bilinear", *, pad: int, border: str = "bilinear",
                out: Tensor | None = None, valid: Tensor | None = None, fill: int = 0
                ) -> Tensor:
    """:func:`sample_cube` through the grid of camera-frame ``rays`` rotated into the cube
    frame, without storing the grid.

    Equal, bit for bit, to ``sample_cube(cubemap, fastgrid.rotated_rays_to_grid(rays,
    rotation, F, pad, dtype=...), ...)`` with the grid in the cube's floating dtype (float32
    for an integer cube): the C++ kernel computes each pixel's grid point in the sampling pass,
    with the operations of the compiled ``rotated_rays_to_grid`` in the same order, and reads
    the cube straight away, so a grid used once (a new rotation per call) costs no pass over
    memory of its own. Where the kernel does not apply (no compiler, or rays in another dtype
    than the grid's) the grid is built first.

    Args:
        cubemap: ``(B, 6, C, F, F)`` on the CPU, as for :func:`sample_cube`.
        rays: ``(Br, H, W, 3)`` (``Br`` 1 or ``B``) or ``(H, W, 3)`` camera-frame directions.
        rotation: ``(Bq, 3, 3)`` (``Bq`` 1 or ``B``) or ``(3, 3)`` camera -> cube frame, or None.
        mode, pad, border, out, fill: as for :func:`sample_cube`.
        valid: ``(1 or max(Br, Bq), H, W)`` bool: the pixels where it is False read ``fill``.

    Returns:
        ``(B, C, H, W)`` in the cubemap's dtype (``out`` when given).
    """
    check_cubemap(cubemap)
    batch = cubemap.shape[0]
    rays, rotation, _ = _check_rays(rays, rotation, cubemap.shape[-1], pad, None)
    points = max(rays.shape[0], 1 if rotation is None else rotation.shape[0])
    if points not in (1, batch):
        raise ValueError(f"rays, rotation: batch {points} does not match the cubemap's {batch}")
    if rays.device.type != "cpu":
        raise ValueError(f"rays: the fast path runs on the CPU, got {rays.device}")

    def sample(work: Tensor, into: Tensor, mask: Tensor | None) -> None:
        _sample_rays(work, rays, rotation, mode, pad, border, into, mask, fill)

    return _run(cubemap, points, tuple(rays.shape[1:3]), mode, border, out, valid, fill, sample)


def _run(cubemap: Tensor, points: int, size: tuple[int, int], mode: str, border: str,
         out: Tensor | None, valid: Tensor | None, fill: int, sample) -> Tensor:
    """What :func:`sample_cube` and :func:`sample_rays` share, after their ``check_cubemap``:
    the checks of the cube's device and dtype, of ``out``, ``valid`` (``points``: the grid's
    batch) and ``fill``; the cube in a dtype and layout the kernels read; then ``sample(work,
    into (B, C, H W), valid (1 or B', H W) or None)``."""
    _check_mode(mode, border)
    if cubemap.device.type != "cpu":
        raise ValueError(f"cubemap: the fast path runs on the CPU, got {cubemap.device}")
    if mode == "bilinear" and not cubemap.is_floating_point():
        raise TypeError(f"cubemap: bilinear sampling needs a floating cubemap, got "
                        f"{cubemap.dtype}")
    half = cubemap.is_floating_point() and cubemap.dtype not in (torch.float32, torch.float64)
    f = cubemap.shape[-1]
    rows_ok = cubemap.stride(-1) == 1 and (cubemap.stride(-2) == f or f == 1)
    work = cubemap.float() if half else (cubemap if rows_ok else cubemap.contiguous())
    batch, chans = cubemap.shape[0], cubemap.shape[2]
    if out is not None:
        _check_out(out, (batch, chans, *size), cubemap.dtype)
    _check_fill(fill, cubemap.dtype)
    if valid is not None:
        if (not isinstance(valid, Tensor) or valid.dtype != torch.bool or valid.dim() != 3
                or valid.shape[0] not in (1, points) or valid.shape[1:] != size):
            raise ValueError(f"valid: expected a bool tensor of shape (1 or {points}, "
                             f"{size[0]}, {size[1]}), got "
                             f"{getattr(valid, 'dtype', type(valid).__name__)} "
                             f"{tuple(getattr(valid, 'shape', ()))}")
        valid = valid.reshape(valid.shape[0], -1)
    into = out if out is not None and out.dtype == work.dtype else None
    if into is None:
        into = memory.empty((batch, chans, *size), work.dtype)
    with torch.no_grad():
        sample(work, into.flatten(2), valid)
    if out is None:
        return into.to(cubemap.dtype)
    if into is not out:
        out.copy_(into)
    return out


def holds(dtype: torch.dtype, value: int) -> bool:
    """Whether ``dtype`` holds the int ``value`` (a ``fill`` of :func:`sample_cube`)."""
    if dtype.is_complex:
        return value == 0   # complex elements are copied as bits: only 0 is a fill
    if dtype == torch.bool:
        return value in (0, 1)
    info = torch.finfo(dtype) if dtype.is_floating_point else torch.iinfo(dtype)
    return info.min <= value <= info.max


def _check_fill(fill: int, dtype: torch.dtype) -> None:
    if isinstance(fill, bool) or not isinstance(fill, int):
        raise TypeError(f"fill: expected an int, got {type(fill).__name__}")
    if not holds(dtype, fill):
        raise ValueError(f"fill: {fill} does not fit in the cubemap's dtype {dtype}")


def _check_out(out: Tensor, shape: tuple[int, ...], dtype: torch.dtype) -> None:
    if not isinstance(out, Tensor) or out.dtype != dtype or out.device.type != "cpu":
        raise TypeError(f"out: expected a CPU tensor of {dtype}, got "
                        f"{getattr(out, 'dtype', type(out).__name__)} on "
                        f"{getattr(out, 'device', '-')}")
    if tuple(out.shape) != shape or out.stride(-1) != 1 or out.stride(-2) != shape[-1]:
        raise ValueError(f"out: expected shape {shape} with contiguous rows and images, got "
                         f"{tuple(out.shape)} with strides {out.stride()}")


def sample_atlas(atlas: Tensor, grid: Tensor, mode: str = "bilinear") -> Tensor:
    """``F.grid_sample(atlas, grid, mode, padding_mode="zeros", align_corners=False)`` of an
    atlas ``(B, C, 6 n, n)``, forward only, to float32 rounding (nearest: exactly, any dtype).

    Args:
        atlas: ``(B, C, 6 n, n)`` on the CPU (``cubemap_to_atlas``), contiguous.
        grid: ``(B' in {1, B}, H, W, 2)`` floating.
        mode: ``"nearest"`` or ``"bilinear"``.

    Returns:
        ``(B, C, H, W)``.
    """
    faces = atlas_to_faces(atlas.contiguous())  # (B, 6, C, n, n) view: an atlas without border
    return sample_cube(faces, grid, mode, pad=0)
