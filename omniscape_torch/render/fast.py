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

The cube is read as it comes: float32 and float64 blended in their precision; float16,
bfloat16 and ``uint8`` blended in float32 (``uint8`` rounded to nearest, half up as OpenCV
rounds, or written as float32 scaled to [0, 1]: :func:`output_dtypes`), any other dtype of 1,
2, 4 or 8 bytes sampled nearest (copied); through its strides, so a channels-last cube (the
faces of image files, ``(B, 6, F, F, C)`` in memory) costs no transposing copy and its image
comes back channels-last (:func:`is_channels_last`). 8-bit channels-last RGB and RGBA take a
vector path (SSE4.1: a texel's channels in one load).

The pixel coordinates are those of ``grid_sample`` (``align_corners=False``) bit for bit:
PyTorch's CPU kernel unnormalises with a fused multiply-add, ``x = fma(gx + 1, W / 2, -0.5)``,
which is reproduced by computing it in float64 and rounding once (exact for float32 grids);
the weights are then identical and the blend differs from ``grid_sample`` by float32 rounding
(one or two ulps: ``grid_sample`` blends with fused multiply-adds too). Nearest sampling
gathers one texel, exact for any dtype (integer labels).

The per-pixel loops are C++ custom ops, ``torch.ops.omniscape_torch.*``
(the headers ``csrc/sample_*.h``, the ops in ``fastsample.cpp`` and ``fastimage.cpp``, built
on first use by [extension][omniscape_torch.render.extension], one library with the town's
shading): one pass per call computes
every pixel's taps (or reads them from the table), blends the interior pixels and reads the
edge pixels' taps through the ring, straight into the output. ``torch.compile`` traces through
them (their fake implementations are registered with them). Where they cannot be built (no
C++ compiler, no ninja) the fast sampler is unavailable (:func:`available`: False after one
warning that says why, the extension's one) and ``OmniProjection`` takes its reference path,
``grid_sample`` on the padded atlas; the functions here then raise.

CPU only; other devices keep ``grid_sample``. Timings: ``benchmarks/bench_projection.py``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
from torch import Tensor

from . import extension
from .antialias import MINIFIES
from ..cubemap.atlas import atlas_to_faces
from ..cubemap.padding import border_plan, check_cubemap
from ..cubemap.grid import rotated_rays_to_grid
from ..cubemap.grid import _check_inputs as _check_rays

__all__ = ["CubeLUT", "CameraGrid", "build_lut", "camera_rays", "sample_cube", "sample_rays",
           "sample_image", "mip_image", "reproject_image", "MIPMAPPED", "reads_rays",
           "sample_atlas", "available", "unavailable_reason",
           "compile_failures", "holds", "is_channels_last", "work_dtype", "grid_dtype",
           "output_dtypes", "MODES", "BORDERS", "BLENDED"]

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
        face_size: ``F``.
        pad: the atlas border ``p`` the grid was made for.
        strides: elements between the faces, rows and texels of one channel in the cubes it
            reads (``(C F F, F, 1)`` for a contiguous cube, ``(F F C, F C, C)`` channels-last).
        table: ``(B', P, 3)``, ``P = H W``: per pixel the entry the C++ kernel reads, its
            code (``base``) and the bits of its two fractions (``frac``) side by side; int32
            for a float32 grid, int64 for a float64 one.
        grid: ``(B', P, 2)`` the grid (the edge pixels are resampled from it).
        size: ``(H, W)``.
    """

    mode: str
    face_size: int
    pad: int
    strides: tuple[int, int, int]
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
# The C++ ops, or why there are none
# ------------------------------------------------------------------------------------------

def _ops():
    """The ops, built and loaded on the first call; None (after one warning, shared with the
    town's shading: :func:`.extension.ops`) where they cannot be built."""
    return extension.ops()


def available() -> bool:
    """Whether the fast sampler runs in this process: its C++ extension is built (on the first
    call, once per machine) and loaded. False, after one ``UserWarning`` that says why
    (:func:`unavailable_reason`), where it cannot be built (no C++ compiler, no ninja)."""
    return _ops() is not None


def unavailable_reason() -> str | None:
    """Why :func:`available` is False (``"Error: message"``), else None."""
    return extension.unavailable_reason()


def compile_failures() -> dict[tuple, str]:
    """``{("extension", "fastsample"): "Error: message"}`` when the C++ extension could not be
    built in this process (:func:`available` is False); empty when it works (or was not needed
    yet)."""
    why = unavailable_reason()
    return {} if why is None else {("extension", "fastsample"): why}


def _require():
    """The ops; a RuntimeError that says why where there are none."""
    ops = _ops()
    if ops is None:
        raise RuntimeError(f"the fast sampler is unavailable ({unavailable_reason()}): use "
                           "grid_sample on the padded atlas (OmniProjection does)")
    return ops


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


@functools.lru_cache(maxsize=16)
def _ring_offsets(face_size: int, pad: int, border: str, dtype: torch.dtype,
                  strides: tuple[int, int, int]) -> tuple[Tensor, Tensor | None]:
    """:func:`_ring_plan` as offsets within one sample and channel of a cube of ``strides``
    (faces, rows, texels); no ring (one dummy texel) without a border. Weights in
    :func:`work_dtype`; None for one-tap plans and for cubes whose elements are copied."""
    if pad == 0:
        return torch.zeros(1, 1, dtype=torch.long), None
    src, weight = _ring_plan(face_size, pad, border, work_dtype(dtype))
    face, texel = torch.div(src, face_size ** 2, rounding_mode="floor"), src % face_size ** 2
    row, col = torch.div(texel, face_size, rounding_mode="floor"), texel % face_size
    offsets = face * strides[0] + row * strides[1] + col * strides[2]
    if weight is None or dtype not in BLENDED:
        return offsets, None
    # each row's nonzero weights first, in their order (the kernel stops at a row's first zero)
    order = torch.sort((weight == 0).to(torch.uint8), dim=1, stable=True).indices
    return offsets.gather(1, order), weight.gather(1, order)


# ------------------------------------------------------------------------------------------
# Public functions
# ------------------------------------------------------------------------------------------

#: Cube dtypes the kernels blend (bilinear sampling; ring texels are weighted sums), in
#: :func:`work_dtype`; the others are sampled nearest, their elements copied (exact).
BLENDED = (torch.float32, torch.float64, torch.float16, torch.bfloat16, torch.uint8)


def work_dtype(dtype: torch.dtype) -> torch.dtype:
    """What a cube of ``dtype`` is blended in and its grid computed in: float64 for float64,
    float32 for every other cube (half precision and ``uint8`` included)."""
    return torch.float64 if dtype == torch.float64 else torch.float32


def output_dtypes(dtype: torch.dtype, mode: str = "bilinear") -> tuple[torch.dtype, ...]:
    """The dtypes the kernels write a cube of ``dtype`` into: its own, and float32 for a
    ``uint8`` cube (scaled to [0, 1]) or a half-precision one; sampled nearest, a ``uint8`` cube
    (class ids, as label images hold them) also into int64 (the ids, no copy after)."""
    scaled = dtype in (torch.uint8, torch.float16, torch.bfloat16)
    ids = (torch.int64,) if mode == "nearest" and dtype == torch.uint8 else ()
    return ((dtype, torch.float32) if scaled else (dtype,)) + ids


def _strides(cube: Tensor) -> tuple[int, int, int]:
    """Elements between the faces, rows and texels of one channel of ``cube (B, 6, C, F, F)``."""
    return cube.stride(1), cube.stride(3), cube.stride(4)


def _layout_strides(channels: int, face_size: int, channels_last: bool) -> tuple[int, int, int]:
    """:func:`_strides` of a contiguous cube ``(B, 6, C, F, F)``, or ``(B, 6, F, F, C)``."""
    if channels_last:
        return face_size * face_size * channels, face_size * channels, channels
    return channels * face_size * face_size, face_size, 1


def _check_grid(grid: Tensor, batch: int | None = None) -> None:
    """A floating ``(B', H, W, 2)`` grid, ``B'`` in ``(1, batch)`` when ``batch`` is given."""
    if not isinstance(grid, Tensor) or not grid.is_floating_point():
        raise TypeError(f"grid: expected a floating tensor (B, H, W, 2), got "
                        f"{getattr(grid, 'dtype', type(grid).__name__)}")
    if grid.dim() != 4 or grid.shape[-1] != 2 or (
            batch is not None and grid.shape[0] not in (1, batch)):
        raise ValueError(f"grid: expected shape ({'B' if batch is None else f'1 or {batch}'}, "
                         f"H, W, 2), got {tuple(grid.shape)}")


def _fits(strides: tuple[int, int, int], face_size: int) -> bool:
    """Whether every texel offset within a sample and channel fits the kernels' int32 codes."""
    return 5 * strides[0] + (face_size - 1) * (strides[1] + strides[2]) < 2 ** 31


def _check_mode(mode: str, border: str) -> None:
    if mode not in MODES:
        raise ValueError(f"mode: expected one of {MODES}, got {mode!r}")
    if border not in BORDERS:
        raise ValueError(f"border: expected one of {BORDERS}, got {border!r}")


def build_lut(grid: Tensor, face_size: int, pad: int, mode: str = "bilinear", *,
              channels: int, channels_last: bool = False) -> CubeLUT:
    """Lookup table of an atlas ``grid`` for contiguous cubes ``(B, 6, channels, F, F)`` (or
    channels-last ones, ``(B, 6, F, F, channels)`` in memory).

    Build it once for a frozen camera and pass it to :func:`sample_cube` on every call.

    Args:
        grid: ``(B', H, W, 2)`` atlas grid (``cubemap.rays_to_grid``, ``align_corners=False``),
            float32 or float64 (the dtype the cube is sampled with: :func:`work_dtype`).
        face_size: ``F``.
        pad: the atlas border ``p`` of the grid.
        mode: ``"nearest"`` or ``"bilinear"``.
        channels: ``C`` of the cubes it will sample.
        channels_last: the cubes hold their channels innermost.

    Returns:
        The :class:`CubeLUT`.
    """
    _check_grid(grid)
    _check_mode(mode, "bilinear")
    if isinstance(channels, bool) or not isinstance(channels, int) or channels < 1:
        raise ValueError(f"channels: expected a positive int, got {channels!r}")
    strides = _layout_strides(channels, face_size, bool(channels_last))
    if not _fits(strides, face_size):
        raise ValueError(f"cube too large for int32 offsets: strides {strides}")
    flat = grid.reshape(grid.shape[0], -1, 2).contiguous()
    table = torch.empty((*flat.shape[:2], 3), dtype=_ENTRY[flat.dtype])
    _require().build_lut(flat, face_size, pad, list(strides), mode == "bilinear", table)
    return CubeLUT(mode, face_size, pad, strides, table, flat, tuple(grid.shape[1:3]))


def grid_dtype(dtype: torch.dtype, mode: str, given: torch.dtype) -> torch.dtype:
    """The dtype the kernels read a grid in for a cube of ``dtype``: :func:`work_dtype` where
    they blend, the ``given`` grid's (float32 or float64) where they copy."""
    blends = dtype.is_floating_point or (mode == "bilinear" and dtype in BLENDED)
    return work_dtype(dtype) if blends else given


def _sample(faces: Tensor, grid: Tensor, mode: str, pad: int, border: str,
            lut: CubeLUT | None, out: Tensor, valid: Tensor | None, fill: int) -> None:
    """Sample ``faces (B, 6, C, F, F)`` (any strides) at ``grid (B', H, W, 2)`` into ``out (B,
    C, H, W)`` (planes or channels-last pixels); the pixels outside the atlas (without ``lut``,
    also those where ``valid (1 or B', H, W)`` is False) read ``fill``."""
    batch, f = faces.shape[0], faces.shape[-1]
    strides = _strides(faces)
    if lut is not None and ((lut.mode, lut.face_size, lut.pad, lut.strides) != (
            mode, f, pad, strides) or lut.base.shape[0] not in (1, batch)):
        raise ValueError(f"lut: built for (mode, F, pad, strides, batch) = "
                         f"{(lut.mode, lut.face_size, lut.pad, lut.strides, lut.base.shape[0])}"
                         f", the call needs {(mode, f, pad, strides, batch)}")
    ops = _require()
    bilinear = mode == "bilinear"
    ring_src, ring_weight = _ring_offsets(f, pad, border, faces.dtype, strides)
    if lut is None:
        points = grid.to(grid_dtype(faces.dtype, mode, grid.dtype)).contiguous()
        ops.sample_grid(faces, points, valid, ring_src, ring_weight, pad, bilinear, fill, out)
        return
    points = lut.grid.to(grid_dtype(faces.dtype, mode, lut.grid.dtype)).contiguous()
    table = lut.table
    if table.dtype != _ENTRY[points.dtype]:   # a table of another grid dtype: converted
        frac = lut.frac.to(points.dtype)
        table = _table(lut.base, frac[0], frac[1])
    ops.sample_lut(faces, table, points, ring_src, ring_weight, pad, list(strides), bilinear,
                   fill, out)


def _samples(dtype: torch.dtype, mode: str) -> bool:
    """Whether the kernels sample a cube of ``dtype`` in ``mode``: the :data:`BLENDED` dtypes in
    both modes, any dtype of 1, 2, 4 or 8 bytes nearest (its elements copied)."""
    return dtype in BLENDED or (mode == "nearest" and torch.empty(
        (), dtype=dtype).element_size() in (1, 2, 4, 8))


def reads_rays(dtype: torch.dtype, rays_dtype: torch.dtype) -> bool:
    """Whether :func:`sample_rays` samples a cube of ``dtype`` through rays of ``rays_dtype``
    without building their grid first: the C++ op computes the grid in the rays' dtype, which
    must be :func:`work_dtype`. False where the fast sampler is unavailable."""
    return (rays_dtype == work_dtype(dtype) and _samples(dtype, "nearest")
            and available())


def _sample_rays(faces: Tensor, rays: Tensor, rotation: Tensor | None, mode: str, pad: int,
                 border: str, out: Tensor, valid: Tensor | None, fill: int) -> None:
    """:func:`_sample` of the grid of ``rays (Br, H, W, 3)`` rotated by ``rotation (Bq, 3, 3)``:
    computed in the sampling pass where the C++ op reads these rays (:func:`reads_rays`), else
    built first."""
    grid_dtype = work_dtype(faces.dtype)
    if rays.dtype != grid_dtype:   # the op would compute the grid in another dtype
        grid = rotated_rays_to_grid(rays, rotation, faces.shape[-1], pad, dtype=grid_dtype)
        return _sample(faces, grid, mode, pad, border, None, out, valid, fill)
    ops = _require()
    ring_src, ring_weight = _ring_offsets(faces.shape[-1], pad, border, faces.dtype,
                                          _strides(faces))
    rot = None if rotation is None else rotation.to(rays.dtype).contiguous()
    ops.sample_rays(faces, rays.contiguous(), rot, valid, ring_src, ring_weight, pad,
                    mode == "bilinear", fill, out)


def sample_cube(cubemap: Tensor, grid: Tensor, mode: str = "bilinear", *, pad: int,
                border: str = "bilinear", lut: CubeLUT | None = None,
                out: Tensor | None = None, valid: Tensor | None = None, fill: int = 0,
                out_dtype: torch.dtype | None = None) -> Tensor:
    """``grid_sample`` of the padded atlas of a cube, without building the atlas; forward only.

    Equal, to float32 rounding, to ``F.grid_sample(cubemap_to_atlas(cubemap, pad, border),
    grid, mode, padding_mode="zeros", align_corners=False)`` (``border="copied"``: every face
    padded with its own edge texels; ``pad=0``: no border). Nearest sampling is exact for any
    dtype (integer labels). Nothing is recorded for autograd: use ``grid_sample`` where a
    gradient is needed.

    The cube is read through its strides, so a channels-last cube (a ``(B, 6, F, F, C)`` tensor
    permuted to ``(B, 6, C, F, F)``) costs no copy, and the image comes back in the same
    layout: channels-last pixels when the cube's channels are innermost, planes otherwise.
    A ``uint8`` cube is blended in float32 and rounded to nearest (half up, as OpenCV's
    ``remap``), or written as float32 scaled to [0, 1] (``out_dtype``); float16 and bfloat16
    cubes are blended in float32 and rounded once.

    Args:
        cubemap: ``(B, 6, C, F, F)`` on the CPU, any strides: float32, float64, float16,
            bfloat16 or ``uint8`` (blended), or any dtype for ``"nearest"``.
        grid: ``(B' in {1, B}, H, W, 2)`` atlas grid (``cubemap.rays_to_grid``), floating.
        mode: ``"nearest"`` or ``"bilinear"``.
        pad: the atlas border ``p`` the grid was made for.
        border: ``"bilinear"`` or ``"nearest"`` (the border resampled from the neighbouring
            faces with that ``cubemap.border_plan``), or ``"copied"``. ``uint8`` labels:
            ``"nearest"`` (a ``uint8`` cube is an image: its border texels are blended).
        lut: a :func:`build_lut` of ``grid`` for this layout (a frozen camera), else built here.
        out: ``(B, C, H, W)`` in ``out_dtype`` to write the image into (any batch strides; each
            ``H x W`` plane contiguous, or channels-last pixels), e.g. part of a larger batch.
        valid: ``(1 or B', H, W)`` bool, without ``lut``: the pixels where it is False read
            ``fill``, as if their grid pointed outside the atlas (so the caller need not move
            them there first).
        fill: the value of the pixels whose taps all lie outside the atlas (``grid_sample``'s
            zero padding: 0), e.g. the ignore index of labels; an int that the output's dtype
            holds.
        out_dtype: the image's dtype (:func:`output_dtypes`): the cube's (default), or float32
            for a ``uint8`` cube (scaled to [0, 1]) or a half-precision one, or int64 for a
            ``uint8`` cube sampled nearest (class ids).

    Returns:
        ``(B, C, H, W)`` in ``out_dtype`` (``out`` when given); ``fill`` where every tap is
        outside the atlas.
    """
    check_cubemap(cubemap)
    _check_grid(grid, cubemap.shape[0])
    if grid.device.type != "cpu":
        raise ValueError(f"grid: the fast path runs on the CPU, got {grid.device}")
    if valid is not None and lut is not None:
        raise ValueError("valid: only without lut (build the table from a grid whose "
                         "invalid pixels lie outside the atlas)")

    def sample(work: Tensor, into: Tensor, mask: Tensor | None) -> None:
        _sample(work, grid, mode, pad, border, lut, into, mask, fill)

    return _run(cubemap, grid.shape[0], tuple(grid.shape[1:3]), mode, border, out, valid, fill,
                out_dtype, sample)


def sample_rays(cubemap: Tensor, rays: Tensor, rotation: Tensor | None = None,
                mode: str = "bilinear", *, pad: int, border: str = "bilinear",
                out: Tensor | None = None, valid: Tensor | None = None, fill: int = 0,
                out_dtype: torch.dtype | None = None) -> Tensor:
    """:func:`sample_cube` through the grid of camera-frame ``rays`` rotated into the cube
    frame, without storing the grid.

    The image of ``sample_cube(cubemap, cubemap.grid.rotated_rays_to_grid(rays, rotation, F,
    pad, dtype=work_dtype(cubemap.dtype)), ...)``, and the grid never stored: the C++ kernel
    computes each pixel's face and face pixel ``(u, v)`` in the sampling pass, with the
    operations of the compiled ``rotated_rays_to_grid`` in the same order, and reads the cube
    straight away, so a grid used once (a new rotation per call) costs no pass over memory of
    its own. Nearest sampling goes through the grid point itself (bit for bit, ties rounded as
    ``grid_sample`` rounds them); bilinear taps come from the atlas pixel ``(u + pad, v + pad +
    face n)`` directly, without the normalised grid and back (two divisions and a float64
    unnormalisation fewer per pixel: 0.6x the time of a 1024 x 1024 ``uint8`` frame), so they
    differ from the grid's image by the grid's own rounding (an ulp of a grid coordinate is up
    to ``3 n`` eps atlas rows) and lie closer to the exact image. For rays in another dtype than
    :func:`work_dtype` the grid is built first.

    Args:
        cubemap: ``(B, 6, C, F, F)`` on the CPU, as for :func:`sample_cube`.
        rays: ``(Br, H, W, 3)`` (``Br`` 1 or ``B``) or ``(H, W, 3)`` camera-frame directions.
        rotation: ``(Bq, 3, 3)`` (``Bq`` 1 or ``B``) or ``(3, 3)`` camera -> cube frame, or None.
        mode: as for :func:`sample_cube`.
        pad: as for :func:`sample_cube`.
        border: as for :func:`sample_cube`.
        out: as for :func:`sample_cube`.
        fill: as for :func:`sample_cube`.
        out_dtype: as for :func:`sample_cube`.
        valid: ``(1 or max(Br, Bq), H, W)`` bool: the pixels where it is False read ``fill``.

    Returns:
        ``(B, C, H, W)`` in ``out_dtype`` (``out`` when given).
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

    return _run(cubemap, points, tuple(rays.shape[1:3]), mode, border, out, valid, fill,
                out_dtype, sample)


def camera_grid(affine: Tensor, limits: Tensor, table: Tensor, rotation: Tensor,
                face_size: int, pad: int, image_size: tuple[int, int], dtype: torch.dtype
                ) -> tuple[Tensor, Tensor]:
    """The atlas grid ``(B, H, W, 2)`` in ``dtype`` (float32 or float64) and validity ``(B, H,
    W)`` of ``B`` radially symmetric cameras rotated by ``rotation (B, 3, 3)``, from their
    tables (``kernels.radial_table``: ``affine (B, 6)``, ``limits (B, 5)``, ``table (B, 2,
    K)``); the invalid pixels at (-2, -2). The C++ op computes each pixel's ray from its table,
    rotates it and writes its grid point, in one pass (``kernels.camera_grid``)."""
    ops = _require()
    batch = affine.shape[0]
    grid = torch.empty((batch, *image_size, 2), dtype=dtype)
    valid = torch.empty((batch, *image_size), dtype=torch.bool)
    ops.camera_grid(*(t.to("cpu", dtype).contiguous() for t in (affine, limits, table, rotation)),
                    face_size, pad, grid, valid)
    return grid, valid


def camera_rays(affine: Tensor, limits: Tensor, table: Tensor, image_size: tuple[int, int],
                dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """The camera-frame unit rays ``(B, H, W, 3)`` in ``dtype`` (float32 or float64) and
    validity ``(B, H, W)`` (domain and cones) of every pixel centre of ``B`` radially symmetric
    cameras, from their tables (``kernels.radial_table``; ``table (B, 2, K)``, or ``(1, 2, K)``
    shared by the cameras), in one pass of the C++ op."""
    tables = [t.to("cpu", dtype).contiguous() for t in (affine, limits, table)]
    batch = affine.shape[0]
    rays = torch.empty((batch, *image_size, 3), dtype=dtype)
    valid = torch.empty((batch, *image_size), dtype=torch.bool)
    _require().camera_rays(*tables, rays, valid)
    return rays, valid


class CameraGrid:
    """The atlas grid of ``B`` radially symmetric cameras, each with its rotation and cones,
    as their tables (``kernels.radial_table``) until it is read: its rays and validity are
    made on first use in one pass of the C++ op over the pixels (:func:`camera_rays`), then
    read by :func:`sample_rays`, which computes the grid inside its sampling pass (one table
    pass for every modality sampled, and no grid in memory); other samplers read
    :meth:`tensor`, built on first use. ``rows`` takes a part of the cameras without computing
    anything (a batch's tables made at once, its rays a few samples at a time).
    ``OmniProjection.render(grid=...)`` takes it (``kernels.camera_grid(..., lazy=True)`` makes
    it).

    Attributes:
        rays: ``(B, H, W, 3)`` camera-frame unit rays, in ``dtype`` (float32 or float64, the
            :func:`work_dtype` of the cubes it samples).
        valid: ``(B, H, W)`` bool: the pixels within the camera's domain and cones.
        rotation: ``(B, 3, 3)`` camera -> cube frame, in ``dtype``.
        face_size: the face size of the atlas the grid is made for.
        pad: the border of the atlas the grid is made for.
        image_size: ``(H, W)``.
    """

    def __init__(self, affine: Tensor, limits: Tensor, table: Tensor, rotation: Tensor,
                 face_size: int, pad: int, image_size: tuple[int, int], dtype: torch.dtype):
        self.tables = tuple(t.to("cpu", dtype).contiguous() for t in (affine, limits, table))
        self.rotation = rotation.to("cpu", dtype).contiguous()
        self.face_size, self.pad, self.dtype = face_size, pad, dtype
        self.image_size = tuple(image_size)
        self._rays: tuple[Tensor, Tensor] | None = None
        self._grid: Tensor | None = None

    def __len__(self) -> int:
        return self.rotation.shape[0]

    def _made(self) -> tuple[Tensor, Tensor]:
        if self._rays is None:
            self._rays = camera_rays(*self.tables, self.image_size, self.dtype)
        return self._rays

    @property
    def rays(self) -> Tensor:
        return self._made()[0]

    @property
    def valid(self) -> Tensor:
        return self._made()[1]

    def tensor(self) -> Tensor:
        """The grid ``(B, H, W, 2)``, its invalid pixels at (-2, -2) (built once)."""
        if self._grid is None:
            grid = rotated_rays_to_grid(self.rays, self.rotation, self.face_size, self.pad)
            self._grid = torch.where(self.valid.unsqueeze(-1), grid, torch.full_like(grid, -2.0))
        return self._grid

    def rows(self, start: int, stop: int) -> "CameraGrid":
        """The cameras ``start:stop``: views of what is made already, nothing computed."""
        part = object.__new__(CameraGrid)
        part.__dict__.update(vars(self))
        part.tables = tuple(t[start:stop] for t in self.tables)
        part.rotation = self.rotation[start:stop]
        part._rays = None if self._rays is None else tuple(t[start:stop] for t in self._rays)
        part._grid = None if self._grid is None else self._grid[start:stop]
        return part


def sample_image(image: Tensor, rays: Tensor, rotation: Tensor | None, intrinsics: Tensor,
                 mode: str = "bilinear", *, valid: Tensor | None = None, fill: int = 0,
                 out: Tensor | None = None, out_dtype: torch.dtype | None = None
                 ) -> tuple[Tensor, Tensor]:
    """A perspective image sampled along rays: each ray rotated into the image's pinhole camera
    and projected, ``u = fx (x / z) + cx``, ``v = fy (y / z) + cy``, then the image sampled
    there (``grid_sample(align_corners=False)`` with border padding, to float rounding of the
    pixel: ``ot.reproject``'s image of a pinhole source), in one C++ pass without a grid.

    The image is read through its strides (a channels-last ``(B, H, W, C)`` tensor permuted to
    ``(B, C, H, W)`` costs no copy and its samples come back channels-last) and in the dtypes
    of :func:`sample_cube`: ``uint8`` blended in float32 and rounded half up (or scaled to
    [0, 1], or, nearest, widened to int64 ids: :func:`output_dtypes`).

    Args:
        image: ``(B, C, H, W)`` on the CPU.
        rays: ``(1 or B, h, w, 3)`` directions (any norm) in :func:`work_dtype` of the image
            (float32 or float64 for an image sampled nearest).
        rotation: ``(1 or B, 3, 3)`` rays -> the image's camera frame, or None.
        intrinsics: ``(1 or B, 4)`` the image's pinhole ``fx, fy, cx, cy`` (pixel centres at
            integers), in the rays' dtype.
        mode: ``"nearest"`` or ``"bilinear"``.
        valid: ``(1 or B, h, w)`` bool: the rays to sample (else ``fill``).
        fill: as for :func:`sample_cube`.
        out: as for :func:`sample_cube`.
        out_dtype: as for :func:`sample_cube`.

    Returns:
        ``(B, C, h, w)`` in ``out_dtype`` (``out`` when given) and ``valid (B, h, w)``: the rays
        in front of the camera (``z > 0``) whose pixel lies in the image (``[-0.5, W - 0.5] x
        [-0.5, H - 0.5]``), and ``valid``.
    """
    _check_mode(mode, "bilinear")
    if not isinstance(image, Tensor) or image.dim() != 4:
        raise ValueError(f"image: expected a tensor (B, C, H, W), got "
                         f"{tuple(getattr(image, 'shape', ())) or type(image).__name__}")
    if image.device.type != "cpu":
        raise ValueError(f"image: the fast path runs on the CPU, got {image.device}")
    if not _samples(image.dtype, mode):
        raise TypeError(f"image: {mode} sampling needs one of {[str(d) for d in BLENDED]}"
                        f"{' (or any integer ids, nearest)' if mode == 'bilinear' else ''}, "
                        f"got {image.dtype}")
    batch, chans = image.shape[:2]
    if not isinstance(rays, Tensor) or rays.dim() != 4 or rays.shape[-1] != 3 \
            or rays.shape[0] not in (1, batch):
        raise ValueError(f"rays: expected (1 or {batch}, h, w, 3), got "
                         f"{tuple(getattr(rays, 'shape', ()))}")
    size = tuple(rays.shape[1:3])
    dtype = work_dtype(image.dtype) if image.dtype in BLENDED else rays.dtype
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"rays: expected float32 or float64, got {rays.dtype}")
    if not isinstance(intrinsics, Tensor) or intrinsics.dim() != 2 or \
            intrinsics.shape[1] != 4 or intrinsics.shape[0] not in (1, batch):
        raise ValueError(f"intrinsics: expected (1 or {batch}, 4) fx, fy, cx, cy, got "
                         f"{tuple(getattr(intrinsics, 'shape', ()))}")
    if rotation is not None and (not isinstance(rotation, Tensor) or rotation.dim() != 3 or
                                 rotation.shape[1:] != (3, 3) or
                                 rotation.shape[0] not in (1, batch)):
        raise ValueError(f"rotation: expected (1 or {batch}, 3, 3), got "
                         f"{tuple(getattr(rotation, 'shape', ()))}")
    out_dtype = _out_dtype(image.dtype, out_dtype, mode, "image")
    if out is not None:
        _check_out(out, (batch, chans, *size), out_dtype)
    _check_fill(fill, out_dtype)
    if valid is not None and (not isinstance(valid, Tensor) or valid.dtype != torch.bool or
                              valid.dim() != 3 or valid.shape[0] not in (1, batch) or
                              tuple(valid.shape[1:]) != size):
        raise ValueError(f"valid: expected a bool tensor (1 or {batch}, {size[0]}, {size[1]}), "
                         f"got {getattr(valid, 'dtype', type(valid).__name__)} "
                         f"{tuple(getattr(valid, 'shape', ()))}")
    ops = _require()
    if out is None:
        out = (torch.empty((batch, *size, chans), dtype=out_dtype).permute(0, 3, 1, 2)
               if chans > 1 and image.stride(1) == 1 else
               torch.empty((batch, chans, *size), dtype=out_dtype))
    seen = torch.empty((batch, *size), dtype=torch.bool)
    with torch.no_grad():
        ops.sample_image(image, rays.to(dtype).contiguous(),
                         None if rotation is None else rotation.to(dtype).contiguous(),
                         intrinsics.to(dtype).contiguous(),
                         None if valid is None else valid.contiguous(), mode == "bilinear",
                         fill, out, seen)
    return out, seen


#: Image dtypes :func:`mip_image` filters (the others: ``antialias.minified``).
MIPMAPPED = (torch.uint8, torch.float32, torch.float64)


def mip_image(image: Tensor, rays: Tensor, rotation: Tensor | None, intrinsics: Tensor,
              valid: Tensor, out: Tensor) -> Tensor:
    """Antialias :func:`sample_image`'s bilinear samples in place: the pixels of ``out`` whose
    footprint minifies the image are overwritten by a filter of its mip pyramid, in one C++
    pass; the others are left as they are, bit for bit.

    The footprint is :func:`~omniscape_torch.render.antialias.footprint`'s: the Jacobian
    columns ``du, dv`` of the rays' image pixels (as :func:`sample_image` projects them) by
    finite differences to the next output pixel, forward where both pixels are ``valid``,
    else backward, else 0; a pixel minifies where a column is longer than
    :data:`~omniscape_torch.render.antialias.MINIFIES` source pixels. Its value is the mean of
    4 bilinear lookups at ``(u, v) +- du / 4 +- dv / 4`` (the centres of the footprint's
    quarters) in the mip level ``k = floor(log2(rho / 2))`` (``rho``: the longer column's
    length; 0 below ``rho = 4``), whose texels (``2**k`` source pixels) are at most a
    quarter's width across, clamped to the level's edge. The pyramid (level ``k + 1`` the
    2 x 2 average of level ``k``, an odd last row or column averaged over the texels it holds;
    ``uint8`` levels rounded half up) is built per call, only to the deepest level a pixel
    reads (whole for an image of at most 4 source pixels an output pixel, where finding that
    level costs more than the levels). :func:`~omniscape_torch.render.antialias.mip_sample` is
    the same rule in PyTorch, the filter off the CPU or with gradients (``docs/augmentation.md``,
    Antialiasing).

    Args:
        image: ``(B, C, H, W)`` ``uint8``, float32 or float64 on the CPU, any strides.
        rays: as given to :func:`sample_image`.
        rotation: as given to :func:`sample_image`.
        intrinsics: as given to :func:`sample_image`.
        valid: ``(B, h, w)`` bool: the pixels :func:`sample_image` found valid (its second
            result); the footprint's differences are taken between valid pixels only.
        out: ``(B, C, h, w)`` :func:`sample_image`'s samples (``uint8`` or float32 for a
            ``uint8`` image, else the image's dtype), overwritten where the pixels minify.

    Returns:
        ``out``.
    """
    if not isinstance(image, Tensor) or image.dtype not in MIPMAPPED:
        raise TypeError(f"image: expected one of {[str(d) for d in MIPMAPPED]}, got "
                        f"{getattr(image, 'dtype', type(image).__name__)}")
    dtype = work_dtype(image.dtype)
    with torch.no_grad():
        _require().mip_image(image, rays.to(dtype).contiguous(),
                             None if rotation is None else rotation.to(dtype).contiguous(),
                             intrinsics.to(dtype).contiguous(), valid.contiguous(), MINIFIES,
                             out)
    return out


def reproject_image(image: Tensor | None, labels: Tensor | None, affine: Tensor, limits: Tensor,
                    table: Tensor, rotation: Tensor, intrinsics: Tensor, bilinear: bool,
                    minifies: float, fill: int, out: Tensor | None, out_labels: Tensor | None,
                    valid: Tensor) -> None:
    """In one call of the C++ op: :func:`camera_rays` of ``B`` radially symmetric cameras,
    :func:`sample_image` of ``image`` along them into ``out`` (its validity into ``valid``),
    :func:`mip_image` of the pixels that minify where ``minifies > 0``, and ``labels``
    sampled nearest into ``out_labels``: those functions' results in turn, bit for bit
    (``RandomReproject``'s fast path; the rays stay inside the call).

    Args:
        image: ``(B, C, H, W)`` ``uint8``, float32 or float64 on the CPU (any strides), or None.
        labels: ``(B, H, W)`` ``uint8`` or int64 ids, or None (one of ``image``, ``labels``).
        affine: ``(B, 6)``, as :func:`camera_rays` takes it (``kernels.radial_table``), in the
            rays' dtype: :func:`work_dtype` of ``image`` (float32 or float64 for labels alone).
        limits: ``(B, 5)``, likewise.
        table: ``(1 or B, 2, K)``, likewise.
        rotation: ``(1 or B, 3, 3)`` rays -> the image's camera frame, in the rays' dtype.
        intrinsics: ``(1 or B, 4)`` the image's pinhole ``fx, fy, cx, cy``, in the rays' dtype.
        bilinear: the image's samples bilinear (else nearest).
        minifies: the prefilter's threshold
            (:data:`~omniscape_torch.render.antialias.MINIFIES`), or 0: no prefilter.
        fill: the label of the pixels outside (an int).
        out: ``(B, C, h, w)`` with ``image`` (its dtype, or float32 for ``uint8``), else None.
        out_labels: ``(B, h, w)`` int64 with ``labels``, else None.
        valid: ``(B, h, w)`` bool, contiguous: written.

    Raises:
        TypeError, ValueError: naming the argument that is not as above.
    """
    if image is None and labels is None:
        raise ValueError("image, labels: pass at least one")
    if (image is None) != (out is None) or (labels is None) != (out_labels is None):
        raise ValueError("out, out_labels: expected out with image and out_labels with labels")
    # the rays' dtype: the image's work dtype; for labels alone float32 or float64 (affine's)
    dtype = getattr(affine, "dtype", None)
    dtype = dtype if dtype in (torch.float32, torch.float64) else torch.float32
    if image is not None:
        if not isinstance(image, Tensor) or image.dim() != 4 or image.device.type != "cpu":
            raise ValueError(f"image: expected a CPU tensor (B, C, H, W), got "
                             f"{tuple(getattr(image, 'shape', ())) or type(image).__name__}")
        if image.dtype not in MIPMAPPED:
            raise TypeError(f"image: expected one of {[str(d) for d in MIPMAPPED]}, got "
                            f"{image.dtype}")
        dtype = work_dtype(image.dtype)
    if labels is not None and (not isinstance(labels, Tensor) or labels.dim() != 3 or
                               labels.dtype not in (torch.uint8, torch.int64)):
        raise ValueError(f"labels: expected uint8 or int64 ids (B, H, W), got "
                         f"{getattr(labels, 'dtype', type(labels).__name__)} "
                         f"{tuple(getattr(labels, 'shape', ()))}")
    if not isinstance(valid, Tensor) or valid.dtype != torch.bool or valid.dim() != 3 or \
            not valid.is_contiguous():
        raise ValueError(f"valid: expected a contiguous bool tensor (B, h, w), got "
                         f"{getattr(valid, 'dtype', type(valid).__name__)} "
                         f"{tuple(getattr(valid, 'shape', ()))}")
    batch, size = valid.shape[0], tuple(valid.shape[1:])
    # each tensor: its first dimension's sizes allowed, the rest (None: any), as written
    for name, t, firsts, rest, want in (
            ("affine", affine, (batch,), (6,), "(B, 6)"),
            ("limits", limits, (batch,), (5,), "(B, 5)"),
            ("table", table, (1, batch), (2, None), "(1 or B, 2, K)"),
            ("rotation", rotation, (1, batch), (3, 3), "(1 or B, 3, 3)"),
            ("intrinsics", intrinsics, (1, batch), (4,), "(1 or B, 4)")):
        if not (isinstance(t, Tensor) and t.dtype == dtype and t.dim() == 1 + len(rest) and
                t.shape[0] in firsts and
                all(r is None or n == r for n, r in zip(t.shape[1:], rest))):
            raise ValueError(f"{name}: expected {dtype} {want} (B = {batch}, valid's), got "
                             f"{getattr(t, 'dtype', type(t).__name__)} "
                             f"{tuple(getattr(t, 'shape', ()))}")
    for name, t, t_out in (("image", image, out), ("labels", labels, out_labels)):
        if t is None:
            continue
        if t.shape[0] != batch:
            raise ValueError(f"{name}: {t.shape[0]} samples, valid has {batch}")
        if not isinstance(t_out, Tensor):
            raise TypeError(f"out{'' if name == 'image' else '_labels'}: expected a tensor, "
                            f"got {type(t_out).__name__}")
        mode = "bilinear" if bilinear and name == "image" else "nearest"
        _check_out(t_out if name == "image" else t_out.unsqueeze(1),
                   (batch, t.shape[1] if name == "image" else 1, *size),
                   _out_dtype(t.dtype, t_out.dtype, mode, name))
    if isinstance(minifies, bool) or not isinstance(minifies, (int, float)) or minifies < 0:
        raise ValueError(f"minifies: expected a threshold >= 0 (0: no prefilter), got "
                         f"{minifies!r}")
    if isinstance(fill, bool) or not isinstance(fill, int):
        raise TypeError(f"fill: expected an int, got {type(fill).__name__}")
    _require().reproject_image(image, labels, affine, limits, table, rotation.contiguous(),
                               intrinsics.contiguous(), bool(bilinear), float(minifies), fill,
                               out, out_labels, valid)


def is_channels_last(t: Tensor) -> bool:
    """Whether the channels of ``t (..., C, H, W)`` (a cube or an image) are its innermost
    dimension in memory (a ``(..., H, W, C)`` tensor permuted, or ``torch.channels_last``);
    the fast sampler writes the image of such a cube in the same layout."""
    return t.shape[-3] > 1 and t.stride(-3) == 1 and t.stride(-1) >= t.shape[-3]


def _run(cubemap: Tensor, points: int, size: tuple[int, int], mode: str, border: str,
         out: Tensor | None, valid: Tensor | None, fill: int, out_dtype: torch.dtype | None,
         sample) -> Tensor:
    """What :func:`sample_cube` and :func:`sample_rays` share, after their ``check_cubemap``:
    the checks of the cube's device and dtype, of ``out_dtype``, ``out``, ``valid``
    (``points``: the grid's batch) and ``fill``; the output allocated in the cube's layout;
    then ``sample(cube, into (B, C, H, W), valid (1 or B', H, W) or None)``."""
    _check_mode(mode, border)
    if cubemap.device.type != "cpu":
        raise ValueError(f"cubemap: the fast path runs on the CPU, got {cubemap.device}")
    if not _samples(cubemap.dtype, mode):
        if mode == "bilinear":
            raise TypeError(f"cubemap: bilinear sampling needs one of "
                            f"{[str(d) for d in BLENDED]}, got {cubemap.dtype}")
        raise TypeError(f"cubemap: nearest sampling copies elements of 1, 2, 4 or 8 bytes, got "
                        f"{cubemap.dtype}")
    out_dtype = _out_dtype(cubemap.dtype, out_dtype, mode, "cubemap")
    f = cubemap.shape[-1]
    if not _fits(_strides(cubemap), f):   # a view into a larger tensor: its elements copied
        cubemap = cubemap.contiguous()
        if not _fits(_strides(cubemap), f):
            raise ValueError(f"cubemap: too large for int32 offsets: {tuple(cubemap.shape)}")
    batch, chans = cubemap.shape[0], cubemap.shape[2]
    shape = (batch, chans, *size)
    interleaved = is_channels_last(cubemap)
    if out is not None:
        _check_out(out, shape, out_dtype)
    _check_fill(fill, out_dtype)
    if valid is not None:
        if (not isinstance(valid, Tensor) or valid.dtype != torch.bool or valid.dim() != 3
                or valid.shape[0] not in (1, points) or valid.shape[1:] != size):
            raise ValueError(f"valid: expected a bool tensor of shape (1 or {points}, "
                             f"{size[0]}, {size[1]}), got "
                             f"{getattr(valid, 'dtype', type(valid).__name__)} "
                             f"{tuple(getattr(valid, 'shape', ()))}")
        valid = valid.contiguous()
    _require()
    if out is None:
        out = (torch.empty((batch, *size, chans), dtype=out_dtype).permute(0, 3, 1, 2)
               if interleaved else torch.empty(shape, dtype=out_dtype))
    with torch.no_grad():
        sample(cubemap, out, valid)
    return out


def holds(dtype: torch.dtype, value: int) -> bool:
    """Whether ``dtype`` holds the int ``value`` (a ``fill`` of :func:`sample_cube`)."""
    if dtype.is_complex:
        return value == 0   # complex elements are copied as bits: only 0 is a fill
    if dtype == torch.bool:
        return value in (0, 1)
    info = torch.finfo(dtype) if dtype.is_floating_point else torch.iinfo(dtype)
    return info.min <= value <= info.max


def _out_dtype(dtype: torch.dtype, out_dtype: torch.dtype | None, mode: str, what: str
               ) -> torch.dtype:
    """The dtype of the samples of a ``what`` of ``dtype``: ``out_dtype``, by default
    ``dtype``; a ``TypeError`` where the kernels write no such samples (:func:`output_dtypes`)."""
    out_dtype = dtype if out_dtype is None else out_dtype
    if out_dtype not in output_dtypes(dtype, mode):
        raise TypeError(f"out_dtype: expected one of "
                        f"{[str(d) for d in output_dtypes(dtype, mode)]} for a {dtype} {what}, "
                        f"got {out_dtype}")
    return out_dtype


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
    width = shape[-1]
    planes = out.stride(-1) == 1
    interleaved = out.stride(1) == 1 and out.stride(-1) >= shape[1]
    if tuple(out.shape) != shape or not (planes or interleaved) or (
            out.stride(-2) != width * out.stride(-1) and shape[-2] > 1):
        raise ValueError(f"out: expected shape {shape} with contiguous rows and images (or "
                         f"channels-last pixels), got {tuple(out.shape)} with strides "
                         f"{out.stride()}")


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
