"""Framing a perspective source in a fisheye: the focal at which it fills a chosen share.

A perspective image seen through a fisheye of 160-200 degrees fills a few percent of it at the
focal that inscribes the image circle (a 48 degree Cityscapes frame: 3-4 % of a 512 x 512
output). :func:`focal_for_coverage` solves, per sample and batched, the focal at which the rays
that reach the source (its image rectangle, in front of it, within the fisheye's field of view)
cover a share ``coverage`` of the output's pixels, as a fisheye on a cropped sensor sees.

The set of fisheye rays that reach a pinhole image is a convex cone (four planes through the
centre and the image's edges, and ``z > 0``); along each image direction ``phi`` about the
fisheye's centre it holds the rays out to an angle ``theta_max(phi)`` from the fisheye's axis,
in closed form per plane (``A cos t + B sin t = 0``: ``t = atan2(-A, B)``) when the axis sees the
source. A radially symmetric lens of focal ``f`` draws them out to the radius
``f r(theta_max(phi))`` (``r``: the model's radius at focal 1), clipped by the output rectangle
at ``rho(phi)``, so the valid share is ``sum_phi min(f r, rho)^2 dphi / (2 H W)`` over
:data:`DIRECTIONS` directions: piecewise ``a + b f^2`` between the focals where a direction
reaches the rectangle, solved exactly after sorting them. Where the fisheye's axis misses the
source (a turn larger than the source's half field of view) the directions away from it count
nothing, so the share is underestimated and the focal comes out larger (more zoom).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["DIRECTIONS", "focal_for_coverage", "reach", "to_edge"]

#: Directions about the fisheye's centre in which the valid region's radius is measured.
DIRECTIONS = 256


def _source_planes(intrinsics: Tensor, source_size: tuple[int, int]) -> Tensor:
    """``(n, 5, 3)`` normals ``m`` of the planes bounding the rays a pinhole sees,
    ``m . ray <= 0`` inside: the image's four edges (pixel centres at integers, edges at
    ``-0.5`` and ``W - 0.5``) and ``z > 0``."""
    fx, fy, cx, cy = intrinsics.unbind(-1)
    height, width = source_size
    one, zero = torch.ones_like(fx), torch.zeros_like(fx)
    left, right = (-0.5 - cx) / fx, (width - 0.5 - cx) / fx
    top, bottom = (-0.5 - cy) / fy, (height - 0.5 - cy) / fy
    return torch.stack((torch.stack((one, zero, -right), -1),     # x / z <= right
                        torch.stack((-one, zero, left), -1),      # x / z >= left
                        torch.stack((zero, one, -bottom), -1),
                        torch.stack((zero, -one, top), -1),
                        torch.stack((zero, zero, -one), -1)), 1)  # z >= 0


def reach(rotation: Tensor, intrinsics: Tensor, source_size: tuple[int, int], half: Tensor,
          phi: Tensor) -> Tensor:
    """``theta_max (n, D)``: along each image direction ``phi (D,)`` about the fisheye's
    centre, the angle from its axis out to which its rays (``ray_src = R @ ray``,
    ``rotation (n, 3, 3)``) reach the pinhole image (``intrinsics (n, 4)``, ``source_size``),
    at most the half field of view ``half (n,)``; 0 where the axis itself misses it."""
    planes = _source_planes(intrinsics, source_size)                 # source frame
    m = torch.einsum("nkj,nji->nki", planes, rotation)               # R^T m: fisheye frame
    a = m[..., 2].unsqueeze(-1)                                      # (n, 5, 1)
    b = m[..., 0, None] * torch.cos(phi) + m[..., 1, None] * torch.sin(phi)   # (n, 5, D)
    cross = torch.where(a < 0, torch.atan2(-a, b), torch.zeros_like(b))
    return torch.minimum(cross.amin(1), half.unsqueeze(-1))


def to_edge(centre: Tensor, image_size: tuple[int, int], phi: Tensor) -> Tensor:
    """``(n, D)`` distance from ``centre (n, 2)`` to the output rectangle's edge (pixel edges
    ``-0.5`` and ``W - 0.5``) along each direction ``phi``."""
    height, width = image_size
    cos, sin = torch.cos(phi), torch.sin(phi)
    big = torch.tensor(math.inf, dtype=centre.dtype)
    cx, cy = centre[:, :1], centre[:, 1:]
    tx = torch.where(cos > 1e-12, (width - 0.5 - cx) / cos,
                     torch.where(cos < -1e-12, (-0.5 - cx) / cos, big))
    ty = torch.where(sin > 1e-12, (height - 0.5 - cy) / sin,
                     torch.where(sin < -1e-12, (-0.5 - cy) / sin, big))
    return torch.minimum(tx, ty)


def focal_for_coverage(radius: Tensor, to_edge: Tensor, coverage: Tensor,
                       image_size: tuple[int, int]) -> Tensor:
    """The focal ``f (n,)`` at which ``sum_d min(f radius, to_edge)^2 * pi / (D H W)`` (the
    valid share, module docstring) equals ``coverage (n,)``.

    Args:
        radius: ``(n, D)`` the valid region's radius at focal 1 in each direction.
        to_edge: ``(n, D)`` the output rectangle's radius in each direction.
        coverage: ``(n,)`` targets in ``(0, 1]``; one beyond what the source can fill
            (a source that does not surround the centre) gives the focal that fills it most.
        image_size: ``(H, W)`` of the output.
    """
    n, d = radius.shape
    norm = math.pi / (d * image_size[0] * image_size[1])             # share per unit r^2
    breaks = torch.where(radius > 0, to_edge / radius.clamp_min(1e-300),
                         torch.full_like(radius, math.inf))
    order = breaks.argsort(-1)
    breaks = breaks.gather(-1, order)
    r2 = radius.gather(-1, order).square()
    e2 = to_edge.gather(-1, order).square()
    zero = torch.zeros(n, 1, dtype=radius.dtype)
    clipped = torch.cat((zero, e2.cumsum(-1)), -1)                   # before break i: sum e^2
    free = r2.flip(-1).cumsum(-1).flip(-1)                           # from break i on: sum r^2
    free = torch.cat((free, zero), -1)
    finite = torch.isfinite(breaks)
    at_break = norm * (clipped[:, :-1] + breaks.square() * free[:, :-1])
    at_break = torch.where(finite, at_break, torch.full_like(at_break, math.inf))
    i = (at_break < coverage.unsqueeze(-1)).sum(-1, keepdim=True)    # the piece holding it
    c, u = clipped.gather(-1, i)[:, 0], free.gather(-1, i)[:, 0]
    focal = torch.sqrt(((coverage / norm - c) / u.clamp_min(1e-300)).clamp_min(0))
    last = torch.where(finite, breaks, torch.zeros_like(breaks)).amax(-1)
    return torch.where(u > 0, focal, last)
