"""Forward-only fast sampling of a cube through an atlas grid: the paper's lookup table.

``OmniProjection``'s reference path pads the cube into an atlas (a copy of every texel) and
calls ``grid_sample``. Without gradients the same image is computed here with no atlas at all:

    grid (B', H, W, 2) --> per pixel the flat offset of its top-left tap in the cube
        (B, 6, C, F, F) and its two bilinear fractions (nearest: the offset of its texel)
    image = 4 taps per channel gathered from the cube and blended

For a frozen camera the offsets and fractions are a lookup table, built once
(:func:`build_lut`) and read on every call; for a grid used once (a rotation per call) they are
computed in the sampling pass itself and never stored.

A pixel whose taps are not all interior texels of one face ("edge" pixels: within a texel of
a seam, about 1% of them) reads the atlas border, which the cube does not hold: those few
pixels are sampled afterwards from a virtual atlas, the cube's interior plus its ring of border
texels, computed from the border plan exactly as
:func:`~omniscape_torch.cubemap.cubemap_to_atlas` computes them. Pixels whose taps all lie
outside the atlas (the invalid ones, grid ``(-2, -2)``) read 0, as with zero padding.

The pixel coordinates are those of ``grid_sample`` (``align_corners=False``) bit for bit:
PyTorch's CPU kernel unnormalises with a fused multiply-add, ``x = fma(gx + 1, W / 2, -0.5)``,
which is reproduced by computing it in float64 and rounding once (exact for float32 grids);
the weights are then identical and the blend differs from ``grid_sample`` by float32 rounding
(one or two ulps: ``grid_sample`` blends with fused multiply-adds too). Nearest sampling
gathers one texel, exact for any dtype (integer labels).

Every step runs in a ``torch.compile`` (inductor) kernel, compiled on first use per (step,
dtype) for any size; where compilation is unavailable or fails the same maths runs eagerly (a
warning, once; see :func:`compile_failures`).

CPU only; other devices keep ``grid_sample``. Timings: ``benchmarks/bench_projection.py``.
"""

from __future__ import annotations

import functools
import threading
import warnings
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from .cubemap.atlas import atlas_to_faces
from .cubemap.padding import border_plan, check_cubemap
from .fastgrid import COMPILE_OPTIONS, _fresh_copy, in_dataloader_worker
from .sampling import unnormalize

__all__ = ["CubeLUT", "build_lut", "sample_cube", "sample_atlas", "compile_failures",
           "MODES", "BORDERS"]

MODES = ("nearest", "bilinear")
#: How the atlas border is filled: resampled from the neighbours with the ``"bilinear"`` or
#: ``"nearest"`` border plan, ``"copied"`` from the face's own edge texels, or no border
#: (``pad = 0``).
BORDERS = ("bilinear", "nearest", "copied")
#: Codes of the lookup table's ``base`` for pixels that do not read 4 interior texels.
_OUTSIDE, _EDGE = -1, -2
#: Channels per kernel call (the kernel is unrolled over them): more channels take several calls.
_CHUNK = 4
#: Inductor options: the indices are in bounds by construction (no per-tap bounds check), and
#: the loop is vectorised although it is gather-heavy (measured faster).
_OPTIONS = {**COMPILE_OPTIONS, "assert_indirect_indexing": False,
            "cpp.enable_tiling_heuristics": False}


@dataclass(frozen=True)
class CubeLUT:
    """Lookup table of a grid for one cube layout (see :func:`build_lut`).

    Attributes:
        mode: ``"nearest"`` or ``"bilinear"``.
        face_size: ``F``. pad: the atlas border ``p`` the grid was made for.
        face_stride: elements between faces of one channel in the cube (``C F F`` for a
            contiguous cube).
        base: ``(B', P)`` int32, ``P = H W``: per pixel the offset of the top-left tap
            (nearest: the texel) within one sample of the cube, or -1 (all taps outside the
            atlas: 0) or -2 (an edge pixel).
        frac: ``(2, B', P)`` the bilinear fractions ``(x - floor x, y - floor y)`` (empty for
            nearest).
        edge: ``(E, 2)`` int64, the ``(b', p)`` of the edge pixels.
        grid: ``(B', P, 2)`` the grid (the edge pixels are resampled from it).
        size: ``(H, W)``.
    """

    mode: str
    face_size: int
    pad: int
    face_stride: int
    base: Tensor
    frac: Tensor
    edge: Tensor
    grid: Tensor
    size: tuple[int, int]


# ------------------------------------------------------------------------------------------
# The maths (compiled, or run eagerly as the fallback)
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
                batch_stride, offset, chan_stride, chans: int, face_size) -> Tensor:
    """Bilinear blend of ``chans`` channels: ``(batch, chans, P)``; 0 where ``base < 0``.

    ``src`` is the flat cube; tap offsets are ``b * batch_stride + offset + c * chan_stride +
    base + (0, 1, F, F + 1)``. Weights and their order are ``grid_sample``'s (nw, ne, sw, se).
    """
    ok = base >= 0
    off = (torch.arange(batch, device=src.device)[:, None] * batch_stride + offset
           + torch.where(ok, base, 0))  # [B, P] int64
    e, s = 1 - fx, 1 - fy
    taps = ((0, s * e), (1, s * fx), (face_size, fy * e), (face_size + 1, fy * fx))
    outs = []
    for c in range(chans):
        acc = None
        for shift, weight in taps:
            term = src[off + (c * chan_stride + shift)] * weight
            acc = term if acc is None else acc + term
        outs.append(torch.where(ok, acc, 0))
    return torch.stack(outs, 1)


