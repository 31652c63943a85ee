"""Sampling an image along rays, with or without the antialiasing prefilter, and the rays of
whole cameras from their radius tables: the C++ ops `camera_grid`, `camera_rays`,
`sample_image`, `mip_image` and `reproject_image`, each beside its torch twin.

The C++ ops run on the CPU without gradients; the twins (`grid_sample` on the image, the
prefilter of `render.antialias`) everywhere else, by each function's `backend` (`_backend`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ...cubemap.grid import rotated_rays_to_grid
from ..antialias import MINIFIES
from . import build
from ._backend import choose
from .cube import (BLENDED, _check_fill, _check_mode, _check_out, _out_dtype, _samples,
                   work_dtype)

__all__ = ["CameraGrid", "MIPMAPPED", "camera_grid", "camera_rays", "mip_image",
           "reproject_image", "sample_image"]


def camera_grid(affine: Tensor, limits: Tensor, table: Tensor, rotation: Tensor,
                face_size: int, pad: int, image_size: tuple[int, int], dtype: torch.dtype
                ) -> tuple[Tensor, Tensor]:
    """The atlas grid ``(B, H, W, 2)`` in ``dtype`` (float32 or float64) and validity ``(B, H,
    W)`` of ``B`` radially symmetric cameras rotated by ``rotation (B, 3, 3)``, from their
    tables (``kernels.radial_table``: ``affine (B, 6)``, ``limits (B, 5)``, ``table (B, 2,
    K)``); the invalid pixels at (-2, -2). The C++ op computes each pixel's ray from its table,
    rotates it and writes its grid point, in one pass (``kernels.camera_grid``)."""
    ops = choose("cpp", what="image kernels")
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
    choose("cpp", what="image kernels").camera_rays(*tables, rays, valid)
    return rays, valid


class CameraGrid:
    """The atlas grid of ``B`` radially symmetric cameras, each with its rotation and cones,
    as their tables (``kernels.radial_table``) until it is read: its rays and validity are
    made on first use in one pass of the C++ op over the pixels (`camera_rays`), then
    read by `sample_rays`, which computes the grid inside its sampling pass (one table
    pass for every modality sampled, and no grid in memory); other samplers read
    `tensor`, built on first use. ``rows`` takes a part of the cameras without computing
    anything (a batch's tables made at once, its rays a few samples at a time).
    ``OmniProjection.render(grid=...)`` takes it (``kernels.camera_grid(..., lazy=True)`` makes
    it).

    Attributes:
        rays: ``(B, H, W, 3)`` camera-frame unit rays, in ``dtype`` (float32 or float64, the
            `work_dtype` of the cubes it samples).
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
    of `sample_cube`: ``uint8`` blended in float32 and rounded half up (or scaled to
    [0, 1], or, nearest, widened to int64 ids: `output_dtypes`).

    Args:
        image: ``(B, C, H, W)`` on the CPU.
        rays: ``(1 or B, h, w, 3)`` directions (any norm) in `work_dtype` of the image
            (float32 or float64 for an image sampled nearest).
        rotation: ``(1 or B, 3, 3)`` rays -> the image's camera frame, or None.
        intrinsics: ``(1 or B, 4)`` the image's pinhole ``fx, fy, cx, cy`` (pixel centres at
            integers), in the rays' dtype.
        mode: ``"nearest"`` or ``"bilinear"``.
        valid: ``(1 or B, h, w)`` bool: the rays to sample (else ``fill``).
        fill: as for `sample_cube`.
        out: as for `sample_cube`.
        out_dtype: as for `sample_cube`.

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
    ops = choose("cpp", what="image kernels")
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


#: Image dtypes `mip_image` filters (the others: ``antialias.minified``).
MIPMAPPED = (torch.uint8, torch.float32, torch.float64)


