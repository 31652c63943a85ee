"""The detection boxes' kernels: box outlines mapped through a camera change, and the pixels of
the boxes that the valid area cuts, read from the rays a renderer samples along; the C++ ops
`outline_points`, `outline_reduce` and `box_pixels`, each beside its torch twin
(`render.detection` calls them; the guide: `docs/detection.md`).
"""

from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor

from ._backend import choose

__all__ = ["box_pixels", "extent", "outline", "outlines"]


def outline(rects: Tensor, counts: Tensor) -> tuple[Tensor, Tensor]:
    """Points on the outlines of `rects (R, 4)` (pixel-centre x0, y0, x1, y1), `counts (R,)`
    per edge -> `(T, 2)` points and their rectangle index `(T,)`."""
    x0, y0, x1, y1 = rects.unbind(-1)
    corners = torch.stack((torch.stack((x0, y0), -1), torch.stack((x1, y0), -1),
                           torch.stack((x1, y1), -1), torch.stack((x0, y1), -1)), 1)  # (R, 4, 2)
    start, end = corners, corners.roll(-1, dims=1)
    per_edge = counts.repeat_interleave(4)                                   # (R * 4,)
    edge = torch.arange(len(per_edge)).repeat_interleave(per_edge)
    first = torch.cumsum(per_edge, 0) - per_edge
    t = ((torch.arange(len(edge)) - first[edge]).to(rects.dtype)
         / per_edge[edge].to(rects.dtype))[:, None]
    start, end = start.reshape(-1, 2)[edge], end.reshape(-1, 2)[edge]
    return start + t * (end - start), torch.arange(len(rects)).repeat_interleave(4 * counts)


def extent(points: Tensor, ok: Tensor, owner: Tensor, count: int) -> Tensor:
    """`(count, 4)` min x, min y, max x, max y of the `ok` points per `owner` (inf where
    none)."""
    inf = torch.full((count, 2), math.inf, dtype=points.dtype)
    big = torch.where(ok[:, None], points, torch.full_like(points, math.inf))
    small = torch.where(ok[:, None], points, torch.full_like(points, -math.inf))
    lo = inf.scatter_reduce(0, owner[:, None].expand(-1, 2), big, "amin")
    hi = (-inf).scatter_reduce(0, owner[:, None].expand(-1, 2), small, "amax")
    return torch.cat((lo, hi), -1)


def _on_centres(pixels: Tensor, w: int, h: int) -> Tensor:
    """Where `pixels` lie within the outer pixel centres `[0, W - 1] x [0, H - 1]`."""
    u, v = pixels[..., 0], pixels[..., 1]
    return (u >= -1e-9) & (u <= w - 1 + 1e-9) & (v >= -1e-9) & (v <= h - 1 + 1e-9)