def _gather_math(src: Tensor, base: Tensor, batch: int, batch_stride, offset, chan_stride,
                 chans: int) -> Tensor:
    """Nearest: the texel at ``base`` of ``chans`` channels, ``(batch, chans, P)``, any dtype
    (exact); 0 where ``base < 0``."""
    ok = base >= 0
    off = (torch.arange(batch, device=src.device)[:, None] * batch_stride + offset
           + torch.where(ok, base, 0))
    zero = torch.zeros((), dtype=src.dtype, device=src.device)
    return torch.stack([torch.where(ok, src[off + c * chan_stride], zero)
                        for c in range(chans)], 1)


def _direct_math(src: Tensor, grid: Tensor, batch: int, batch_stride, offset, chan_stride,
                 chans: int, face_size, pad, face_stride, bilinear: bool):
    """A grid used once: the table and the sampling in one pass, never stored. Returns the
    image ``(batch, chans, P)`` (0 at the pixels that are not interior) and ``base`` (its
    codes tell the edge pixels)."""
    base, fx, fy = _lut_math(grid, face_size, pad, face_stride, bilinear)
    if bilinear:
        out = _blend_math(src, base, fx, fy, batch, batch_stride, offset, chan_stride, chans,
                          face_size)
    else:
        out = _gather_math(src, base, batch, batch_stride, offset, chan_stride, chans)
    return out, base


# ------------------------------------------------------------------------------------------
# Compilation, with the eager fallback
# ------------------------------------------------------------------------------------------

_COMPILED: dict[tuple, Callable | None] = {}
_FAILURES: dict[tuple, str] = {}
_LOCK = threading.Lock()


def compile_failures() -> dict[tuple, str]:
    """The compilations that failed in this process: ``{(kernel, dtype): "Error: message"}``;
    empty when every compilation worked (or none was tried)."""
    return dict(_FAILURES)


def _fail(key: tuple, exc: BaseException) -> None:
    _COMPILED[key] = None
    _FAILURES[key] = f"{type(exc).__name__}: {exc}"
    first = str(exc).strip().splitlines()[0][:300] if str(exc).strip() else ""
    warnings.warn(f"fastsample: torch.compile failed ({key[0]}, {key[1]}): "
                  f"{type(exc).__name__}: {first}. Using the eager path for these inputs from "
                  "now on (see fastsample.compile_failures()).", UserWarning, stacklevel=4)


def _call(name: str, dtype: torch.dtype, *args):
    """``_TARGETS[name](*args)``, compiled once per (name, dtype); eager after a failure."""
    if in_dataloader_worker():   # compiling in a forked worker can deadlock
        return _TARGETS[name](*args)
    key = (name, dtype)
    if key not in _COMPILED:
        with _LOCK:
            if key not in _COMPILED:
                try:
                    _COMPILED[key] = torch.compile(_fresh_copy(_TARGETS[name]), dynamic=True,
                                                   options=_OPTIONS)
                except Exception as exc:  # torch.compile unsupported here
                    _fail(key, exc)
    fn = _COMPILED[key]
    if fn is not None:
        try:
            return fn(*args)
        except torch.OutOfMemoryError:
            raise
        except Exception as exc:  # inductor, a missing C++ compiler, ...
            with _LOCK:
                _fail(key, exc)
    return _TARGETS[name](*args)


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
    return offsets, (weight if dtype.is_floating_point else None)


def _ring_math(src: Tensor, ring_src: Tensor, ring_weight: Tensor | None, batch: int,
               batch_stride, offset, chan_stride, chans: int) -> Tensor:
    """The ring texels ``(batch, chans, N)`` of ``chans`` channels from the flat cube: ring
    texel ``t`` reads the cube at ``ring_src[t] (K,)`` (offsets within one sample and channel)
    with ``ring_weight[t]``, or its one texel where ``ring_weight`` is None (exact, any
    dtype)."""
    start = torch.arange(batch, device=src.device)[:, None, None] * batch_stride + offset
    outs = []
    for c in range(chans):
        taps = src[start + c * chan_stride + ring_src]  # [B, N, K]
        outs.append(taps[..., 0] if ring_weight is None else (taps * ring_weight).sum(-1))
    return torch.stack(outs, 1)


