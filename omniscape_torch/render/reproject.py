"""Reprojection between any two cameras of the registry, and equirectangular panoramas.

For every pixel of the destination camera: its ray (``dst_camera.ray_grid()``), rotated into the
source camera's frame, projected by the source camera, sampled from the source image with
``grid_sample(align_corners=False)`` (pixel ``u`` is grid ``(2 u + 1) / W - 1``). A real fisheye
image becomes a pinhole or equirectangular view; a panorama becomes a cubemap.

A full (360 degree) equirectangular source wraps around in longitude: two columns of the far
side are added on each side before sampling, so bilinear and bicubic interpolation are
continuous across the +-180 degree seam; at the poles the rows are clamped (``border``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .. import cubemap as cm
from ..cameras import Camera
from ..cameras._checks import not_a_camera
from ..io.labels import IGNORE_INDEX
from .antialias import minified
from .reference import (check_out_dtype, from_float, grid_sample, nearest_gather,
                        pixels_to_grid, warn_if_label_map)

INTERPOLATIONS = ("nearest", "bilinear", "bicubic")

#: Columns added on each side of a full panorama: bicubic reads 2 texels left and right of u.
_WRAP = 2
#: Relative tolerance on ``2 pi fx = W`` for a panorama to count as full (and wrap).
_FULL_CIRCLE_RTOL = 1e-6


def equirectangular_camera(width: int, height: int, *, dtype: torch.dtype = torch.float32
                           ) -> Camera:
    """A full 360 x 180 degree panorama of ``width x height`` pixels (longitude 0 at the
    centre column, latitude positive downwards): ``fx = W / (2 pi)``, ``fy = H / pi``,
    ``cx = (W - 1) / 2``, ``cy = (H - 1) / 2``."""
    params = torch.tensor([width / (2 * math.pi), height / math.pi, (width - 1) / 2,
                           (height - 1) / 2], dtype=dtype)
    return Camera("equirectangular", params, (height, width))


def wraps_in_longitude(camera: Camera) -> bool:
    """True for an equirectangular camera whose ``W`` columns span 360 degrees
    (``2 pi fx = W``, every camera of a batch): its left and right edges are the same meridian."""
    if camera.model.name != "equirectangular":
        return False
    width = camera.image_size[1]
    fx = camera.params.detach()[..., 0]
    return bool(((2 * math.pi * fx - width).abs() <= _FULL_CIRCLE_RTOL * width).all())


def intrinsics_from_matrix(matrix: Tensor, name: str = "intrinsics") -> Tensor:
    """Pinhole ``fx, fy, cx, cy`` ``(..., 4)`` of a camera matrix ``K (..., 3, 3)`` (kornia's and
    torchvision's form, OpenCV's ``cameraMatrix``): ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``,
    pixel centres at integers.

    Raises:
        ValueError: naming ``name``: not ``(3, 3)`` / ``(B, 3, 3)``, not finite, a non-zero skew
            ``K[0, 1]`` (the pinhole model has none) or ``K[1, 0]``, or a last row other than
            ``[0, 0, 1]``.
    """
    k = torch.as_tensor(matrix)
    if k.dim() not in (2, 3) or k.shape[-2:] != (3, 3):
        raise ValueError(f"{name}: expected a camera matrix K (3, 3) or (B, 3, 3), got "
                         f"{tuple(k.shape)}")
    if not k.is_floating_point():
        k = k.double()
    if not bool(torch.isfinite(k).all()):
        raise ValueError(f"{name}: K holds non-finite values")
    skew = k[..., 0, 1]
    if bool((skew != 0).any()):
        raise ValueError(f"{name}: K has skew K[0, 1] = {skew.flatten()[skew.flatten() != 0][0]:g}"
                         f"; the pinhole source has zero skew (undistort or resample the "
                         f"images, or pass a camera of the registry)")
    if bool((k[..., 1, 0] != 0).any()):
        raise ValueError(f"{name}: K[1, 0] must be 0 in a camera matrix, got "
                         f"{k[..., 1, 0].flatten().tolist()}")
    last = torch.tensor([0.0, 0.0, 1.0], dtype=k.dtype, device=k.device)
    if bool((k[..., 2, :] != last).any()):
        raise ValueError(f"{name}: the last row of K must be [0, 0, 1], got "
                         f"{k[..., 2, :].reshape(-1, 3)[0].tolist()}")
    return torch.stack((k[..., 0, 0], k[..., 1, 1], k[..., 0, 2], k[..., 1, 2]), dim=-1)


def _is_labels(image: Tensor, labels: bool | None) -> bool:
    """Whether ``image`` is sampled as class ids: ``labels``, or by default its dtype (integer
    dtypes other than ``uint8``; a ``uint8`` tensor is an 8-bit image unless ``labels=True``)."""
    if labels is None:
        if image.dtype == torch.uint8:
            if image.dim() == 3:
                raise ValueError(f"image: a uint8 tensor {tuple(image.shape)} is ambiguous: "
                                 "uint8 is read as an 8-bit image, (B, C, H, W); pass "
                                 "labels=True for (B, H, W) class ids, or an image "
                                 "(B, C, H, W)")
            warn_if_label_map(image, 1)   # an image by default: say so if it looks like ids
            return False
        return not (image.is_floating_point() or image.is_complex())
    if labels and (image.is_floating_point() or image.is_complex()):
        raise TypeError(f"image: labels=True needs integer class ids, got {image.dtype}")
    if not labels and not (image.is_floating_point() or image.dtype == torch.uint8):
        raise TypeError(f"image: expected a floating or uint8 image (labels=False), got "
                        f"{image.dtype}; convert with ot.io.to_float, or pass labels=True for "
                        f"class ids")
    return bool(labels)


def _image_dtype(image: Tensor, labels: bool, out_dtype: object) -> torch.dtype | None:
    """The dtype of the sampled image: ``out_dtype``, by default the image's (None: labels,
    which come back int64)."""
    if labels:
        if out_dtype is not None:
            raise ValueError(f"out_dtype: describes an image; labels come back int64, got "
                             f"{out_dtype!r}")
        return None
    return check_out_dtype(image.dtype, out_dtype)


def sample_camera(image: Tensor, camera: Camera, rays: Tensor, *,
                  interpolation: str = "bilinear", labels: bool | None = None,
                  ignore_index: int = IGNORE_INDEX, out_dtype: torch.dtype | None = None,
                  antialias: bool = True) -> tuple[Tensor, Tensor]:
    """Sample ``image`` seen by ``camera`` along ``rays`` given in that camera's frame.

    Args:
        image: ``(B, C, H, W)`` floating or ``uint8`` (an 8-bit image), or integer labels
            ``(B, H, W)`` / ``(B, C, H, W)`` (nearest only, never blended). A batch of 1 is
            shared by every ray batch. Images other than float32 and float64 (``uint8``,
            float16, bfloat16) are sampled in float32, through a float32 grid.
        camera: the camera that took ``image`` (one, or a batch of ``B``).
        rays: ``(h, w, 3)`` or ``(B, h, w, 3)`` directions in the camera frame.
        interpolation: ``"nearest"``, ``"bilinear"`` or ``"bicubic"`` (images; bicubic may
            overshoot the input's range: a ``uint8`` image saturates).
        labels: treat ``image`` as integer class ids; ``None`` decides by its dtype: integer
            dtypes other than ``uint8`` are labels, ``uint8`` is an image (pass
            ``labels=True`` for ``uint8`` class ids).
        ignore_index: label of invalid pixels.
        out_dtype: the image's dtype: the input's (default; ``uint8`` rounded to nearest, half
            up, and saturated, as OpenCV's ``remap``), or a floating dtype (a ``uint8`` image
            scaled to [0, 1]). Not for labels.
        antialias: where an output pixel covers more than one source pixel (the rays' grid
            minifies), read the image through its mip pyramid, 2 x 2 taps over the pixel's
            footprint (`antialias`), instead of one point sample
            (bilinear and bicubic; ``"nearest"`` and labels are point samples). Pixels that do
            not minify are sampled as without it, bit for bit.

    Returns:
        ``values (B, C, h, w)`` in ``out_dtype`` (labels: int64, ``(B, h, w)`` for
        ``(B, H, W)`` input) and ``valid (B, 1, h, w)``: the source camera's validity (model
        domain, image bounds, fov). Invalid pixels are 0 (labels: ``ignore_index``).
    """
    if not isinstance(image, Tensor):
        raise TypeError(f"image: expected a tensor, got {type(image).__name__}")
    labels = _is_labels(image, labels)
    out_dtype = _image_dtype(image, labels, out_dtype)
    squeeze = labels and image.dim() == 3
    if squeeze:
        image = image.unsqueeze(1)
    if image.dim() != 4:
        raise ValueError(f"image: expected (B, C, H, W) (labels: (B, H, W)), got "
                         f"{tuple(image.shape)}")
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation: expected one of {INTERPOLATIONS}, got "
                         f"{interpolation!r}")
    if rays.dim() not in (3, 4) or rays.shape[-1] != 3:
        raise ValueError(f"rays: expected (h, w, 3) or (B, h, w, 3), got {tuple(rays.shape)}")
    height, width = image.shape[-2:]
    if (height, width) != camera.image_size:
        raise ValueError(f"image: size {(height, width)} does not match the camera's "
                         f"image_size {camera.image_size}")
    if not isinstance(antialias, bool):
        raise TypeError(f"antialias: expected a bool, got {antialias!r}")
    if len(camera.batch_shape) > 1:
        raise ValueError(f"camera: expected one camera or a batch (B,), got batch "
                         f"{tuple(camera.batch_shape)}")
    batches = {("image", image.shape[0])} | {("camera", n) for n in camera.batch_shape}
    if rays.dim() == 4:
        batches.add(("rays", rays.shape[0]))
    sizes = {n for what, n in batches if what != "image" or n != 1}
    if len(sizes) > 1:
        raise ValueError("batch sizes disagree: " + ", ".join(
            f"{what} {n}" for what, n in sorted(batches)))
    batch = sizes.pop() if sizes else 1

    if camera.batch_shape and rays.dim() == 3:
        rays = rays.expand(batch, *rays.shape)
    pixels, valid = camera.project(rays.to(camera.params.dtype))
    period = None
    if wraps_in_longitude(camera):
        period = float(width)
        # valid u lie in [-0.5, W - 0.5]; the padded columns hold their neighbours across the seam
        pixels = pixels + torch.tensor([float(_WRAP), 0.0], dtype=pixels.dtype,
                                       device=pixels.device)
        image = torch.cat((image[..., -_WRAP:], image, image[..., :_WRAP]), dim=-1)
        width += 2 * _WRAP
    grid = pixels_to_grid(pixels, width, height)
    # invalid lanes may project far away: keep their grid finite and their gradient zero
    grid = torch.where(valid.unsqueeze(-1), grid, torch.zeros_like(grid))
    if grid.dim() == 3:
        grid, valid = grid.unsqueeze(0), valid.unsqueeze(0)
    grid = grid.expand(batch, *grid.shape[1:])
    valid = valid.expand(batch, *valid.shape[1:]).unsqueeze(1)
    image = image.expand(batch, *image.shape[1:])
    if labels:
        out = nearest_gather(image, grid).long()
        out = torch.where(valid, out, torch.full_like(out, ignore_index))
        return (out[:, 0] if squeeze else out), valid
    if image.dtype == torch.uint8 and out_dtype == torch.uint8 and torch.is_grad_enabled() \
            and (rays.requires_grad or camera.params.requires_grad):
        raise TypeError("image: a uint8 image into a uint8 image has no gradient; pass a "
                        "floating out_dtype (or convert it with ot.io.to_float) to "
                        "differentiate through the cameras or the rotation")
    # float32 and float64 are sampled as they are; the others in float32 (a half-precision
    # grid is off by pixels, and grid_sample has no uint8 kernel)
    work = image if image.dtype in (torch.float32, torch.float64) else image.float()
    out = grid_sample(work, grid.to(work.dtype), interpolation)
    if antialias and interpolation != "nearest":
        if pixels.dim() == 3:
            pixels = pixels.unsqueeze(0)
        mip = minified(work, pixels.expand(batch, *pixels.shape[1:]), valid[:, 0], period)
        if mip is not None:
            out = torch.where(mip[1], mip[0].to(out.dtype), out)
    out = torch.where(valid, out, torch.zeros_like(out))
    return from_float(out, image.dtype, out_dtype), valid


def reproject(image: Tensor, src_camera: Camera | Tensor, dst_camera: Camera, *,
              rotation: Tensor | None = None, interpolation: str = "bilinear",
              labels: bool | None = None, ignore_index: int = IGNORE_INDEX,
              out_dtype: torch.dtype | None = None, antialias: bool = True,
              backend: str = "auto") -> tuple[Tensor, Tensor]:
    """Resample ``image`` taken by ``src_camera`` into ``dst_camera`` (same centre).

    ``out[b, :, v, u] = image[b]`` sampled at ``src.project(R @ dst.unproject(u, v))``.

    Args:
        image: ``(B, C, H_src, W_src)`` floating or ``uint8`` (an 8-bit image), or integer
            labels ``(B, H_src, W_src)`` / ``(B, C, H_src, W_src)``. A batch of 1 is shared by a
            batch of cameras/rotations.
        src_camera: any camera of the registry (one, or a batch of ``B`` of one model; e.g. a
            distorted ``opencv`` camera or an Aria ``fisheye624`` read by ``Camera.load``), or a
            pinhole camera matrix ``K (3, 3)`` / ``(B, 3, 3)`` (zero skew, last row
            ``[0, 0, 1]``) of images of ``image``'s size. Its validity (model domain, image
            bounds, ``fov``) is part of ``valid``. Samples of different source models: one call
            per model.
        dst_camera: any camera of the registry (one, or a batch of ``B``), the five models of
            other tools (``fov``, ``division``, ``opencv``, ``thin_prism_fisheye``,
            ``fisheye624``) included.
        rotation: optional ``(3, 3)`` or ``(B, 3, 3)`` mapping destination-camera rays into the
            source camera's frame, ``ray_src = R @ ray_dst`` (default: the same orientation).
        interpolation: ``"nearest"``, ``"bilinear"`` or ``"bicubic"``; labels are always nearest.
        labels: treat ``image`` as integer class ids; ``None`` decides by its dtype (integer
            dtypes other than ``uint8``; pass ``labels=True`` for ``uint8`` class ids).
        ignore_index: label of invalid pixels.
        out_dtype: the image's dtype: the input's (default; ``uint8`` rounded to nearest, half
            up, and saturated), or a floating dtype (a ``uint8`` image scaled to [0, 1]).
        antialias: prefilter the image where the destination minifies it (a pixel covering
            more than one source pixel): mip lookups over each pixel's footprint
            (`sample_camera`); False: one point sample per pixel. Pixels that do not
            minify are the same either way, bit for bit.
        backend: ``"auto"`` (default): on the CPU without gradients, a pinhole source into a
            radially symmetric destination (``kernels.camera.RADIAL``; nearest or bilinear)
            takes the C++ path of ``RandomReproject``: the destination's rays from its radius
            table (``kernels.camera.camera_rays``), the image sampled along them
            (``kernels.image.sample_image``, then ``mip_image`` where it minifies), the same
            kernels in the same order, so a ``RandomReproject`` with a fixed ``camera`` and no
            jitter gives this image bit for bit; everything else (and ``"torch"``) the torch
            path below; ``"cpp"`` the C++ path or an error.

    Returns:
        ``image (B, C, H_dst, W_dst)`` in ``out_dtype`` (labels: int64, ``(B, H_dst, W_dst)``
        for ``(B, H_src, W_src)`` input) and ``valid (B, 1, H_dst, W_dst)``: valid in both
        cameras. Invalid pixels are 0 (labels: ``ignore_index``). Differentiable with respect to
        the image, both cameras' parameters and the rotation (bilinear and bicubic; a ``uint8``
        image into a floating ``out_dtype``: the cameras and the rotation). The sampling grid is
        built in the cameras' dtype and cast to the image's (float32 for ``uint8``, float16 and
        bfloat16 images, which are sampled in float32 and rounded once).

    Examples:
        >>> import omniscape_torch as ot, torch
        >>> pano = torch.rand(1, 3, 64, 128)
        >>> fisheye = ot.Camera("equidistant", [20.0, 20.0, 31.5, 31.5], (64, 64))
        >>> out, valid = ot.reproject(pano, ot.equirectangular_camera(128, 64), fisheye)
        >>> out.shape, valid.shape
        (torch.Size([1, 3, 64, 64]), torch.Size([1, 1, 64, 64]))
    """
    if not isinstance(image, Tensor):
        raise TypeError(f"image: expected a tensor, got {type(image).__name__}")
    labels = _is_labels(image, labels)
    if isinstance(src_camera, Tensor):   # a camera matrix K: the pinhole of the image's size
        src_camera = Camera("pinhole", intrinsics_from_matrix(src_camera, "src_camera"),
                            tuple(image.shape[-2:]))
    elif not isinstance(src_camera, Camera):
        raise not_a_camera("src_camera", src_camera,
                           "an ot.Camera or a camera matrix K (3, 3) / (B, 3, 3)")
    if not isinstance(dst_camera, Camera):
        raise not_a_camera("dst_camera", dst_camera)
    if len(src_camera.batch_shape) == 1:
        n = src_camera.batch_shape[0]
        if image.shape[0] not in (1, n):
            raise ValueError(f"batch sizes disagree: src_camera {n}, image {image.shape[0]}")
        if len(dst_camera.batch_shape) == 1 and dst_camera.batch_shape[0] != n:
            raise ValueError(f"batch sizes disagree: src_camera {n}, dst_camera "
                             f"{dst_camera.batch_shape[0]}")
    if rotation is not None:
        cm.check_rotation(rotation)
        if rotation.dim() not in (2, 3):
            raise ValueError(f"rotation: expected (3, 3) or (B, 3, 3), got "
                             f"{tuple(rotation.shape)}")
        cams = dst_camera.batch_shape
        if rotation.dim() == 3 and len(cams) == 1 and len(rotation) != cams[0]:
            raise ValueError(f"batch sizes disagree: rotation {len(rotation)}, dst_camera "
                             f"{cams[0]}")
    _image_dtype(image, labels, out_dtype)   # (both paths: checked once here)
    fast = _fast_path(image, labels, src_camera, dst_camera, rotation, interpolation,
                      antialias, backend)
    if fast is not None:
        return _reproject_fast(image, labels, src_camera, dst_camera, rotation, interpolation,
                               ignore_index, out_dtype, antialias, *fast)
    rays, valid_dst = dst_camera.ray_grid()  # [(B,) h, w, 3]
    if rotation is not None:
        rot = rotation.to(rays.dtype)
        rays = (torch.einsum("ij,...hwj->...hwi", rot, rays) if rot.dim() == 2
                else torch.einsum("bij,bhwj->bhwi", rot, rays.expand(len(rot), *rays.shape[-3:])))
    values, valid = sample_camera(image, src_camera, rays, interpolation=interpolation,
                                  labels=labels, ignore_index=ignore_index, out_dtype=out_dtype,
                                  antialias=antialias)
    valid_dst = valid_dst.unsqueeze(0) if valid_dst.dim() == 2 else valid_dst
    valid = valid & valid_dst.unsqueeze(1)
    if not labels:
        return torch.where(valid, values, torch.zeros_like(values)), valid
    mask = valid[:, 0] if values.dim() == 3 else valid
    return torch.where(mask, values, torch.full_like(values, ignore_index)), valid


def equirect_to_cubemap(panorama: Tensor, face_size: int, *, interpolation: str = "bilinear",
                        labels: bool | None = None, ignore_index: int = IGNORE_INDEX,
                        out_dtype: torch.dtype | None = None) -> Tensor:
    """The six faces (``FACES`` order, DESIGN.md's orientation) of a full equirectangular
    panorama.

    Face ``k`` is ``reproject(panorama, equirectangular_camera(W, H), face_pinhole,
    rotation=face_rotations()[k])`` with the face pinhole ``fx = fy = F / 2``,
    ``cx = cy = (F - 1) / 2``; the six faces are sampled in one call, the geometry in float64.
    Point samples (``reproject(..., antialias=False)``'s): faces of ``F >= W / 4`` do not
    minify the panorama but around its poles, where a face pixel's footprint is no
    parallelogram (a pole is a whole row).

    Args:
        panorama: ``(B, C, H, W)`` floating or ``uint8`` (an 8-bit image), or integer labels
            ``(B, H, W)`` (nearest).
        face_size: ``F``.
        interpolation: ``"nearest"``, ``"bilinear"`` or ``"bicubic"``.
        labels: treat ``panorama`` as integer class ids; ``None`` decides by its dtype (integer
            dtypes other than ``uint8``; pass ``labels=True`` for ``uint8`` class ids).
        out_dtype: the faces' dtype (`sample_camera`): the panorama's (default; ``uint8``
            rounded to nearest, half up), or a floating dtype (``uint8`` scaled to [0, 1]).

    Returns:
        ``(B, 6, C, F, F)`` in ``out_dtype`` (labels ``(B, 6, F, F)`` int64, or
        ``(B, 6, C, F, F)`` for ``(B, C, H, W)`` labels). Every texel is valid.
    """
    if not isinstance(face_size, int) or isinstance(face_size, bool) or face_size < 1:
        raise ValueError(f"face_size: expected a positive int, got {face_size!r}")
    if not isinstance(panorama, Tensor) or panorama.dim() < 3:
        raise ValueError(f"panorama: expected (B, C, H, W) (labels: (B, H, W)), got "
                         f"{tuple(getattr(panorama, 'shape', ())) or type(panorama).__name__}")
    height, width = panorama.shape[-2:]
    if width != 2 * height:
        raise ValueError(f"panorama: expected a full equirectangular panorama, W = 2 H (360 x "
                         f"180 degrees), got H x W = {height} x {width}; for part of the "
                         f"sphere, reproject from its camera with ot.reproject")
    camera = equirectangular_camera(width, height, dtype=torch.float64).to(panorama.device)
    rays = cm.face_rays(face_size, dtype=torch.float64, device=panorama.device, normalize=True)
    values, _ = sample_camera(panorama, camera, rays.reshape(6 * face_size, face_size, 3),
                              interpolation=interpolation, labels=labels,
                              ignore_index=ignore_index, out_dtype=out_dtype, antialias=False)
    if values.dim() == 3:  # labels (B, 6F, F)
        return values.reshape(-1, 6, face_size, face_size)
    faces = values.reshape(values.shape[0], values.shape[1], 6, face_size, face_size)
    return faces.transpose(1, 2)


def _fast_path(image: Tensor, labels: bool, src: Camera, dst: Camera, rotation: Tensor | None,
               interpolation: str, antialias: bool, backend: str
               ) -> tuple[torch.dtype, str] | None:
    """`reproject`'s C++ case (its `backend` docstring): `(the rays' dtype, the dst model)`, or
    None for the torch path (`"cpp"` where it is not the case: an error)."""
    from .kernels import resolve
    from .kernels.camera import RADIAL
    from .kernels.cube import BLENDED, work_dtype
    from .kernels.image import MIPMAPPED
    route = resolve(backend, image, src.params, dst.params, rotation, what="reproject")
    if route != "cpp":
        return None
    model = dst.model.name
    dtype = torch.float64 if image.dtype == torch.float64 else torch.float32
    blended = labels or (image.dtype in BLENDED and (
        not antialias or interpolation == "nearest" or image.dtype in MIPMAPPED))
    unified_lens = model == "unified" and bool(dst.params.detach()[..., 7:9].ne(0).any())
    case = (src.model.name == "pinhole" and src.fov is None and src.blind_fov is None
            and model in RADIAL and not unified_lens and len(dst.batch_shape) <= 1
            and len(src.batch_shape) <= 1 and interpolation in ("nearest", "bilinear")
            and blended and (labels or work_dtype(image.dtype) == dtype))
    if case:
        return dtype, model
    if backend == "cpp":
        raise ValueError("backend: 'cpp' reprojects a pinhole source into a radially "
                         f"symmetric camera ({', '.join(RADIAL)}), nearest or bilinear; got "
                         f"{src.model.name} -> {model}, {interpolation}")
    return None


def _reproject_fast(image: Tensor, labels: bool, src: Camera, dst: Camera,
                    rotation: Tensor | None, interpolation: str, ignore_index: int,
                    out_dtype: torch.dtype | None, antialias: bool, dtype: torch.dtype,
                    model: str) -> tuple[Tensor, Tensor]:
    """`reproject`'s C++ path (`_fast_path`): the kernels `RandomReproject` runs op by op."""
    from .kernels import camera as kcamera
    from .kernels import image as kimage
    from .kernels.cube import output_dtypes
    squeeze = labels and image.dim() == 3
    work = image.unsqueeze(1) if squeeze else image
    if work.dim() != 4:
        raise ValueError(f"image: expected (B, C, H, W) (labels: (B, H, W)), got "
                         f"{tuple(image.shape)}")
    if tuple(work.shape[-2:]) != src.image_size:
        raise ValueError(f"image: size {tuple(work.shape[-2:])} does not match the camera's "
                         f"image_size {src.image_size}")
    # (in the rays' dtype, as RandomReproject hands its cameras to the same kernels)
    params = dst.params.detach().reshape(-1, dst.params.shape[-1]).to(dtype)
    fov = None if dst.fov is None else torch.as_tensor(dst.fov).reshape(-1).expand(len(params))
    rays, valid = kcamera.camera_rays(model, params, dst.image_size, fov=fov, dtype=dtype,
                                      backend="cpp")
    if dst.blind_fov is not None:   # the central blind cone of the destination
        cos = torch.cos(0.5 * torch.as_tensor(dst.blind_fov, dtype=torch.float64))
        valid = valid & (rays[..., 2] < cos.reshape(-1, 1, 1).to(rays.dtype))
    k = src.params.detach().reshape(-1, 4).to(dtype)
    rot = None if rotation is None else rotation.detach().reshape(-1, 3, 3).to(dtype)
    batch = max(len(work), len(rays), len(k), 1 if rot is None else len(rot))
    if len(work) not in (1, batch):
        raise ValueError(f"batch sizes disagree: image {len(work)}, cameras {batch}")
    work = work.expand(batch, *work.shape[1:])
    if labels:
        wide = work.dtype in (torch.uint8, torch.int64)
        ids, seen = kimage.sample_image(work, rays, rot, k, "nearest", valid=valid,
                                        fill=ignore_index if wide else 0,
                                        out_dtype=torch.int64 if wide else None)
        ids = ids.long()
        if not wide:
            ids = torch.where(seen.unsqueeze(1), ids, torch.full_like(ids, ignore_index))
        mask = seen.unsqueeze(1)
        return (ids[:, 0] if squeeze else ids), mask
    out_dtype = check_out_dtype(image.dtype, out_dtype)
    written = output_dtypes(image.dtype, interpolation)   # by the kernels, in the same pass
    kernel_dtype = out_dtype if out_dtype in written else written[-1]
    values, seen = kimage.sample_image(work, rays, rot, k, interpolation, valid=valid,
                                       out_dtype=kernel_dtype)
    if antialias and interpolation == "bilinear":
        kimage.mip_image(work, rays, rot, k, seen, values)
    return values.to(out_dtype), seen.unsqueeze(1)