def outlines(rects: Tensor, counts: Tensor, owner: Tensor, padded: Tensor, extra: int,
             forward: Callable[[Tensor], tuple[Tensor, Tensor, Tensor]],
             size: tuple[int, int], step: float, *, backend: str = "auto"
             ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The outlines of `rects (m, 4)` (pixel centres) of the samples `owner (m,)` (sorted),
    `counts (m,)` points per edge, written into the rows of `padded (n, columns, 2)` after
    their first `extra` points and mapped by `forward` in one call.

    Args:
        rects: `(m, 4)` the boxes (pixel centres).
        counts: `(m,)` points per edge.
        owner: `(m,)` the sample of each box (sorted).
        padded: `(n, columns, 2)` float64: each sample's `extra` points first; the outline
            points are written after them (the rest stays 0).
        extra: the points per row before the outlines.
        forward: `(n, columns, 2)` source points -> output `(pixels, seen, mapped)`, each
            `(n, columns, ...)` (the camera change).
        size: `(H, W)` of the output.
        step: the distance (output pixels) of `longest`'s nearness rule.
        backend: the C++ ops `outline_points` and `outline_reduce`, or torch (`_backend`).

    Returns:
        `extents (m, 8)` (the extent of each box's seen points within the output's outer
        pixel centres, then of its mapped points; inf where none), `longest (m,)` (the longest
        step between consecutive mapped points of its closed outline of which one lies within
        `step` pixels of those centres), `flags (m,)` (1: a point not seen; 2: one not
        mapped), and the mapped `pixels, seen` of every row (for the `extra` points).
    """
    m, (h, w) = len(rects), size
    ops = choose(backend, rects, padded, what="outlines")
    if ops is not None:
        extents = torch.full((m, 8), math.inf, dtype=torch.float64)
        longest = torch.zeros(m, dtype=torch.float64)
        flags = torch.zeros(m, dtype=torch.long)
        ops.outline_points(rects.contiguous(), counts, owner, extra, padded)
        pix, ok, through = forward(padded)
        ops.outline_reduce(pix.contiguous(), ok.contiguous(), through.contiguous(), counts,
                           owner, extra, w, h, step, extents, longest, flags)
        return extents, longest, flags, pix, ok
    n, columns = padded.shape[:2]
    sizes = torch.zeros(n, dtype=torch.long).index_add_(0, owner, 4 * counts)
    slots = torch.arange(columns)[None]
    slots = (slots >= extra) & (slots < extra + sizes[:, None])
    points, which = outline(rects, counts)
    padded[slots] = points
    pix, ok, through = forward(padded)
    line, seen, mapped = pix[slots], ok[slots], through[slots]
    seen = seen & _on_centres(line, w, h)
    extents = torch.cat((extent(line, seen, which, m), extent(line, mapped, which, m)), -1)
    near = (mapped & (line[:, 0] > -step) & (line[:, 0] < w - 1 + step)
            & (line[:, 1] > -step) & (line[:, 1] < h - 1 + step))
    nxt, near_nxt, mapped_nxt = line.roll(-1, 0), near.roll(-1, 0), mapped.roll(-1, 0)
    last = torch.cumsum(4 * counts, 0) - 1
    first = last - 4 * counts + 1
    nxt[last], near_nxt[last], mapped_nxt[last] = line[first], near[first], mapped[first]
    steps = torch.where(mapped & mapped_nxt & (near | near_nxt), (nxt - line).norm(dim=-1), 0.0)
    longest = torch.zeros(m, dtype=steps.dtype).scatter_reduce(0, which, steps, "amax")
    flags = ((torch.bincount(which[~seen], minlength=m) > 0).long()
             + 2 * (torch.bincount(which[~mapped], minlength=m) > 0).long())
    return extents, longest, flags, pix, ok


def box_pixels(rays: Tensor, rotation: Tensor | None, intrinsics: Tensor, valid: Tensor | None,
               sample: Tensor, windows: Tensor, rects: Tensor, *, backend: str = "auto"
               ) -> Tensor:
    """Per box `m` the extent `(M, 4)` int64 (min column, min row, max column, max row; -1
    where none) of the pixels of `sample[m]` within `windows[m]` (c0, r0, c1, r1, inclusive)
    whose rays `(n, h, w, 3)`, rotated by `rotation (n, 3, 3)` (or None) into the pinhole
    `intrinsics (1 or n, 4)` as `image.sample_image` projects them (`u = fx x / z + cx`, in
    front: `z > 0`), are `valid (n, h, w)` (or None) and land in the source pixel-centre
    rectangle `rects[m]` (float64 u0, v0, u1, v1). `backend`: the C++ op or torch."""
    ops = choose(backend, rays, what="box_pixels")
    if ops is not None:
        out = torch.empty(len(sample), 4, dtype=torch.long)
        ops.box_pixels(
            rays.contiguous(), None if rotation is None else rotation.to(rays.dtype).contiguous(),
            intrinsics.to(rays.dtype).contiguous(),
            None if valid is None else valid.contiguous(), sample, windows, rects, out)
        return out
    out = torch.full((len(sample), 4), -1, dtype=torch.long)
    k = intrinsics.to(rays.dtype)
    for m, (b, (c0, r0, c1, r1)) in enumerate(zip(sample.tolist(), windows.tolist())):
        ray = rays[b, r0:r1 + 1, c0:c1 + 1]                                   # (hh, ww, 3)
        if rotation is not None:
            ray = ray @ rotation[b].to(rays.dtype).T
        fx, fy, cx, cy = k[b if len(k) > 1 else 0]
        z = ray[..., 2]
        ahead = z > 0
        safe = torch.where(ahead, z, torch.ones_like(z))
        u, v = fx * (ray[..., 0] / safe) + cx, fy * (ray[..., 1] / safe) + cy
        u0, v0, u1, v1 = rects[m].tolist()
        hit = ahead & (u >= u0) & (u <= u1) & (v >= v0) & (v <= v1)
        if valid is not None:
            hit = hit & valid[b, r0:r1 + 1, c0:c1 + 1]
        rows, cols = hit.nonzero(as_tuple=True)
        if len(rows):
            out[m] = torch.stack((cols.min() + c0, rows.min() + r0, cols.max() + c0,
                                  rows.max() + r0))
    return out