def _edge_math(src: Tensor, ring: Tensor, grid: Tensor, sample: Tensor, batch_stride, offset,
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
    at = sample * batch_stride + offset
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


_TARGETS = {"lut": _lut_math, "blend": _blend_math, "gather": _gather_math,
            "direct": _direct_math, "ring": _ring_math, "edge": _edge_math}


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
    flat = grid.reshape(grid.shape[0], -1, 2)
    base, fx, fy = _call("lut", grid.dtype, flat, face_size, pad, face_stride,
                         mode == "bilinear")
    frac = torch.stack((fx, fy)) if mode == "bilinear" else flat.new_empty(0)
    return CubeLUT(mode, face_size, pad, face_stride, base, frac,
                   torch.nonzero(base == _EDGE), flat, tuple(grid.shape[1:3]))


def _sample(faces: Tensor, grid: Tensor, mode: str, pad: int, border: str,
            lut: CubeLUT | None) -> Tensor:
    """Sample ``faces (B, 6, C, F, F)`` (any strides with unit texel stride in a face row)."""
    batch, _, chans, f, _ = faces.shape
    sb, sk, sc, sf, _ = faces.stride()
    if lut is not None and ((lut.mode, lut.face_size, lut.pad, lut.face_stride) != (
            mode, f, pad, sk) or lut.base.shape[0] not in (1, batch)):
        raise ValueError(f"lut: built for (mode, F, pad, face stride, batch) = "
                         f"{(lut.mode, lut.face_size, lut.pad, lut.face_stride, lut.base.shape[0])}"
                         f", the call needs {(mode, f, pad, sk, batch)}")
    span = sum((size - 1) * stride for size, stride in zip(faces.shape, faces.stride())) + 1
    src = faces.as_strided((span,), (1,))
    bilinear = mode == "bilinear"
    chunks = range(0, chans, _CHUNK)  # channels per kernel call
    if lut is None:   # a grid used once: its table is computed in the sampling pass
        _check_offsets(sk)
        flat = grid.reshape(grid.shape[0], -1, 2)
        parts = [_call("direct", faces.dtype, src, flat, batch, sb, c * sc, sc,
                       min(_CHUNK, chans - c), f, pad, sk, bilinear) for c in chunks]
        base = parts[0][1]
        parts = [image for image, _ in parts]
        lut = CubeLUT(mode, f, pad, sk, base, flat.new_empty(0), torch.nonzero(base == _EDGE),
                      flat, tuple(grid.shape[1:3]))
    elif bilinear:
        fx, fy = lut.frac.to(faces.dtype)
        parts = [_call("blend", faces.dtype, src, lut.base, fx, fy, batch, sb, c * sc, sc,
                       min(_CHUNK, chans - c), f) for c in chunks]
    else:
        parts = [_call("gather", faces.dtype, src, lut.base, batch, sb, c * sc, sc,
                       min(_CHUNK, chans - c)) for c in chunks]
    out = parts[0] if len(parts) == 1 else torch.cat(parts, 1)
    if lut.edge.numel():   # the pixels next to a seam read the border: the virtual atlas
        sample, pixel = lut.edge.unbind(1)
        if lut.base.shape[0] == 1 and batch > 1:  # one grid for the whole batch
            pixel = pixel.repeat(batch)
            sample = torch.arange(batch).repeat_interleave(lut.edge.shape[0])
        points = lut.grid[lut.edge[:, 0], lut.edge[:, 1]].repeat(len(sample) // len(lut.edge), 1)
        if faces.is_floating_point():
            points = points.to(faces.dtype)
        ring_src, ring_weight = _ring_offsets(f, pad, border, faces.dtype, sk)
        for c in chunks:
            k = min(_CHUNK, chans - c)
            ring = _call("ring", faces.dtype, src, ring_src, ring_weight, batch, sb, c * sc, sc,
                         k)
            out[sample, c:c + k, pixel] = _call("edge", faces.dtype, src, ring, points, sample,
                                                sb, c * sc, sc, k, f, pad, sk, bilinear)
    return out.view(batch, chans, *lut.size)


def sample_cube(cubemap: Tensor, grid: Tensor, mode: str = "bilinear", *, pad: int,
                border: str = "bilinear", lut: CubeLUT | None = None) -> Tensor:
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

    Returns:
        ``(B, C, H, W)`` in the cubemap's dtype; 0 where every tap is outside the atlas.
    """
    check_cubemap(cubemap)
    _check_grid(grid, cubemap.shape[0])
    _check_mode(mode, border)
    if cubemap.device.type != "cpu" or grid.device.type != "cpu":
        raise ValueError(f"cubemap, grid: the fast path runs on the CPU, got {cubemap.device} "
                         f"and {grid.device}")
    if mode == "bilinear" and not cubemap.is_floating_point():
        raise TypeError(f"cubemap: bilinear sampling needs a floating cubemap, got "
                        f"{cubemap.dtype}")
    half = cubemap.is_floating_point() and cubemap.dtype not in (torch.float32, torch.float64)
    f = cubemap.shape[-1]
    rows_ok = cubemap.stride(-1) == 1 and (cubemap.stride(-2) == f or f == 1)
    work = cubemap.float() if half else (cubemap if rows_ok else cubemap.contiguous())
    if work.is_floating_point():
        grid = grid.to(work.dtype)
    with torch.no_grad():
        return _sample(work, grid, mode, pad, border, lut).to(cubemap.dtype)


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
