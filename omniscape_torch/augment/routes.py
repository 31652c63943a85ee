"""The render routes of `RandomReproject` (mixed into it): the C++ ops in one fused call or op
by op, or the exact torch path."""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch
from torch import Tensor

from ..cameras import Camera
from ..render.antialias import MINIFIES
from ..render.kernels import image as fast
from ..render.kernels.camera import camera_rays
from ..render.reproject import sample_camera
from .targets import _Part, _slices


class _Routes:
    """`RandomReproject`'s render routes."""

    def _rays(self, name: str, params: Tensor, fov: Tensor) -> tuple[Tensor, Tensor]:
        """The unit rays ``(n, H, W, 3)`` and validity ``(n, H, W)`` of ``n`` cameras of model
        ``name`` (``params (n, P)`` in the rays' dtype, float32 or float64) within their fields
        of view ``fov (n,)``: `camera_rays`, through
        the table of `_unit_lens` where the model has one."""
        if self._unit_lens(name) is None:
            return camera_rays(name, params, self.image_size, fov=fov, dtype=params.dtype,
                               backend=self.backend)
        return fast.camera_rays(*self._tables(name, params, fov), self.image_size, params.dtype)

    def _tables(self, name: str, params: Tensor, fov: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``affine (n, 6)``, ``limits (n, 5)`` and ``table (1, 2, K)`` of ``n`` cameras of a
        model with a `_unit_lens` table, in the dtype of ``params (n, P)``, as
        `camera_rays` takes them: ``cx, cy`` and ``M =
        diag(1 / fx, 1 / fy)``, the table's limits with ``cos(fov / 2)`` and no blind cone."""
        unit = self._unit_lens(name)
        cams = params.numpy()[:, :4].astype(np.float64)   # (NumPy's slicing: cheaper)
        n = len(cams)
        affine = np.zeros((n, 6))          # cx, cy and M = diag(1 / fx, 1 / fy)
        affine[:, :2] = cams[:, 2:]
        affine[:, 2::3] = 1 / cams[:, :2]
        limits = np.empty((n, 5))          # scale, root, end, cos(fov / 2), no blind cone
        limits[:] = unit.limits_row
        limits[:, 3] = np.cos(0.5 * fov.numpy().astype(np.float64))
        table = unit.tables[params.dtype]
        as_dtype = cams.dtype if params.dtype == torch.float64 else np.float32   # the rays'
        return (torch.from_numpy(affine.astype(as_dtype)),
                torch.from_numpy(limits.astype(as_dtype)), table)


    def _render_fast(self, name: str, part: "_Part", image: Tensor | None,
                     labels: Tensor | None, depth: Tensor | None, result: dict,
                     scan: Callable | None = None) -> None:
        """The samples ``part.index`` through the C++ ops: the cameras' rays from their tables
        (or ``Camera.ray_grid`` where a model has none), then ``fast.sample_image``; ``scan``
        (if given) reads the rays as ``sample_image`` does. The common case (a lens with a
        table, a pinhole source, image and ``uint8`` or int64 labels, no depth, no detection
        targets) runs as one call of the C++ op ``reproject_image`` per run of samples: the
        same kernels, in the same order, without the rays in Python."""
        if (part.source is None and scan is None and depth is None and
                self._unit_lens(name) is not None and
                (image is None or image.dtype in fast.MIPMAPPED or not self.antialias) and
                (labels is None or labels.dtype in (torch.uint8, torch.int64))):
            self._render_fused(name, part, image, labels, result)
            return
        rays, valid = self._rays(name, part.params, part.fov)
        target, rotation = rays, part.rotation
        if part.source is None:
            k = part.intrinsics.to(rays.dtype)
        else:
            # any other source model: the rays projected by it in torch, in its dtype; the C++
            # op then reads the pixels as the rays (u, v, 1) of the unit pinhole (fx = fy = 1,
            # cx = cy = 0), so u = 1 * (u / 1) + 0 exactly, and checks the image bounds
            src = torch.einsum("bij,bhwj->bhwi", rotation.to(part.source.params.dtype),
                               rays.to(part.source.params.dtype))
            pixels, seen_src = part.source.project(src)                      # (n, h, w, 2)
            valid = valid & seen_src
            pixels = torch.where(valid.unsqueeze(-1), pixels, torch.full_like(pixels, -2.0))
            rays = torch.cat((pixels, torch.ones_like(pixels[..., :1])), dim=-1)
            rotation = None
            k = torch.tensor([[1.0, 1.0, 0.0, 0.0]], dtype=rays.dtype)
        if scan is not None:
            scan(part.index, rays, rotation, k, valid)
        for at, (a, b) in _slices(part.index):   # runs of consecutive samples: views
            rows = slice(a, b)
            rot = None if rotation is None else rotation[rows]
            kr = k if part.source is not None else k[rows]
            seen = result["valid"][at, 0]
            if image is not None:
                _, seen_rgb = fast.sample_image(
                    image[at], rays[rows], rot, kr, self.interpolation,
                    valid=valid[rows], out=result["rgb"][at], out_dtype=result["rgb"].dtype)
                seen.copy_(seen_rgb)
                if self.antialias and self.interpolation != "nearest":
                    self._antialias(image[at], rays[rows], rot, kr, seen_rgb,
                                    result["rgb"][at])
            if labels is not None:
                wide = labels.dtype in (torch.uint8, torch.int64)   # int64 ids in the pass
                out = result["labels"][at].unsqueeze(1)
                ids, seen_ids = fast.sample_image(
                    labels[at].unsqueeze(1), rays[rows], rot, kr,
                    "nearest", valid=valid[rows], fill=self.ignore_index if wide else 0,
                    out=out if wide else None, out_dtype=torch.int64 if wide else None)
                if not wide:
                    out.copy_(torch.where(seen_ids.unsqueeze(1), ids.long(),
                                          torch.full_like(out, self.ignore_index)))
                seen.copy_(seen_ids)
            if depth is not None:
                z, seen_z = fast.sample_image(depth[at], rays[rows], rot, kr, "nearest",
                                              valid=valid[rows])
                result["depth"][at] = self._range(z, target[rows], part.rotation[rows],
                                                  seen_z.unsqueeze(1))
                seen.copy_(seen_z)

    def _render_fused(self, name: str, part: "_Part", image: Tensor | None,
                      labels: Tensor | None, result: dict) -> None:
        """`_render_fast` of the common case, one ``reproject_image`` call per run of
        consecutive samples."""
        affine, limits, table = self._tables(name, part.params, part.fov)
        k = part.intrinsics.to(part.params.dtype).contiguous()   # (an expanded (4,) row)
        minifies = (MINIFIES if image is not None and self.antialias and
                    self.interpolation != "nearest" else 0.0)
        rgb, ids, valid = result.get("rgb"), result.get("labels"), result["valid"][:, 0]
        for at, (a, b) in _slices(part.index):   # runs of consecutive samples
            whole = b - a == len(valid)          # the batch: the tensors, not views of them

            def rows(t: Tensor | None, index: slice) -> Tensor | None:
                return t if t is None or whole else t[index]

            fast.reproject_image(
                rows(image, at), rows(labels, at), rows(affine, slice(a, b)),
                rows(limits, slice(a, b)), table, rows(part.rotation, slice(a, b)),
                rows(k, slice(a, b)), self.interpolation == "bilinear", minifies,
                self.ignore_index, rows(rgb, at), rows(ids, at), rows(valid, at),
                trusted=True)   # (the inputs are the module's own: checked)

    @staticmethod
    def _antialias(image: Tensor, rays: Tensor, rotation: Tensor | None, k: Tensor,
                   seen: Tensor, out: Tensor) -> None:
        """Overwrite the pixels of ``out`` (the fast op's samples) whose footprint minifies the
        source with its mip filter, `mip_image`; float16
        and bfloat16 images through float32, in which the op blends them."""
        if image.dtype in fast.MIPMAPPED:
            fast.mip_image(image, rays, rotation, k, seen, out)
        else:
            work = out.float()
            fast.mip_image(image.float(), rays, rotation, k, seen, work)
            out.copy_(work)

    def _render_exact(self, name: str, part: "_Part", image: Tensor | None,
                      labels: Tensor | None, depth: Tensor | None, result: dict) -> None:
        """The samples ``part.index`` through ``Camera.ray_grid`` and ``sample_camera``
        (``grid_sample``; any device, differentiable with respect to the images)."""
        camera = Camera(name, part.params, self.image_size)
        rays, valid = camera.ray_grid()                                     # (n, h, w, 3)
        valid = valid & (rays[..., 2] >= torch.cos(0.5 * part.fov)[:, None, None])
        src = torch.einsum("bij,bhwj->bhwi", part.rotation, rays)
        source = (Camera("pinhole", part.intrinsics.to(rays.dtype), part.source_size)
                  if part.source is None else part.source)
        mask = valid.unsqueeze(1)
        sel = part.index.to(result["valid"].device)
        seen = None
        if image is not None:
            values, ok = sample_camera(image[sel], source, src, interpolation=self.interpolation,
                                       out_dtype=result["rgb"].dtype, antialias=self.antialias)
            seen = ok & mask
            result["rgb"][sel] = torch.where(seen, values, torch.zeros_like(values))
        if labels is not None:
            ids, ok = sample_camera(labels[sel], source, src, labels=True,
                                    ignore_index=self.ignore_index)
            seen = ok & mask
            result["labels"][sel] = torch.where(seen[:, 0], ids, self.ignore_index)
        if depth is not None:
            z, ok = sample_camera(depth[sel], source, src, interpolation="nearest")
            seen = ok & mask
            result["depth"][sel] = self._range(z, rays, part.rotation, seen)
        result["valid"][sel] = seen

    def _range(self, z: Tensor, rays: Tensor, rotation: Tensor, seen: Tensor) -> Tensor:
        """Planar source depth ``z (n, 1, h, w)`` sampled along unit fisheye ``rays (n, h, w,
        3)`` -> their range (``|p| = z / cos`` of the ray to the source axis), or its ``z`` along
        the fisheye's axis (``depth_output``); 0 where not ``seen``."""
        axis = torch.einsum("bj,bhwj->bhw", rotation[:, 2].to(rays.dtype), rays)   # src z
        # a wide source (a fisheye) sees rays at or past 90 degrees: no planar depth there (0)
        seen = seen & (axis > 0).unsqueeze(1)
        cos = torch.where(seen[:, 0], axis, torch.ones_like(axis)).unsqueeze(1)
        out = z.to(rays.dtype) / cos
        if self.depth_output == "z":
            out = out * rays[..., 2].unsqueeze(1)
        return torch.where(seen, out, torch.zeros_like(out)).to(z.dtype)

