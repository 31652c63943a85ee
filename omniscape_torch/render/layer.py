"""``OmniProjection``: the paper's cubemap -> omnidirectional lookup table as a batched layer.

    camera params --(unproject)--> rays (H, W, 3) --(rotate)--> cube frame
        --> grid on the padded cube atlas --> grid_sample per modality --> image + valid mask

The rays of a fixed camera are computed once and cached; the grid too while no rotation is
given. Learnable intrinsics or a rotation batch rebuild the grid on every call, with gradients.
RGB is sampled with ``grid_sample`` (nearest, bilinear or bicubic) on an atlas whose faces carry
borders resampled from their neighbours, so sampling is continuous across seams and corners.
Depth is converted from the cube's planar depth to range (view-independent) before sampling,
labels are sampled nearest and never blended.

Every sampling goes through the kernel boundary (`omniscape_torch.render.kernels.cube`): the
C++ ops where no gradient is needed (grad disabled, or neither the cubemaps, the camera
parameters nor the rotation require it) and the cube is on the CPU (same output to float32
rounding, no atlas built; a frozen camera's lookup table is cached with its grid; under a
rotation the grid is computed from the rays in the sampling pass and never stored), else their
torch twin, `grid_sample` on the padded atlas (any device, gradients). The layer's `backend`
(`"auto"`, `"cpp"`, `"torch"`; `fast=False` is `"torch"`) is resolved once per call
(`kernels.resolve`) and passed to every kernel. On a GPU every call takes the torch route.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .. import cubemap as cm
from .kernels import cube as fastsample
from .kernels import image as kimage
from .kernels._backend import check_backend, resolve
from ..cameras import Camera
from ..cameras._checks import not_a_camera
from ..cubemap.grid import rotated_rays_to_grid
from .reference import check_out_dtype, from_float, warn_if_label_map

INTERPOLATIONS = ("nearest", "bilinear", "bicubic")
DEPTH_INTERPOLATIONS = ("nearest", "bilinear", "edge_aware")
BORDERS = ("resampled", "copied", "none")
#: Pixels rendered per chunk of samples on the CPU's fast path when every sample has its own
#: grid and some sampler builds it (a rotation batch with bicubic RGB, soft labels, or rays the
#: C++ kernel does not read; see ``_grid_free``): a chunk's grid and intermediates stay in the
#: cache and in memory the allocator reuses, where a whole batch's are fresh pages on every call
#: (a page fault per 4 KiB; measured: 16 x 512 x 512 augmentation 96 -> 45 ms for the grids
#: alone).
CHUNK_PIXELS = 2 ** 20
#: Border width of the atlas per interpolation: the texels a kernel reads beyond a face edge.
_PAD = {"nearest": 1, "bilinear": 1, "bicubic": 2}


def pad_for(interpolation: str, border: str = "resampled") -> int:
    """The atlas border of a layer of this ``interpolation`` and ``border`` (``OmniProjection``'s
    ``pad``): the texels its kernel reads beyond a face edge, none without a border."""
    return 0 if border == "none" else _PAD[interpolation]


def _check_rotation(rotation: Tensor | None, batch: int, device, name: str = "rotation"):
    if rotation is None:
        return None
    if isinstance(rotation, Tensor) and rotation.device != device:
        raise ValueError(f"{name}: on {rotation.device}, the cubemap is on {device}")
    cm.check_rotation(rotation, name)
    if rotation.shape == (3, 3):
        rotation = rotation.unsqueeze(0)
    if rotation.dim() != 3 or rotation.shape[1:] != (3, 3) or rotation.shape[0] not in (1, batch):
        raise ValueError(f"{name}: expected shape ({batch}, 3, 3) or (3, 3), got "
                         f"{tuple(rotation.shape)}")
    return rotation


class OmniProjection(nn.Module):
    """Render a cubemap batch into a fisheye, catadioptric or any other registered camera.

    Args:
        camera: the target camera (one, or a batch of ``B`` cameras of one model).
        face_size: ``F``, texels per cube face side.
        interpolation: ``"nearest"``, ``"bilinear"`` (default) or ``"bicubic"`` for RGB.
        supersample: ``s``: average ``s x s`` rays per pixel (anti-aliasing when the cube is much
            finer than the output); labels and nearest depth use the pixel centre.
        depth_interpolation: ``"nearest"`` (default), ``"bilinear"``, or ``"edge_aware"``:
            bilinear, falling back to the nearest texel where the four taps disagree by more than
            ``depth_edge_threshold`` (relative), so no "flying pixels" appear across depth edges.
        depth_edge_threshold: relative spread of the four taps that marks a depth edge.
        ignore_index: label of pixels outside the valid area.
        border: how faces are padded: ``"resampled"`` from the neighbours (default; continuous
            across seams), ``"copied"`` (edge texels repeated, what a naive atlas does; for
            comparison), ``"none"`` (no padding; for comparison).
        fused_grid: build rebuilt grids (rotations, learnable intrinsics) with the fused
            ``torch.compile`` kernel of ``omniscape_torch.cubemap.grid`` (2x faster per call; the
            first call compiles for a few seconds; falls back to eager torch, with a warning,
            where compilation is unavailable). The output is the same either way.
        fast: False is ``backend="torch"`` (kept for code written before ``backend``).
        backend: ``"auto"`` (default): nearest and bilinear sampling by the C++ ops
            (``kernels.cube``: a lookup table on the cube, no atlas; CPU) whenever no
            gradient is needed: a cached grid's table is built once and kept; under a rotation
            each pixel's grid point is computed from the camera's rays in the sampling pass,
            no grid stored (``benchmarks/bench_projection.py``); else their torch twin,
            ``grid_sample`` on the padded atlas. ``"torch"``: the twin always; ``"cpp"``: the
            ops always (an error where they cannot run). Same output to float32 rounding
            either way, and gradients come from the twin.

    Shapes:
        cubemap ``(B, 6, C, F, F)``; rotation ``(B, 3, 3)`` or ``(3, 3)`` mapping camera rays into
        the cube frame; output ``image (B, C, H, W)`` and ``valid (B, 1, H, W)``.
    """

    def __init__(self, camera: Camera, face_size: int, *, interpolation: str = "bilinear",
                 supersample: int = 1, depth_interpolation: str = "nearest",
                 depth_edge_threshold: float = 0.05, ignore_index: int = 255,
                 border: str = "resampled", fused_grid: bool = True,
                 fast: bool = True, backend: str = "auto") -> None:
        super().__init__()
        if not isinstance(camera, Camera):
            raise not_a_camera("camera", camera)
        if isinstance(face_size, bool) or not isinstance(face_size, int) or face_size < 1:
            raise ValueError(f"face_size: expected a positive int, got {face_size!r}")
        if interpolation not in INTERPOLATIONS:
            raise ValueError(f"interpolation: expected one of {INTERPOLATIONS}, got "
                             f"{interpolation!r}")
        if depth_interpolation not in DEPTH_INTERPOLATIONS:
            raise ValueError(f"depth_interpolation: expected one of {DEPTH_INTERPOLATIONS}, got "
                             f"{depth_interpolation!r}")
        if isinstance(supersample, bool) or not isinstance(supersample, int) or supersample < 1:
            raise ValueError(f"supersample: expected a positive int, got {supersample!r}")
        if border not in BORDERS:
            raise ValueError(f"border: expected one of {BORDERS}, got {border!r}")
        if not depth_edge_threshold > 0:
            raise ValueError(f"depth_edge_threshold: expected > 0, got {depth_edge_threshold}")
        self.camera = camera
        self.face_size = face_size
        self.interpolation = interpolation
        self.supersample = supersample
        self.depth_interpolation = depth_interpolation
        self.depth_edge_threshold = float(depth_edge_threshold)
        self.ignore_index = int(ignore_index)
        self.border = border
        self.fused_grid = bool(fused_grid)
        self.fast = bool(fast)
        self.backend = check_backend(backend) if self.fast else "torch"
        self.pad = pad_for(interpolation, border)
        self._rays_cache: tuple | None = None
        self._grid_cache: tuple | None = None
        self._lut_cache: dict = {}  # lookup tables of the cached grids (fastsample)

    def extra_repr(self) -> str:
        return (f"face_size={self.face_size}, interpolation={self.interpolation!r}, "
                f"supersample={self.supersample}, depth={self.depth_interpolation!r}, "
                f"border={self.border!r}, backend={self.backend!r}")

    # ---------------------------------------------------------------------------------------
    # Rays and grids
    # ---------------------------------------------------------------------------------------
    def _sub_pixels(self) -> Tensor:
        """``(H s, W s, 2)`` sub-pixel sample positions, centred in their pixels."""
        s = self.supersample
        grid = self.camera.pixel_grid()
        if s == 1:
            return grid
        kw = dict(dtype=grid.dtype, device=grid.device)
        offsets = (torch.arange(s, **kw) + 0.5) / s - 0.5
        h, w = self.camera.image_size
        u = (grid[..., 0].unsqueeze(-1) + offsets).reshape(h, w * s)
        v = (grid[..., 1].unsqueeze(1) + offsets.view(s, 1)).reshape(h * s, w)
        return torch.stack((u.repeat_interleave(s, 0), v.repeat_interleave(s, 1)), -1)

    def _fixed(self) -> bool:
        return not (torch.is_grad_enabled() and self.camera.params.requires_grad)

    def camera_rays(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Rays in the camera frame: ``(rays (*Bc, Hs, Ws, 3), valid_sub (*Bc, Hs, Ws),
        centre_rays (*Bc, H, W, 3), valid (*Bc, H, W))``; cached while the camera is fixed."""
        params = self.camera.params
        # id() of a tensor the cache keeps alive (below): no other tensor can take it over
        key = (id(params), params._version, params.device, params.dtype, self.supersample)
        if self._fixed() and self._rays_cache is not None and self._rays_cache[0] == key:
            return self._rays_cache[1]
        self.camera.check_params()   # new or changed parameters: still in the model's domain?
        batch = self.camera.batch_shape
        centre = self.camera.pixel_grid()
        rays_c, valid_c = self.camera.unproject(centre.expand(batch + centre.shape))
        if self.supersample == 1:
            rays_s, valid_s = rays_c, valid_c
        else:
            sub = self._sub_pixels()
            rays_s, valid_s = self.camera.unproject(sub.expand(batch + sub.shape))
        out = (rays_s, valid_s, rays_c, valid_c)
        if self._fixed():
            self._rays_cache = (key, tuple(t.detach() for t in out), params)
            self._grid_cache = None   # grids and lookup tables of other rays are stale
            self._lut_cache.clear()
        return out

    def _grid(self, rays: Tensor, rotation: Tensor | None, dtype: torch.dtype) -> Tensor:
        """Atlas grid ``(B', h, w, 2)`` of camera-frame ``rays (*Bc, h, w, 3)``: the fused
        (compiled) kernel when the grid is rebuilt on every call (a rotation, or learnable
        intrinsics), the eager one for a grid computed once and cached."""
        rebuilt = rotation is not None or not self._fixed()
        return rotated_rays_to_grid(rays, rotation, self.face_size, self.pad, dtype=dtype,
                                    compiled=rebuilt and self.fused_grid)

    def sampling_grid(self, rotation: Tensor | None = None, dtype: torch.dtype = torch.float32
                      ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Grids for the sub-pixel samples and the pixel centres, and the validity. The invalid
        pixels' grid entries lie outside the atlas (-2, -2), where ``grid_sample`` reads 0.

        Args:
            rotation: ``(B, 3, 3)`` or ``(3, 3)`` camera -> cube frame, or None.
            dtype: dtype of the grids.

        Returns:
            ``grid_sub (B', Hs, Ws, 2)``, ``valid_sub (B', Hs, Ws)``, ``grid_centre
            (B', H, W, 2)``, ``valid (B', H, W)``; ``B'`` is 1 for one camera and no rotation.
            Cached while the camera is fixed and ``rotation`` is None.
        """
        if rotation is not None and rotation.dim() == 2:
            rotation = rotation.unsqueeze(0)
        rays_s, valid_s, rays_c, valid_c = self.camera_rays()
        cacheable = rotation is None and self._fixed()
        key = (self._rays_cache[0] if self._rays_cache else None, dtype)
        if cacheable and self._grid_cache is not None and self._grid_cache[0] == key:
            return self._grid_cache[1]
        valid_s, valid_c = _batched(valid_s), _batched(valid_c)
        # Invalid rays point outside the atlas: sampled with zero padding they read 0, so the
        # image needs no mask afterwards (their gradient is 0 too).
        grid_s = _outside(self._grid(rays_s, rotation, dtype), valid_s)
        grid_c = grid_s if self.supersample == 1 else _outside(
            self._grid(rays_c, rotation, dtype), valid_c)
        out = (grid_s, valid_s, grid_c, valid_c)
        if cacheable:
            self._grid_cache = (key, out)
        return out

    # ---------------------------------------------------------------------------------------
    # Sampling
    # ---------------------------------------------------------------------------------------
    def _sample_cube(self, cube: Tensor, grid: Tensor, mode: str, pad_mode: str,
                     valid: Tensor | None, route: str, *, fill: int = 0,
                     out: Tensor | None = None, out_dtype: torch.dtype | None = None) -> Tensor:
        """`kernels.cube.sample_cube` of ``cube`` (or `sample_rays` of a grid of rays that the
        C++ op reads), by the call's ``route`` (`render`). The lookup table of a cached grid
        is kept with it. ``valid``: the mask of a grid whose invalid pixels were not moved
        outside the atlas, else None; ``fill``: the value of the pixels outside; ``out``:
        where to write the image; ``out_dtype``: its dtype."""
        border = "copied" if self.border == "copied" else pad_mode
        kw = dict(pad=self.pad, border=border, fill=fill, out=out, out_dtype=out_dtype,
                  edge_threshold=self.depth_edge_threshold, backend=self.backend)
        if isinstance(grid, kimage.CameraGrid):   # per-sample rays and rotations
            if mode in fastsample.MODES and fastsample.reads_rays(cube.dtype, grid.dtype):
                return fastsample.sample_rays(cube, grid.rays, grid.rotation, mode,
                                              valid=grid.valid, **kw)
            grid = grid.tensor()
        if isinstance(grid, _RayGrid):
            if mode in fastsample.MODES and fastsample.reads_rays(cube.dtype, grid.rays.dtype):
                return fastsample.sample_rays(cube, grid.rays, grid.rotation, mode,
                                              valid=valid, **kw)
            grid = grid.tensor()   # built once for every modality, as the layer builds grids
        if route != "cpp" or mode not in fastsample.MODES:
            return fastsample.sample_cube(cube, grid, mode, valid=valid, **kw)
        cache = self._grid_cache
        cached = cache is not None and any(grid is g for g in cache[1])
        # the layouts the lookup tables are built for: contiguous, or contiguous channels-last
        last = fastsample.is_channels_last(cube)
        if last and not cube.permute(0, 1, 3, 4, 2).is_contiguous():
            cube = cube.permute(0, 1, 3, 4, 2).contiguous().permute(0, 1, 4, 2, 3)
        elif not last:
            cube = cube.contiguous()
        lut = None
        if cached:
            key = (cache[0], id(grid), mode, cube.shape[2], last, cube.dtype)
            if self._lut_cache and next(iter(self._lut_cache))[0] != cache[0]:
                self._lut_cache.clear()  # the grids changed: drop their tables
            lut = self._lut_cache.get(key)
            if lut is None:
                lut_grid = grid.to(fastsample.grid_dtype(cube.dtype, mode, grid.dtype))
                lut = self._lut_cache[key] = fastsample.build_lut(
                    lut_grid, self.face_size, self.pad, mode, channels=cube.shape[2],
                    channels_last=last)
        return fastsample.sample_cube(cube, grid, mode, lut=lut, valid=valid, **kw)

    def _sample_image(self, cube: Tensor, grid: Tensor, mode: str, pad_mode: str,
                      valid: Tensor | None, route: str, out: Tensor | None = None,
                      out_dtype: torch.dtype | None = None) -> Tensor:
        """Sample a floating or ``uint8`` cube into ``out_dtype`` (default: the cube's). Half
        precision and ``uint8`` are blended in float32 (the grid stays float32: a bfloat16 grid
        is off by pixels on a 512 face) and rounded once; a ``uint8`` cube into a floating
        ``out_dtype`` is scaled to [0, 1]. ``route``: the call's (`render`); ``out``: where
        it may write the image."""
        out_dtype = cube.dtype if out_dtype is None else out_dtype
        written = fastsample.output_dtypes(cube.dtype)   # by the kernels, in the same pass
        kernel_dtype = out_dtype if out_dtype in written else written[-1]
        image = self._sample_cube(cube, grid, mode, pad_mode, valid, route,
                                  out_dtype=kernel_dtype,
                                  out=out if kernel_dtype == out_dtype else None)
        image = image.to(out_dtype)   # another floating dtype: converted after
        if out is not None and image.data_ptr() != out.data_ptr():
            out.copy_(image)
        return image

    def _average(self, image: Tensor, valid_sub: Tensor) -> Tensor:
        """Mean over each pixel's valid ``s x s`` sub-samples."""
        s = self.supersample
        if s == 1:
            return image
        weight = valid_sub.unsqueeze(1).to(image.dtype)
        # the sum of s x s samples of the pool, divided before it is summed: no overflow near
        # the dtype's largest value (exact for s a power of 2)
        total = F.avg_pool2d(image * (weight / (s * s)), s) * (s * s)
        count = F.avg_pool2d(weight, s)
        return total / count.clamp(min=1.0 / (s * s))

    def forward(self, cubemap: Tensor, rotation: Tensor | None = None, *,
                out_dtype: torch.dtype | None = None, channels_last: bool = False
                ) -> tuple[Tensor, Tensor]:
        """Render ``cubemap (B, 6, C, F, F)`` (RGB or any float channels; ``channels_last``:
        ``(B, 6, F, F, C)``), floating or ``uint8``; ``out_dtype`` as for `render`.

        Returns:
            ``image (B, C, H, W)`` (``channels_last``: ``(B, H, W, C)``; 0 outside the valid
            area) and ``valid (B, 1, H, W)`` bool.
        """
        out = self.render(rgb=cubemap, rotation=rotation, out_dtype=out_dtype,
                          channels_last=channels_last)
        return out["rgb"], out["valid"]

    def render(self, *, rgb: Tensor | None = None, depth: Tensor | None = None,
               labels: Tensor | None = None, rotation: Tensor | None = None,
               depth_output: str = "range", soft_labels: int | None = None,
               out: dict[str, Tensor] | None = None,
               grid: tuple[Tensor, Tensor] | None = None,
               out_dtype: torch.dtype | None = None,
               channels_last: bool = False) -> dict[str, Tensor]:
        """Render several modalities of one cubemap batch through the same grid.

        Args:
            rgb: ``(B, 6, C, F, F)`` (any channels; ``channels_last``: ``(B, 6, F, F, C)``),
                floating, or ``uint8`` as simulators and image files give it (sampled as it
                is, no float copy: see ``out_dtype``; no gradient). Any strides: a
                ``(B, 6, F, F, C)`` tensor permuted to ``(B, 6, C, F, F)`` is read without a
                copy, and its image comes back channels-last in memory too.
            depth: ``(B, 6, F, F)`` or ``(B, 6, 1, F, F)`` planar depth per face (distance along
                the face axis, metres), as a simulator's depth camera renders it.
            labels: ``(B, 6, F, F)`` or ``(B, 6, 1, F, F)`` integer class ids.
            rotation: ``(B, 3, 3)`` or ``(3, 3)``: camera rays -> cube frame.
            depth_output: ``"range"`` (distance along the ray, default) or ``"z"`` (along the
                omni camera's optical axis).
            soft_labels: number of classes K: also return per-class probabilities
                ``(B, K, H, W)``, bilinearly sampled one-hot labels (soft-label training).
            out: tensors to write outputs into, by the keys below (each of that output's shape
                and dtype, any strides; e.g. rows of a larger batch). The fast path samples
                straight into them; the outputs not given are allocated.
            grid: ``(grid (B' in {1, B}, H, W, 2), valid (B', H, W))``: an atlas grid of this
                layer's face size and border (``self.pad``) to sample through instead of the
                camera's, its invalid pixels already outside the atlas (e.g. per-sample random
                cameras and attitudes in one kernel, ``render.kernels.camera_grid``), or a
                ``fast.CameraGrid`` of them (``camera_grid(..., lazy=True)``: the fast path
                computes every pixel's ray inside its sampling pass); not with ``rotation`` or
                ``supersample > 1``. The camera then gives only the image size.
            out_dtype: the dtype of the ``rgb`` image: the cube's (default; ``uint8`` rounded
                to nearest, as OpenCV's ``remap`` rounds), or a floating dtype (a ``uint8``
                cube scaled to [0, 1] in the same pass).
            channels_last: ``rgb`` is ``(B, 6, F, F, C)`` (channels innermost, as image files
                and simulators store them) and its image ``(B, H, W, C)``.

        Returns:
            dict with ``valid (B, 1, H, W)`` and, for each input, ``rgb (B, C, H, W)``
            (``channels_last``: ``(B, H, W, C)``) in ``out_dtype``,
            ``depth (B, 1, H, W)`` (0 where invalid), ``labels (B, H, W)`` int64
            (``ignore_index`` where invalid), ``soft_labels (B, K, H, W)``.
        """
        given = [t for t in (rgb, depth, labels) if t is not None]
        if not given:
            raise ValueError("render: pass at least one of rgb, depth, labels")
        if depth_output not in ("range", "z"):
            raise ValueError(f"depth_output: expected 'range' or 'z', got {depth_output!r}")
        if not isinstance(channels_last, bool):
            raise TypeError(f"channels_last: expected a bool, got {type(channels_last).__name__}")
        if rgb is not None:
            rgb, out_dtype = _check_rgb(rgb, out_dtype, channels_last)
        elif out_dtype is not None or channels_last:
            raise ValueError("out_dtype, channels_last: they describe rgb, which is not given")
        depth = _as_cube(depth, "depth")
        labels = _as_cube(labels, "labels")
        if depth is not None and not depth.is_floating_point():
            raise TypeError(f"depth: expected a floating-point cubemap, got {depth.dtype}")
        if labels is not None and (labels.is_floating_point() or labels.is_complex()):
            raise TypeError(f"labels: expected an integer cubemap, got {labels.dtype}")
        ref = next(t for t in (rgb, depth, labels) if t is not None)
        batch, size = ref.shape[0], ref.shape[-1]
        for name, t in (("rgb", rgb), ("depth", depth), ("labels", labels)):
            if t is None:
                continue
            if t.shape[0] != batch or t.shape[-1] != size:
                raise ValueError(f"{name}: shape {tuple(t.shape)} does not match the batch and "
                                 f"face size of the other modalities {tuple(ref.shape)}")
            if t.device != ref.device:
                raise ValueError(f"{name}: on {t.device}, other modalities on {ref.device}")
        if size != self.face_size:
            raise ValueError(f"cubemap: face size {size} does not match the layer's face_size "
                             f"{self.face_size}")
        if ref.device != self.camera.params.device:
            raise ValueError(f"cubemap: on {ref.device}, the camera is on "
                             f"{self.camera.params.device}")
        cams = self.camera.batch_shape
        if cams not in ((), (batch,)):
            raise ValueError(f"cubemap: batch {batch} does not match the camera batch "
                             f"{tuple(cams)}")
        rotation = _check_rotation(rotation, batch, ref.device)
        points = None   # a given grid's tensor, which may carry a gradient
        if grid is not None:
            grid = self._check_given_grid(grid, batch, ref.device, rotation)
            points = None if isinstance(grid, kimage.CameraGrid) else grid[0]
        if rgb is not None and not rgb.is_floating_point() and torch.is_grad_enabled() and any(
                t is not None and t.requires_grad
                for t in (rotation, self.camera.params, points)):
            raise TypeError(f"rgb: a {rgb.dtype} cubemap has no gradient; convert it to float "
                            "(ot.io.to_float) to differentiate through the rotation or camera")
        # the C++ route only where no gradient is asked for: gradients come from the twin
        route = resolve(self.backend, rgb, depth, labels, rotation, self.camera.params, points,
                        what="OmniProjection")
        call = _Call(route, depth_output, soft_labels, grid, out_dtype, channels_last)
        if soft_labels is not None:
            if labels is None:
                raise ValueError("soft_labels: needs labels")
            if isinstance(soft_labels, bool) or not isinstance(soft_labels, int) \
                    or soft_labels < 1:
                raise ValueError(f"soft_labels: expected a number of classes, got "
                                 f"{soft_labels!r}")
            if bool((labels < 0).any()) or bool((labels >= soft_labels).any()):
                raise ValueError(f"labels: ids must lie in [0, {soft_labels}) for "
                                 f"soft_labels={soft_labels}")
        if out is not None:
            produced = {"valid"} | {key for key, t in (("rgb", rgb), ("depth", depth),
                                                       ("labels", labels),
                                                       ("soft_labels", soft_labels))
                                     if t is not None}
            if not isinstance(out, dict) or not set(out) <= produced:
                raise ValueError(f"out: expected a dict with keys among {sorted(produced)}, got "
                                 f"{sorted(out) if isinstance(out, dict) else type(out).__name__}")
        pixels = math.prod(self.camera.image_size) * self.supersample ** 2
        step = max(1, CHUNK_PIXELS // pixels)
        if (route == "cpp" and rotation is not None
                and rotation.shape[0] > step and cams == ()
                and not self._grid_free(rgb, depth, labels, soft_labels)):
            # a grid per sample: a few samples at a time (see CHUNK_PIXELS), written into
            # outputs allocated once for the batch
            outputs = dict(out or {})
            for i in range(0, batch, step):
                self._render(_rows(rgb, i, step), _rows(depth, i, step), _rows(labels, i, step),
                             rotation[i:i + step], call, (outputs, slice(i, i + step), batch))
            return outputs
        if out is None:
            return self._render(rgb, depth, labels, rotation, call)
        outputs = dict(out)
        self._render(rgb, depth, labels, rotation, call, (outputs, slice(None), batch))
        return outputs

    def _check_given_grid(self, grid: object, batch: int, device: torch.device,
                          rotation: Tensor | None
                          ) -> tuple[Tensor, Tensor] | kimage.CameraGrid:
        """``render``'s ``grid`` argument, checked."""
        h, w = self.camera.image_size
        if rotation is not None or self.supersample != 1:
            raise ValueError("grid: a given grid already holds the attitude and one sample per "
                             "pixel: pass no rotation, use supersample=1")
        if isinstance(grid, kimage.CameraGrid):
            if (len(grid) not in (1, batch) or grid.image_size != (h, w)
                    or (grid.face_size, grid.pad) != (self.face_size, self.pad)):
                raise ValueError(f"grid: expected cameras (1 or {batch}) of {h} x {w} pixels "
                                 f"for faces of {self.face_size} texels padded by {self.pad}, "
                                 f"got {len(grid)} of {grid.image_size} for "
                                 f"{grid.face_size} padded by {grid.pad}")
            if device.type != "cpu":
                raise ValueError(f"grid: a CameraGrid lies on the CPU, the cubemap on {device}")
            return grid
        if not (isinstance(grid, tuple) and len(grid) == 2
                and all(isinstance(t, Tensor) for t in grid)):
            raise TypeError(f"grid: expected a tuple (grid, valid) of tensors, got "
                            f"{type(grid).__name__}")
        points, valid = grid
        if (not points.is_floating_point() or points.dim() != 4 or points.shape[0] not in
                (1, batch) or points.shape[1:] != (h, w, 2)):
            raise ValueError(f"grid: expected a floating tensor (1 or {batch}, {h}, {w}, 2), got "
                             f"{points.dtype} {tuple(points.shape)}")
        if valid.dtype != torch.bool or valid.shape != points.shape[:3]:
            raise ValueError(f"grid: expected valid, a bool tensor {tuple(points.shape[:3])}, "
                             f"got {valid.dtype} {tuple(valid.shape)}")
        if points.device != device or valid.device != device:
            raise ValueError(f"grid: on {points.device}, the cubemap is on {device}")
        return points, valid

    def _grid_free(self, rgb: Tensor | None, depth: Tensor | None, labels: Tensor | None,
                   soft_labels: int | None) -> bool:
        """Whether the C++ route renders these inputs under a rotation without building a
        grid: every sampler reads the rays (``kernels.cube.sample_rays``)."""
        rays = self.camera_rays()[0]
        wanted = ((rgb, self.interpolation), (depth, self.depth_interpolation),
                  (labels, "nearest"))
        return soft_labels is None and all(
            t is None or (mode in fastsample.MODES and fastsample.reads_rays(t.dtype, rays.dtype))
            for t, mode in wanted)

    def _render(self, rgb: Tensor | None, depth: Tensor | None, labels: Tensor | None,
                rotation: Tensor | None, call: _Call,
                into: tuple[dict, slice, int] | None = None) -> dict[str, Tensor]:
        """``render`` of checked inputs; ``into``: ``(outputs, rows, batch)``, the outputs of a
        whole batch (those missing allocated here) whose ``rows`` this call renders."""
        ref = next(t for t in (rgb, depth, labels) if t is not None)
        batch = ref.shape[0]
        grid_dtype = torch.float64 if ref.dtype == torch.float64 else torch.float32
        depth_output, soft_labels, route = call.depth_output, call.soft_labels, call.route
        if isinstance(call.grid, kimage.CameraGrid):
            grid_s = grid_c = call.grid
            valid_s = valid_c = call.grid.valid
            mask_s = mask_c = None
        elif call.grid is not None:
            points, valid_c = call.grid
            grid_s = grid_c = points.to(grid_dtype)
            valid_s = valid_c
            mask_s = mask_c = None
        elif route == "cpp" and rotation is not None:
            # a grid used once: the fast samplers compute it from the rays as they go, and take
            # the valid mask (any other sampler builds it, see _RayGrid)
            rays_s, valid_s, rays_c, valid_c = self.camera_rays()
            valid_s, valid_c = _batched(valid_s), _batched(valid_c)
            grid_s = _RayGrid(self, rays_s, rotation, grid_dtype)
            grid_c = grid_s if self.supersample == 1 else _RayGrid(self, rays_c, rotation,
                                                                   grid_dtype)
            mask_s, mask_c = valid_s, valid_c
        else:
            grid_s, valid_s, grid_c, valid_c = self.sampling_grid(rotation, grid_dtype)
            mask_s, mask_c = None, None
        valid = valid_c.expand(batch, *valid_c.shape[1:]).unsqueeze(1)
        out: dict[str, Tensor] = {"valid": valid}

        def target(key: str, shape: tuple[int, ...], dtype: torch.dtype) -> Tensor | None:
            """The rows of ``into``'s output ``key`` (per sample ``shape``), for a sampler to
            write into."""
            if into is None:
                return None
            outputs, rows, total = into
            if key not in outputs:
                outputs[key] = torch.empty((total, *shape), dtype=dtype, device=ref.device)
            given = outputs[key]
            if not isinstance(given, Tensor) or given.shape != (total, *shape) or \
                    given.dtype != dtype or given.device != ref.device:
                raise ValueError(f"out[{key!r}]: expected a {dtype} tensor of shape "
                                 f"{(total, *shape)} on {ref.device}, got "
                                 f"{getattr(given, 'dtype', type(given).__name__)} "
                                 f"{tuple(getattr(given, 'shape', ()))}")
            return given[rows]

        if rgb is not None:
            chans, (h, w) = rgb.shape[2], self.camera.image_size
            if self.supersample == 1:
                rows = target("rgb", (h, w, chans) if call.channels_last else (chans, h, w),
                              call.out_dtype)
                if rows is not None and call.channels_last:
                    rows = rows.permute(0, 3, 1, 2)
                image = self._sample_image(rgb, grid_s, self.interpolation, "bilinear", mask_s,
                                           route, rows, call.out_dtype)
            else:   # averaged in floats: a pixel whose centre is invalid may have valid samples
                work = torch.float64 if rgb.dtype == torch.float64 else torch.float32
                image = self._sample_image(rgb, grid_s, self.interpolation, "bilinear", mask_s,
                                           route, None, work)
                image = self._average(image, valid_s.expand(batch, *valid_s.shape[1:]))
                image = torch.where(valid, image, torch.zeros_like(image))
                image = from_float(image, work, call.out_dtype)
            if call.channels_last:   # (B, H, W, C): a view where it was sampled channels-last
                image = image.permute(0, 2, 3, 1).contiguous()
            out["rgb"] = image

        if depth is not None:
            rng = cm.depth_to_range(depth.squeeze(2)).unsqueeze(2)
            sampled = self._sample_depth(rng, grid_c, mask_c, route)
            if depth_output == "z":
                rays_c = self.camera_rays()[2]
                z = rays_c[..., 2] if rays_c.dim() == 4 else rays_c[..., 2].unsqueeze(0)
                sampled = sampled * z.unsqueeze(1).to(sampled.dtype)
            out["depth"] = torch.where(valid, sampled, torch.zeros_like(sampled))

        if labels is not None:
            # gathered, not grid-sampled: ids of any integer dtype and size come back exact,
            # with the ignore index outside where the ids' dtype holds it
            ignore = self.ignore_index
            rows = target("labels", tuple(valid.shape[2:]), torch.int64)
            # the kernels write int64 ids from 8-bit ones (label images) in their pass
            wide = labels.dtype == torch.uint8 or labels.dtype == torch.int64
            filled = wide or fastsample.holds(labels.dtype, ignore)
            ids = self._sample_cube(
                labels, grid_c, "nearest", "nearest", mask_c, route,
                fill=ignore if filled else 0,
                out=None if rows is None or not wide else rows.unsqueeze(1),
                out_dtype=torch.int64 if wide else None)[:, 0]
            if rows is None:
                rows = ids if ids.dtype == torch.int64 else torch.empty(
                    ids.shape, dtype=torch.int64, device=ids.device)
            if rows.data_ptr() != ids.data_ptr():
                rows.copy_(ids)
            if not filled:
                rows.masked_fill_(~valid[:, 0], ignore)
            out["labels"] = rows
            if soft_labels is not None:
                onehot = F.one_hot(labels[:, :, 0], soft_labels).permute(0, 1, 4, 2, 3)
                probs = self._sample_image(onehot.to(grid_dtype), grid_s, "bilinear", "bilinear",
                                           mask_s, route)
                probs = self._average(probs, valid_s.expand(batch, *valid_s.shape[1:]))
                out["soft_labels"] = torch.where(valid, probs, torch.zeros_like(probs))
        if into is not None:   # the other outputs: copied into their rows
            for key, value in out.items():
                rows = target(key, value.shape[1:], value.dtype)
                if rows.data_ptr() != value.data_ptr():
                    rows.copy_(value)
        return out

    def _sample_depth(self, rng: Tensor, grid: Tensor, valid: Tensor | None,
                      route: str) -> Tensor:
        """Sample range ``(B, 6, 1, F, F)``. For nearest and edge-aware sampling the border is
        padded nearest, so that no depth is blended across a seam either; plain bilinear pads
        bilinear (smooth across seams, blends across depth edges like everywhere else)."""
        work = rng if rng.dtype in (torch.float32, torch.float64) else rng.float()
        mode = self.depth_interpolation
        pad_mode = "bilinear" if mode == "bilinear" else "nearest"
        return self._sample_cube(work, grid, mode, pad_mode, valid, route).to(rng.dtype)


@dataclass(frozen=True)
class _Call:
    """What one ``render`` call decided: its route (`"cpp"` or `"torch"`, `kernels.resolve`),
    the depth output, soft labels, a given grid, the rgb image's dtype and layout."""

    route: str
    depth_output: str
    soft_labels: int | None
    grid: tuple[Tensor, Tensor] | None
    out_dtype: torch.dtype | None = None
    channels_last: bool = False


def _check_rgb(rgb: object, out_dtype: object, channels_last: bool
               ) -> tuple[Tensor, torch.dtype]:
    """``render``'s ``rgb`` as ``(B, 6, C, F, F)`` (a view of a channels-last cube) and the
    image's dtype."""
    if not isinstance(rgb, Tensor):
        raise TypeError(f"rgb: expected a tensor, got {type(rgb).__name__}")
    if channels_last:
        if rgb.dim() != 5 or rgb.shape[1] != 6 or rgb.shape[2] != rgb.shape[3]:
            raise ValueError(f"rgb: expected shape (B, 6, F, F, C) with channels_last=True, got "
                             f"{tuple(rgb.shape)}")
        rgb = rgb.permute(0, 1, 4, 2, 3)
    cm.check_cubemap(rgb, "rgb")
    if not (rgb.is_floating_point() or rgb.dtype == torch.uint8):
        raise TypeError(f"rgb: expected a floating-point or uint8 cubemap, got {rgb.dtype}")
    warn_if_label_map(rgb, 2)
    return rgb, check_out_dtype(rgb.dtype, out_dtype)


class _RayGrid:
    """The grid of camera-frame ``rays`` rotated by ``rotation``, not built yet: the fast
    samplers read the rays (``fastsample.sample_rays``), the others the grid, built on first
    use (``tensor``) with the invalid rays left where they point."""

    def __init__(self, layer: OmniProjection, rays: Tensor, rotation: Tensor,
                 dtype: torch.dtype) -> None:
        self.layer, self.rays, self.rotation, self.dtype = layer, rays, rotation, dtype
        self._grid: Tensor | None = None

    def tensor(self) -> Tensor:
        if self._grid is None:
            self._grid = self.layer._grid(self.rays, self.rotation, self.dtype)
        return self._grid


def _outside(grid: Tensor | _RayGrid | kimage.CameraGrid, valid: Tensor | None) -> Tensor:
    """``grid (B, h, w, 2)`` with the invalid entries moved outside the atlas (-2, -2); the
    grid itself where ``valid`` is None (already moved)."""
    if isinstance(grid, (_RayGrid, kimage.CameraGrid)):
        grid = grid.tensor()
    if valid is None:
        return grid
    return torch.where(valid.unsqueeze(-1), grid, torch.full_like(grid, -2.0))


def _as_cube(t: Tensor | None, name: str) -> Tensor | None:
    """Accept ``(B, 6, F, F)`` or ``(B, 6, 1, F, F)``; return ``(B, 6, 1, F, F)``."""
    if t is None:
        return None
    if not isinstance(t, Tensor):
        raise TypeError(f"{name}: expected a tensor, got {type(t).__name__}")
    if t.dim() == 4:
        t = t.unsqueeze(2)
    if t.dim() != 5 or t.shape[1] != 6 or t.shape[2] != 1 or t.shape[3] != t.shape[4]:
        raise ValueError(f"{name}: expected shape (B, 6, F, F) or (B, 6, 1, F, F), got "
                         f"{tuple(t.shape)}")
    return t


def _rows(t: Tensor | None, start: int, count: int) -> Tensor | None:
    return None if t is None else t[start:start + count]


def _batched(valid: Tensor) -> Tensor:
    return valid.unsqueeze(0) if valid.dim() == 2 else valid