def mip_image(image: Tensor, rays: Tensor, rotation: Tensor | None, intrinsics: Tensor,
              valid: Tensor, out: Tensor) -> Tensor:
    """Antialias `sample_image`'s bilinear samples in place: the pixels of ``out`` whose
    footprint minifies the image are overwritten by a filter of its mip pyramid, in one C++
    pass; the others are left as they are, bit for bit.

    The footprint is `footprint`'s: the Jacobian
    columns ``du, dv`` of the rays' image pixels (as `sample_image` projects them) by
    finite differences to the next output pixel, forward where both pixels are ``valid``,
    else backward, else 0; a pixel minifies where a column is longer than
    `MINIFIES` source pixels. Its value is the mean of
    4 bilinear lookups at ``(u, v) +- du / 4 +- dv / 4`` (the centres of the footprint's
    quarters) in the mip level ``k = floor(log2(rho / 2))`` (``rho``: the longer column's
    length; 0 below ``rho = 4``), whose texels (``2**k`` source pixels) are at most a
    quarter's width across, clamped to the level's edge. The pyramid (level ``k + 1`` the
    2 x 2 average of level ``k``, an odd last row or column averaged over the texels it holds;
    ``uint8`` levels rounded half up) is built per call, only to the deepest level a pixel
    reads (whole for an image of at most 4 source pixels an output pixel, where finding that
    level costs more than the levels). `mip_sample` is
    the same rule in PyTorch, the filter off the CPU or with gradients (``docs/augmentation.md``,
    Antialiasing).

    Args:
        image: ``(B, C, H, W)`` ``uint8``, float32 or float64 on the CPU, any strides.
        rays: as given to `sample_image`.
        rotation: as given to `sample_image`.
        intrinsics: as given to `sample_image`.
        valid: ``(B, h, w)`` bool: the pixels `sample_image` found valid (its second
            result); the footprint's differences are taken between valid pixels only.
        out: ``(B, C, h, w)`` `sample_image`'s samples (``uint8`` or float32 for a
            ``uint8`` image, else the image's dtype), overwritten where the pixels minify.

    Returns:
        ``out``.
    """
    if not isinstance(image, Tensor) or image.dtype not in MIPMAPPED:
        raise TypeError(f"image: expected one of {[str(d) for d in MIPMAPPED]}, got "
                        f"{getattr(image, 'dtype', type(image).__name__)}")
    dtype = work_dtype(image.dtype)
    with torch.no_grad():
        choose("cpp", what="image kernels").mip_image(image, rays.to(dtype).contiguous(),
                             None if rotation is None else rotation.to(dtype).contiguous(),
                             intrinsics.to(dtype).contiguous(), valid.contiguous(), MINIFIES,
                             out)
    return out


def reproject_image(image: Tensor | None, labels: Tensor | None, affine: Tensor, limits: Tensor,
                    table: Tensor, rotation: Tensor, intrinsics: Tensor, bilinear: bool,
                    minifies: float, fill: int, out: Tensor | None, out_labels: Tensor | None,
                    valid: Tensor, *, trusted: bool = False) -> None:
    """In one call of the C++ op: `camera_rays` of ``B`` radially symmetric cameras,
    `sample_image` of ``image`` along them into ``out`` (its validity into ``valid``),
    `mip_image` of the pixels that minify where ``minifies > 0``, and ``labels``
    sampled nearest into ``out_labels``: those functions' results in turn, bit for bit
    (``RandomReproject``'s fast path; the rays stay inside the call).

    Args:
        image: ``(B, C, H, W)`` ``uint8``, float32 or float64 on the CPU (any strides), or None.
        labels: ``(B, H, W)`` ``uint8`` or int64 ids, or None (one of ``image``, ``labels``).
        affine: ``(B, 6)``, as `camera_rays` takes it (``kernels.radial_table``), in the
            rays' dtype: `work_dtype` of ``image`` (float32 or float64 for labels alone).
        limits: ``(B, 5)``, likewise.
        table: ``(1 or B, 2, K)``, likewise.
        rotation: ``(1 or B, 3, 3)`` rays -> the image's camera frame, in the rays' dtype.
        intrinsics: ``(1 or B, 4)`` the image's pinhole ``fx, fy, cx, cy``, in the rays' dtype.
        bilinear: the image's samples bilinear (else nearest).
        minifies: the prefilter's threshold
            (`MINIFIES`), or 0: no prefilter.
        fill: the label of the pixels outside (an int).
        out: ``(B, C, h, w)`` with ``image`` (its dtype, or float32 for ``uint8``), else None.
        out_labels: ``(B, h, w)`` int64 with ``labels``, else None.
        valid: ``(B, h, w)`` bool, contiguous: written.
        trusted: the caller made every argument itself as above (``RandomReproject``'s fused
            path, which checked its inputs once): the checks are skipped (a few microseconds
            of a call of a few hundred).

    Raises:
        TypeError, ValueError: naming the argument that is not as above.
    """
    if trusted:   # (the caller chose the C++ route for these inputs: kernels.resolve)
        build.ops().reproject_image(image, labels, affine, limits, table, rotation, intrinsics, bilinear,
                            minifies, fill, out, out_labels, valid)
        return
    ops = choose("cpp", affine, what="reproject_image")
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
    ops.reproject_image(image, labels, affine, limits, table, rotation.contiguous(),
                               intrinsics.contiguous(), bool(bilinear), float(minifies), fill,
                               out, out_labels, valid)


