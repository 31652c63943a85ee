"""Sampling a cube through an atlas grid, a lookup table or rays: the paper's lookup table, as
the C++ ops `build_lut`, `sample_lut`, `sample_grid` and `sample_rays` beside their torch twin,
`grid_sample` on the padded atlas (`reference_sample`).

The twin pads the cube into an atlas (a copy of every texel) and calls `grid_sample`; it has
gradients and runs on any device. Without gradients on the CPU the same image is computed by
the C++ ops with no atlas at all:

    grid (B', H, W, 2) --> per pixel the flat offset of its top-left tap in the cube
        (B, 6, C, F, F) and its two bilinear fractions (nearest: the offset of its texel)
    image = 4 taps per channel gathered from the cube and blended

For a frozen camera the offsets and fractions are a lookup table, built once (`build_lut`) and
read on every call; for a grid used once they are computed in the sampling pass itself and
never stored; for camera rays under a new rotation per call (`sample_rays`) so is the grid,
from the rays.

A pixel whose taps are not all interior texels of one face ("edge" pixels: within a texel of a
seam, about 1% of them) reads the atlas border, which the cube does not hold: its taps read a
virtual atlas, the cube's interior plus its ring of border texels, each computed from the
border plan exactly as `omniscape_torch.cubemap.cubemap_to_atlas` computes them. Pixels whose
taps all lie outside the atlas (the invalid ones, grid `(-2, -2)`) read 0, as with zero
padding (or `fill`).

The cube is read as it comes: float32 and float64 blended in their precision; float16,
bfloat16 and `uint8` blended in float32 (`uint8` rounded to nearest, half up as OpenCV rounds,
or written as float32 scaled to [0, 1]: `output_dtypes`), any other dtype of 1, 2, 4 or 8
bytes sampled nearest (copied); through its strides, so a channels-last cube (the faces of
image files, `(B, 6, F, F, C)` in memory) costs no transposing copy and its image comes back
channels-last (`is_channels_last`). 8-bit channels-last RGB and RGBA take a vector path
(SSE4.1: a texel's channels in one load).

The pixel coordinates are those of `grid_sample` (`align_corners=False`) bit for bit:
PyTorch's CPU kernel unnormalises with a fused multiply-add, `x = fma(gx + 1, W / 2, -0.5)`,
which is reproduced by computing it in float64 and rounding once (exact for float32 grids);
the weights are then identical and the blend differs from `grid_sample` by float32 rounding
(one or two ulps: `grid_sample` blends with fused multiply-adds too). Nearest sampling gathers
one texel, exact for any dtype (integer labels).

`backend` (`_backend`): `"cpp"` the ops (CPU, forward only, nearest and bilinear), `"torch"`
the twin (also bicubic, and `"edge_aware"` depth), `"auto"` the ops where they can run. Timings:
`benchmarks/bench_projection.py`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
from torch import Tensor

from ...cubemap.atlas import atlas_to_faces, cubemap_to_atlas, faces_to_atlas
from ...cubemap.padding import border_plan, check_cubemap
from ...cubemap.grid import rotated_rays_to_grid
from ...cubemap.grid import _check_inputs as _check_rays
from ..reference import from_float, grid_sample, nearest_gather
from ._backend import check_backend, choose

__all__ = ["BLENDED", "BORDERS", "CubeLUT", "MODES", "REFERENCE_MODES", "atlas", "build_lut",
           "edge_aware", "grid_dtype", "holds", "is_channels_last", "output_dtypes",
           "reads_rays", "reference_sample", "sample_atlas", "sample_cube", "sample_rays",
           "work_dtype"]

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
    """Lookup table of a grid for one cube layout (see `build_lut`).

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
    """The entries ``(B', P, 3)`` of `CubeLUT` from codes and fractions (float32 or
    float64)."""
    entry = _ENTRY[fx.dtype]
    return torch.stack((base.to(entry), fx.view(entry), fy.view(entry)), -1)


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
    """`_ring_plan` as offsets within one sample and channel of a cube of ``strides``
    (faces, rows, texels); no ring (one dummy texel) without a border. Weights in
    `work_dtype`; None for one-tap plans and for cubes whose elements are copied."""
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
#: `work_dtype`; the others are sampled nearest, their elements copied (exact).
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
    """`_strides` of a contiguous cube ``(B, 6, C, F, F)``, or ``(B, 6, F, F, C)``."""
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

    Build it once for a frozen camera and pass it to `sample_cube` on every call.

    Args:
        grid: ``(B', H, W, 2)`` atlas grid (``cubemap.rays_to_grid``, ``align_corners=False``),
            float32 or float64 (the dtype the cube is sampled with: `work_dtype`).
        face_size: ``F``.
        pad: the atlas border ``p`` of the grid.
        mode: ``"nearest"`` or ``"bilinear"``.
        channels: ``C`` of the cubes it will sample.
        channels_last: the cubes hold their channels innermost.

    Returns:
        The `CubeLUT`.
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
    ops = choose("cpp", grid, what="build_lut")   # a table is what the C++ ops read
    ops.build_lut(flat, face_size, pad, list(strides), mode == "bilinear", table)
    return CubeLUT(mode, face_size, pad, strides, table, flat, tuple(grid.shape[1:3]))


def grid_dtype(dtype: torch.dtype, mode: str, given: torch.dtype) -> torch.dtype:
    """The dtype the kernels read a grid in for a cube of ``dtype``: `work_dtype` where
    they blend, the ``given`` grid's (float32 or float64) where they copy."""
    blends = dtype.is_floating_point or (mode == "bilinear" and dtype in BLENDED)
    return work_dtype(dtype) if blends else given


def _sample(ops, faces: Tensor, grid: Tensor, mode: str, pad: int, border: str,
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
    """Whether the kernels sample a cube of ``dtype`` in ``mode``: the `BLENDED` dtypes in
    both modes, any dtype of 1, 2, 4 or 8 bytes nearest (its elements copied)."""
    return dtype in BLENDED or (mode == "nearest" and torch.empty(
        (), dtype=dtype).element_size() in (1, 2, 4, 8))


def reads_rays(dtype: torch.dtype, rays_dtype: torch.dtype) -> bool:
    """Whether `sample_rays` samples a cube of ``dtype`` through rays of ``rays_dtype``
    without building their grid first: the C++ op computes the grid in the rays' dtype, which
    must be `work_dtype`."""
    return rays_dtype == work_dtype(dtype) and _samples(dtype, "nearest")


def _sample_rays(ops, faces: Tensor, rays: Tensor, rotation: Tensor | None, mode: str,
                 pad: int, border: str, out: Tensor, valid: Tensor | None, fill: int) -> None:
    """`_sample` of the grid of ``rays (Br, H, W, 3)`` rotated by ``rotation (Bq, 3, 3)``:
    computed in the sampling pass where the C++ op reads these rays (`reads_rays`), else
    built first."""
    grid_dtype = work_dtype(faces.dtype)
    if rays.dtype != grid_dtype:   # the op would compute the grid in another dtype
        grid = rotated_rays_to_grid(rays, rotation, faces.shape[-1], pad, dtype=grid_dtype)
        return _sample(ops, faces, grid, mode, pad, border, None, out, valid, fill)
    ring_src, ring_weight = _ring_offsets(faces.shape[-1], pad, border, faces.dtype,
                                          _strides(faces))
    rot = None if rotation is None else rotation.to(rays.dtype).contiguous()
    ops.sample_rays(faces, rays.contiguous(), rot, valid, ring_src, ring_weight, pad,
                    mode == "bilinear", fill, out)


def sample_cube(cubemap: Tensor, grid: Tensor, mode: str = "bilinear", *, pad: int,
                border: str = "bilinear", lut: CubeLUT | None = None,
                out: Tensor | None = None, valid: Tensor | None = None, fill: int = 0,
                out_dtype: torch.dtype | None = None, edge_threshold: float = 0.05,
                backend: str = "auto") -> Tensor:
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
        lut: a `build_lut` of ``grid`` for this layout (a frozen camera), else built here.
        out: ``(B, C, H, W)`` in ``out_dtype`` to write the image into (any batch strides; each
            ``H x W`` plane contiguous, or channels-last pixels), e.g. part of a larger batch.
        valid: ``(1 or B', H, W)`` bool, without ``lut``: the pixels where it is False read
            ``fill``, as if their grid pointed outside the atlas (so the caller need not move
            them there first).
        fill: the value of the pixels whose taps all lie outside the atlas (``grid_sample``'s
            zero padding: 0), e.g. the ignore index of labels; an int that the output's dtype
            holds.
        out_dtype: the image's dtype (`output_dtypes`): the cube's (default), or float32
            for a ``uint8`` cube (scaled to [0, 1]) or a half-precision one, or int64 for a
            ``uint8`` cube sampled nearest (class ids).
        edge_threshold: for ``mode="edge_aware"`` (torch only), `reference_sample`'s.
        backend: the C++ ops or `reference_sample` (`_backend`; ``"bicubic"`` and
            ``"edge_aware"`` have no C++ op).

    Returns:
        ``(B, C, H, W)`` in ``out_dtype`` (``out`` when given); ``fill`` where every tap is
        outside the atlas.
    """
    check_cubemap(cubemap)
    _check_grid(grid, cubemap.shape[0])
    if valid is not None and lut is not None:
        raise ValueError("valid: only without lut (build the table from a grid whose "
                         "invalid pixels lie outside the atlas)")
    ops = _choose(backend, mode, border, cubemap, grid)
    if ops is None:
        return reference_sample(cubemap, grid, mode, pad=pad, border=border, valid=valid,
                                fill=fill, out=out, out_dtype=out_dtype,
                                edge_threshold=edge_threshold)

    def sample(work: Tensor, into: Tensor, mask: Tensor | None) -> None:
        _sample(ops, work, grid, mode, pad, border, lut, into, mask, fill)

    return _run(cubemap, grid.shape[0], tuple(grid.shape[1:3]), mode, border, out, valid, fill,
                out_dtype, sample)


def sample_rays(cubemap: Tensor, rays: Tensor, rotation: Tensor | None = None,
                mode: str = "bilinear", *, pad: int, border: str = "bilinear",
                out: Tensor | None = None, valid: Tensor | None = None, fill: int = 0,
                out_dtype: torch.dtype | None = None, edge_threshold: float = 0.05,
                backend: str = "auto") -> Tensor:
    """`sample_cube` through the grid of camera-frame ``rays`` rotated into the cube
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
    `work_dtype` the grid is built first.

    Args:
        cubemap: ``(B, 6, C, F, F)`` on the CPU, as for `sample_cube`.
        rays: ``(Br, H, W, 3)`` (``Br`` 1 or ``B``) or ``(H, W, 3)`` camera-frame directions.
        rotation: ``(Bq, 3, 3)`` (``Bq`` 1 or ``B``) or ``(3, 3)`` camera -> cube frame, or None.
        mode: as for `sample_cube`.
        pad: as for `sample_cube`.
        border: as for `sample_cube`.
        out: as for `sample_cube`.
        fill: as for `sample_cube`.
        out_dtype: as for `sample_cube`.
        valid: ``(1 or max(Br, Bq), H, W)`` bool: the pixels where it is False read ``fill``.
        edge_threshold: as for `sample_cube`.
        backend: the C++ op or the grid built and `reference_sample` (`_backend`).

    Returns:
        ``(B, C, H, W)`` in ``out_dtype`` (``out`` when given).
    """
    check_cubemap(cubemap)
    batch = cubemap.shape[0]
    rays, rotation, _ = _check_rays(rays, rotation, cubemap.shape[-1], pad, None)
    points = max(rays.shape[0], 1 if rotation is None else rotation.shape[0])
    if points not in (1, batch):
        raise ValueError(f"rays, rotation: batch {points} does not match the cubemap's {batch}")
    ops = _choose(backend, mode, border, cubemap, rays, rotation)
    if ops is None:
        grid = rotated_rays_to_grid(rays, rotation, cubemap.shape[-1], pad,
                                    dtype=work_dtype(cubemap.dtype))
        return reference_sample(cubemap, grid, mode, pad=pad, border=border, valid=valid,
                                fill=fill, out=out, out_dtype=out_dtype,
                                edge_threshold=edge_threshold)

    def sample(work: Tensor, into: Tensor, mask: Tensor | None) -> None:
        _sample_rays(ops, work, rays, rotation, mode, pad, border, into, mask, fill)

    return _run(cubemap, points, tuple(rays.shape[1:3]), mode, border, out, valid, fill,
                out_dtype, sample)


def is_channels_last(t: Tensor) -> bool:
    """Whether the channels of ``t (..., C, H, W)`` (a cube or an image) are its innermost
    dimension in memory (a ``(..., H, W, C)`` tensor permuted, or ``torch.channels_last``);
    the fast sampler writes the image of such a cube in the same layout."""
    return t.shape[-3] > 1 and t.stride(-3) == 1 and t.stride(-1) >= t.shape[-3]


def _run(cubemap: Tensor, points: int, size: tuple[int, int], mode: str, border: str,
         out: Tensor | None, valid: Tensor | None, fill: int, out_dtype: torch.dtype | None,
         sample) -> Tensor:
    """What `sample_cube` and `sample_rays` share, after their ``check_cubemap``:
    the checks of the cube's device and dtype, of ``out_dtype``, ``out``, ``valid``
    (``points``: the grid's batch) and ``fill``; the output allocated in the cube's layout;
    then ``sample(cube, into (B, C, H, W), valid (1 or B', H, W) or None)``."""
    _check_mode(mode, border)
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
    if out is None:
        out = (torch.empty((batch, *size, chans), dtype=out_dtype).permute(0, 3, 1, 2)
               if interleaved else torch.empty(shape, dtype=out_dtype))
    with torch.no_grad():
        sample(cubemap, out, valid)
    return out


def holds(dtype: torch.dtype, value: int) -> bool:
    """Whether ``dtype`` holds the int ``value`` (a ``fill`` of `sample_cube`)."""
    if dtype.is_complex:
        return value == 0   # complex elements are copied as bits: only 0 is a fill
    if dtype == torch.bool:
        return value in (0, 1)
    info = torch.finfo(dtype) if dtype.is_floating_point else torch.iinfo(dtype)
    return info.min <= value <= info.max


def _out_dtype(dtype: torch.dtype, out_dtype: torch.dtype | None, mode: str, what: str
               ) -> torch.dtype:
    """The dtype of the samples of a ``what`` of ``dtype``: ``out_dtype``, by default
    ``dtype``; a ``TypeError`` where the kernels write no such samples (`output_dtypes`)."""
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
    atlas ``(B, C, 6 n, n)`` by the C++ ops, forward only, to float32 rounding (nearest:
    exactly, any dtype).

    Args:
        atlas: ``(B, C, 6 n, n)`` on the CPU (``cubemap_to_atlas``), contiguous.
        grid: ``(B' in {1, B}, H, W, 2)`` floating.
        mode: ``"nearest"`` or ``"bilinear"``.

    Returns:
        ``(B, C, H, W)``.
    """
    faces = atlas_to_faces(atlas.contiguous())  # (B, 6, C, n, n) view: an atlas without border
    return sample_cube(faces, grid, mode, pad=0, backend="cpp")


# ------------------------------------------------------------------------------------------
# The torch twin
# ------------------------------------------------------------------------------------------

#: Modes of the twin beyond the C++ ops' `MODES`: bicubic (`grid_sample`) and edge-aware
#: bilinear (depth).
REFERENCE_MODES = (*MODES, "bicubic", "edge_aware")


def _choose(backend: str, mode: str, border: str, *tensors):
    """The ops for a sampler call in `mode` on `tensors`, or None for the twin (a mode without
    an op takes the twin under `"auto"`; under `"cpp"` it is refused)."""
    if mode not in REFERENCE_MODES:
        raise ValueError(f"mode: expected one of {REFERENCE_MODES}, got {mode!r}")
    if border not in BORDERS:
        raise ValueError(f"border: expected one of {BORDERS}, got {border!r}")
    if mode not in MODES:
        if backend == "cpp":
            raise ValueError(f"mode: {mode!r} has no C++ op (backend='cpp' samples "
                             f"{MODES}); use backend='auto' or 'torch'")
        check_backend(backend)
        return None
    return choose(backend, *tensors, what="sample_cube")


def atlas(cube: Tensor, pad: int, border: str) -> Tensor:
    """The padded atlas `(B, C, 6 n, n)` the twin samples: `cubemap_to_atlas` with the border
    resampled by `border` (`"bilinear"` or `"nearest"`), or every face padded with its own edge
    texels (`"copied"`, what a naive atlas does); exact for any dtype."""
    if border != "copied" or pad == 0:
        return cubemap_to_atlas(cube, pad, "nearest" if border == "copied" else border)
    b, _, c, f, _ = cube.shape
    # replicate by indexing (exact for any dtype): padded texel i reads clamp(i - p, 0, F-1)
    idx = (torch.arange(f + 2 * pad, device=cube.device) - pad).clamp(0, f - 1)
    padded = cube.reshape(b * 6, c, f, f)[:, :, idx][:, :, :, idx]
    return faces_to_atlas(padded.reshape(b, 6, c, f + 2 * pad, f + 2 * pad))


def edge_aware(atlas: Tensor, grid: Tensor, threshold: float) -> Tensor:
    """Bilinear interpolation of `atlas (B, 1, Ha, Wa)` at `grid (B, h, w, 2)` that returns the
    nearest tap where the four taps spread by more than `threshold` relative to their minimum
    (depth: no "flying pixels" across depth edges)."""
    b, _, ha, wa = atlas.shape
    # pixel coordinates of align_corners=False: x = ((gx + 1) W - 1) / 2
    x = ((grid[..., 0] + 1) * wa - 1) / 2
    y = ((grid[..., 1] + 1) * ha - 1) / 2
    x0 = torch.floor(x.detach()).clamp(0, wa - 2)
    y0 = torch.floor(y.detach()).clamp(0, ha - 2)
    fx, fy = (x - x0).clamp(0, 1), (y - y0).clamp(0, 1)
    x0, y0 = x0.long(), y0.long()
    flat = atlas.reshape(b, ha * wa)
    idx = (y0 * wa + x0).reshape(b, -1)

    def tap(dy: int, dx: int) -> Tensor:
        return flat.gather(1, idx + dy * wa + dx).reshape(x.shape)

    t00, t01, t10, t11 = tap(0, 0), tap(0, 1), tap(1, 0), tap(1, 1)
    w00, w01 = (1 - fx) * (1 - fy), fx * (1 - fy)
    w10, w11 = (1 - fx) * fy, fx * fy
    blend = t00 * w00 + t01 * w01 + t10 * w10 + t11 * w11
    taps = torch.stack((t00, t01, t10, t11), -1)
    weights = torch.stack((w00, w01, w10, w11), -1)
    lo, hi = taps.detach().amin(-1), taps.detach().amax(-1)
    edge = (hi - lo) > threshold * lo.abs()
    nearest = taps.gather(-1, weights.detach().argmax(-1, keepdim=True)).squeeze(-1)
    return torch.where(edge, nearest, blend).unsqueeze(1)


def reference_sample(cubemap: Tensor, grid: Tensor, mode: str = "bilinear", *, pad: int,
                     border: str = "bilinear", valid: Tensor | None = None, fill: int = 0,
                     out: Tensor | None = None, out_dtype: torch.dtype | None = None,
                     edge_threshold: float = 0.05) -> Tensor:
    """The twin of `sample_cube`: `grid_sample` (`align_corners=False`, zero padding) on the
    padded atlas (`atlas`), differentiable, on any device; integer cubes gathered nearest
    (`reference.nearest_gather`: exact ids of any dtype).

    Floating cubes of float32 and float64 are sampled in their dtype, the others (half
    precision, `uint8` images) in float32 and converted once (`reference.from_float`: `uint8`
    rounded half up, or scaled to [0, 1] into a floating `out_dtype`); a `uint8` cube sampled
    nearest with a `"nearest"` or `"copied"` border holds ids (labels) and is gathered. The pixels whose grid lies
    outside the atlas (or where `valid (1 or B', H, W)` is False) read 0 (`fill` for integer
    cubes). Arguments as for `sample_cube`; `mode` also `"bicubic"` or `"edge_aware"`.
    """
    batch = cubemap.shape[0]
    if valid is not None:
        grid = torch.where(valid.unsqueeze(-1), grid, torch.full_like(grid, -2.0))
    if grid.shape[0] != batch:
        grid = grid.expand(batch, *grid.shape[1:])
    out_dtype = cubemap.dtype if out_dtype is None else out_dtype
    # ids (any integer dtype, a uint8 one with a border of copied texels) are gathered; a uint8
    # image, whose border texels are blended, is sampled in float32 as the other images
    image_u8 = cubemap.dtype == torch.uint8 and (mode != "nearest" or border == "bilinear")
    if not cubemap.is_floating_point() and not image_u8:
        if mode != "nearest":
            raise TypeError(f"cubemap: {mode} sampling needs a floating or uint8 cube, got "
                            f"{cubemap.dtype}")
        ids = nearest_gather(atlas(cubemap, pad, border), grid)
        if out_dtype.is_floating_point:
            image = from_float(ids.float(), cubemap.dtype, out_dtype)
        else:
            image = ids.to(out_dtype)
        if fill != 0:   # (the gather clamps: the pixels outside the atlas read fill here)
            image = image.masked_fill((grid.abs() > 1).any(-1).unsqueeze(1), fill)
    else:
        work = cubemap if cubemap.dtype in (torch.float32, torch.float64) else cubemap.float()
        padded = atlas(work, pad, border)
        points = grid.to(padded.dtype)
        if mode == "edge_aware":
            image = edge_aware(padded, points, edge_threshold)
        else:
            image = grid_sample(padded, points, mode, padding_mode="zeros")
        image = from_float(image, cubemap.dtype, out_dtype)
    if out is not None:
        out.copy_(image)
        return out
    return image
