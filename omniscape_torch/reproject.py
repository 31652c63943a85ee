"""Reprojection between any two cameras of the registry, and equirectangular panoramas.

For every pixel of the destination camera: its ray (``dst_camera.ray_grid()``), rotated into the
source camera's frame, projected by the source camera, sampled from the source image. A real
fisheye image becomes a pinhole or equirectangular view; a panorama becomes a cubemap.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from . import cubemap as cm
from .cameras import Camera
from .io.labels import IGNORE_INDEX
from .sampling import grid_sample, nearest_gather, pixels_to_grid

INTERPOLATIONS = ("nearest", "bilinear", "bicubic")


def equirectangular_camera(width: int, height: int, *, dtype: torch.dtype = torch.float32
                           ) -> Camera:
    """A full 360 x 180 degree panorama of ``width x height`` pixels (longitude 0 at the
    centre column, latitude positive downwards)."""
    params = torch.tensor([width / (2 * math.pi), height / math.pi, (width - 1) / 2,
                           (height - 1) / 2], dtype=dtype)
    return Camera("equirectangular", params, (height, width))


def sample_camera(image: Tensor, camera: Camera, rays: Tensor, *,
                  interpolation: str = "bilinear", ignore_index: int = IGNORE_INDEX
                  ) -> tuple[Tensor, Tensor]:
    """Sample ``image`` seen by ``camera`` along ``rays`` given in that camera's frame.

    Args:
        image: ``(B, C, H, W)`` floating, or integer labels ``(B, H, W)`` / ``(B, 1, H, W)``
            (nearest only, never blended).
        camera: the camera that took ``image`` (one, or a batch of ``B``).
        rays: ``(h, w, 3)`` or ``(B, h, w, 3)`` directions in the camera frame.
        interpolation: ``"nearest"``, ``"bilinear"`` or ``"bicubic"`` (floating images).
        ignore_index: label of invalid pixels.

    Returns:
        ``values (B, C, h, w)`` (labels: ``(B, h, w)`` int64) and ``valid (B, 1, h, w)``; invalid
        pixels are 0 (labels: ``ignore_index``). An equirectangular source wraps around in
        longitude, so sampling is continuous across its +-180 degree seam.
    """
    if not isinstance(image, Tensor):
        raise TypeError(f"image: expected a tensor, got {type(image).__name__}")
    labels = not image.is_floating_point()
    if labels and image.dim() == 3:
        image = image.unsqueeze(1)
    if image.dim() != 4:
        raise ValueError(f"image: expected (B, C, H, W) (labels: (B, H, W)), got "
                         f"{tuple(image.shape)}")
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation: expected one of {INTERPOLATIONS}, got "
                         f"{interpolation!r}")
    batch, _, height, width = image.shape
    if (height, width) != camera.image_size:
        raise ValueError(f"image: size {(height, width)} does not match the camera's "
                         f"image_size {camera.image_size}")
    if camera.batch_shape not in ((), (batch,)):
        raise ValueError(f"image: batch {batch} does not match the camera batch "
                         f"{tuple(camera.batch_shape)}")
    if camera.batch_shape and rays.dim() == 3:
        rays = rays.expand(batch, *rays.shape)
    pixels, valid = camera.project(rays.to(camera.params.dtype))
    if camera.model.name == "equirectangular":
        # wrap in longitude: two columns of the far side on each side of the panorama
        image = torch.cat((image[..., -2:], image, image[..., :2]), dim=-1)
        pixels = pixels + torch.tensor([2.0, 0.0], dtype=pixels.dtype, device=pixels.device)
        width += 4
    grid = pixels_to_grid(pixels, width, height)
    if grid.dim() == 3:
        grid, valid = grid.unsqueeze(0), valid.unsqueeze(0)
    valid = valid.expand(batch, *valid.shape[1:]).unsqueeze(1)
    if labels:
        out = nearest_gather(image, grid)[:, 0]
        return torch.where(valid[:, 0], out.long(), torch.full_like(out.long(), ignore_index)), valid
    grid = grid.to(image.dtype).expand(batch, *grid.shape[1:])
    out = grid_sample(image, grid, interpolation)
    return torch.where(valid, out, torch.zeros_like(out)), valid


def reproject(image: Tensor, src_camera: Camera, dst_camera: Camera, *,
              rotation: Tensor | None = None, interpolation: str = "bilinear",
              ignore_index: int = IGNORE_INDEX) -> tuple[Tensor, Tensor]:
    """Resample ``image`` taken by ``src_camera`` into ``dst_camera`` (same centre).

    Args:
        image: ``(B, C, H_src, W_src)`` floating, or integer labels ``(B, H_src, W_src)``.
        src_camera, dst_camera: any cameras of the registry (one, or a batch of ``B``).
        rotation: optional ``(3, 3)`` or ``(B, 3, 3)`` mapping destination-camera rays into the
            source camera's frame (default: the same orientation).
        interpolation: ``"nearest"``, ``"bilinear"`` or ``"bicubic"``.

    Returns:
        ``image (B, C, H_dst, W_dst)`` (labels ``(B, H_dst, W_dst)``) and ``valid
        (B, 1, H_dst, W_dst)``: valid in both cameras. Differentiable with respect to the image,
        both cameras' parameters and the rotation.
    """
    rays, valid_dst = dst_camera.ray_grid()
    if rotation is not None:
        if not isinstance(rotation, Tensor) or rotation.shape[-2:] != (3, 3) \
                or rotation.dim() not in (2, 3):
            raise ValueError(f"rotation: expected (3, 3) or (B, 3, 3), got "
                             f"{tuple(getattr(rotation, 'shape', ()))}")
        rot = rotation.to(rays.dtype)
        rays = (torch.einsum("ij,...hwj->...hwi", rot, rays) if rot.dim() == 2
                else torch.einsum("bij,bhwj->bhwi", rot, rays.expand(len(rot), *rays.shape[-3:])))
    values, valid = sample_camera(image, src_camera, rays, interpolation=interpolation,
                                  ignore_index=ignore_index)
    valid_dst = valid_dst.unsqueeze(0) if valid_dst.dim() == 2 else valid_dst
    valid = valid & valid_dst.unsqueeze(1)
    if values.is_floating_point():
        return torch.where(valid, values, torch.zeros_like(values)), valid
    return torch.where(valid[:, 0], values, torch.full_like(values, ignore_index)), valid


def equirect_to_cubemap(panorama: Tensor, face_size: int, *, interpolation: str = "bilinear",
                        ignore_index: int = IGNORE_INDEX) -> Tensor:
    """The six faces (``FACES`` order, DESIGN.md's orientation) of a full equirectangular
    panorama.

    Args:
        panorama: ``(B, C, H, W)`` floating, or integer labels ``(B, H, W)`` (nearest).
        face_size: ``F``.

    Returns:
        ``(B, 6, C, F, F)`` (labels ``(B, 6, F, F)``).
    """
    if not isinstance(face_size, int) or isinstance(face_size, bool) or face_size < 1:
        raise ValueError(f"face_size: expected a positive int, got {face_size!r}")
    height, width = panorama.shape[-2:]
    dtype = panorama.dtype if panorama.is_floating_point() else torch.float32
    camera = equirectangular_camera(width, height, dtype=torch.float64)
    camera = camera.to(panorama.device)
    rays = cm.face_rays(face_size, dtype=torch.float64, device=panorama.device, normalize=True)
    values, _ = sample_camera(panorama, camera, rays.reshape(6 * face_size, face_size, 3),
                              interpolation=interpolation, ignore_index=ignore_index)
    if values.dim() == 3:  # labels (B, 6F, F)
        return values.reshape(-1, 6, face_size, face_size)
    return values.reshape(values.shape[0], values.shape[1], 6, face_size, face_size) \
        .transpose(1, 2).to(dtype)
