"""Framing a perspective source in a fisheye: the focal at which it fills a chosen share.

A perspective image seen through a fisheye of 160-200 degrees fills a few percent of it at the
focal that inscribes the image circle (a 48 degree Cityscapes frame: 3-4 % of a 512 x 512
output). `focal_for_coverage` solves, per sample and batched, the focal at which the rays
that reach the source (its image rectangle, in front of it, within the fisheye's field of view)
cover a share ``coverage`` of the output's pixels, as a fisheye on a cropped sensor sees.

The set of fisheye rays that reach a pinhole image is a convex cone (four planes through the
centre and the image's edges, and ``z > 0``); along each image direction ``phi`` about the
fisheye's centre it holds the rays out to an angle ``theta_max(phi)`` from the fisheye's axis,
in closed form per plane (``A cos t + B sin t = 0``: ``t = atan2(-A, B)``) when the axis sees the
source. A radially symmetric lens of focal ``f`` draws them out to the radius
``f r(theta_max(phi))`` (``r``: the model's radius at focal 1), clipped by the output rectangle
at ``rho(phi)``, so the valid share is ``sum_phi min(f r, rho)^2 dphi / (2 H W)`` over
`DIRECTIONS` directions: piecewise ``a + b f^2`` between the focals where a direction
reaches the rectangle, solved exactly after sorting them. Where the fisheye's axis misses the
source (a turn larger than the source's half field of view) the directions away from it count
nothing, so the share is underestimated and the focal comes out larger (more zoom).

The arrays are float64 NumPy (tensors are read as such): ``RandomReproject`` frames each call's
draws here. `reach` and `focal_for_coverage` run as the C++ ops `framing_reach` and
`framing_focal` or as their NumPy twins below, by their `backend` (`kernels._backend`: the
same arithmetic, per sample in one loop; the C++ within float rounding of the NumPy): on a
few samples NumPy's two dozen calls cost about ten times the loops.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ._backend import choose

__all__ = ["COS_SIN", "DIRECTIONS", "PHI", "focal_for_coverage", "reach", "to_edge"]

#: Directions about the fisheye's centre in which the valid region's radius is measured.
DIRECTIONS = 256
#: Their angles ``phi`` (radians, ``(D,)``, evenly spaced from 0; read-only).
PHI = np.arange(DIRECTIONS) * (2 * math.pi / DIRECTIONS)
_COS, _SIN = np.cos(PHI), np.sin(PHI)
#: The ``x, y`` components of the normals of the planes bounding a pinhole's rays: its image's
#: right, left, bottom and top edges, then ``z > 0`` (`reach`).
_NORMALS_XY = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0], [0.0, 0.0]])
#: Per edge plane ``m_z = (sign * c - offset) / f`` with ``(f, c)`` the focal and principal
#: point of its axis: ``sign``, the intrinsics' columns of ``f`` and ``c``, and ``offset`` as
#: ``(1, W - 0.5)`` pairs (edges at ``-0.5`` and ``W - 0.5``: pixel centres at integers).
_SIGN = np.array([1.0, -1.0, 1.0, -1.0])
_FOCAL_COLUMN, _CENTRE_COLUMN = [0, 0, 1, 1], [2, 2, 3, 3]
for _table in (PHI, _COS, _SIN, _NORMALS_XY, _SIGN):
    _table.flags.writeable = False
#: ``cos, sin (2, D)`` float64 tensor of `PHI`, as the C++ ops read them (never
#: written).
COS_SIN = torch.from_numpy(np.stack((_COS, _SIN)))


def _as_tensors(*arrays: np.ndarray) -> list[torch.Tensor]:
    """float64 contiguous tensors of ``arrays`` (sharing their memory where they are such)."""
    return [torch.from_numpy(np.ascontiguousarray(a, np.float64)) for a in arrays]


def _normals(intrinsics: np.ndarray, source_size: tuple[int, int]) -> np.ndarray:
    """``(n, 5, 3)`` normals ``m`` of the planes bounding the rays a pinhole sees,
    ``m . ray <= 0`` inside: ``x / z <= right``, ``x / z >= left``, the same in ``y``, and
    ``z >= 0``."""
    height, width = source_size
    offset = np.array([width - 0.5, 0.5, height - 0.5, 0.5])
    normals = np.empty((len(intrinsics), 5, 3))
    normals[..., :2] = _NORMALS_XY
    normals[:, :4, 2] = ((_SIGN * intrinsics[:, _CENTRE_COLUMN] - offset) /
                         intrinsics[:, _FOCAL_COLUMN])
    normals[:, 4, 2] = -1.0
    return normals


def reach(rotation: np.ndarray, intrinsics: np.ndarray, source_size: tuple[int, int],
          half: np.ndarray, *, backend: str = "auto") -> np.ndarray:
    """``theta_max (n, D)``: along each image direction `PHI` about the fisheye's
    centre, the angle from its axis out to which its rays (``ray_src = R @ ray``,
    ``rotation (n, 3, 3)``) reach the pinhole image (``intrinsics (n, 4)``, ``source_size``),
    at most the half field of view ``half (n,)``; 0 where the axis itself misses it.

    Each plane's crossing ``t = atan2(-A, B)`` (``A < 0``: the axis inside) decreases with
    ``B / -A``, so the nearest plane is the one of the largest ratio: one ``atan2`` per
    direction, not one per plane. `backend`: the C++ op `framing_reach` or this NumPy
    (`kernels._backend`)."""
    ops = choose(backend, what="framing.reach")
    if ops is not None:
        theta = np.empty((len(half), DIRECTIONS))
        ops.framing_reach(*_as_tensors(rotation, intrinsics, half), COS_SIN[0], COS_SIN[1],
                          int(source_size[0]), int(source_size[1]), torch.from_numpy(theta))
        return theta
    intrinsics = np.asarray(intrinsics, np.float64)
    m = _normals(intrinsics, source_size) @ np.asarray(rotation, np.float64)   # fisheye frame
    a = m[..., 2]                                                    # (n, 5)
    inside = (a < 0).all(-1, keepdims=True)                          # the axis sees the source
    scale = np.where(inside, -1 / np.where(a < 0, a, -1.0), 0.0)
    ratio = ((m[..., 0] * scale)[..., None] * _COS +
             (m[..., 1] * scale)[..., None] * _SIN).max(1)           # (n, D)
    cross = np.where(inside, np.arctan2(1.0, ratio), 0.0)
    return np.minimum(cross, np.asarray(half, np.float64)[:, None])


def to_edge(centre: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """``(n, D)`` distance from ``centre (n, 2)`` to the output rectangle's edge (pixel edges
    ``-0.5`` and ``W - 0.5``) along each direction `PHI`."""
    height, width = image_size
    centre = np.asarray(centre, np.float64)
    out = np.full((len(centre), DIRECTIONS), math.inf)
    for c, size, t in ((_COS, width, centre[:, :1]), (_SIN, height, centre[:, 1:])):
        ahead, behind = c > 1e-12, c < -1e-12
        safe = np.where(ahead | behind, c, 1.0)
        dist = np.where(ahead, (size - 0.5 - t) / safe, np.where(behind, (-0.5 - t) / safe,
                                                                  math.inf))
        np.minimum(out, dist, out=out)
    return out


def focal_for_coverage(radius: np.ndarray, to_edge: np.ndarray, coverage: np.ndarray,
                       image_size: tuple[int, int], *, backend: str = "auto") -> np.ndarray:
    """The focal ``f (n,)`` at which ``sum_d min(f radius, to_edge)^2 * pi / (D H W)`` (the
    valid share, module docstring) equals ``coverage (n,)``.

    Args:
        radius: ``(n, D)`` the valid region's radius at focal 1 in each direction.
        to_edge: ``(n, D)`` (or ``(1, D)``, shared) the output rectangle's radius in each
            direction.
        coverage: ``(n,)`` targets in ``(0, 1]``; one beyond what the source can fill
            (a source that does not surround the centre) gives the focal that fills it most.
        image_size: ``(H, W)`` of the output.
        backend: the C++ op `framing_focal` or the NumPy below (`kernels._backend`).
    """
    ops = choose(backend, what="framing.focal_for_coverage")
    if ops is not None:
        focal = np.empty(len(coverage))
        ops.framing_focal(*_as_tensors(radius, to_edge, coverage), int(image_size[0]),
                          int(image_size[1]), torch.from_numpy(focal))
        return focal
    radius = np.ascontiguousarray(radius, np.float64)
    to_edge = np.asarray(to_edge, np.float64)
    coverage = np.asarray(coverage, np.float64)
    n, d = radius.shape
    norm = math.pi / (d * image_size[0] * image_size[1])             # share per unit r^2
    finite = radius > 0
    breaks = np.where(finite, to_edge / np.where(finite, radius, 1.0), math.inf)
    rows = np.arange(n)[:, None]
    flat = breaks.argsort(-1) + rows * d                             # sorted, flat indices
    breaks, finite = breaks.ravel()[flat], finite.ravel()[flat]
    r2 = radius.ravel()[flat] ** 2
    e2 = np.ascontiguousarray(np.broadcast_to(to_edge, (n, d))).ravel()[flat] ** 2
    # sum e^2 before break i (clipped), sum r^2 from break i on (free), i = 0..D
    clipped, free = np.zeros((n, d + 1)), np.zeros((n, d + 1))
    np.cumsum(e2, -1, out=clipped[:, 1:])
    np.cumsum(r2[:, ::-1], -1, out=free[:, -2::-1])
    ends = np.where(finite, breaks, 0.0)                             # (no inf * 0)
    at_break = np.where(finite, norm * (clipped[:, :-1] + ends ** 2 * free[:, :-1]), math.inf)
    i = (at_break < coverage[:, None]).sum(-1)                       # the piece holding it
    c, u = clipped[rows[:, 0], i], free[rows[:, 0], i]
    focal = np.sqrt(np.maximum((coverage / norm - c) / np.maximum(u, 1e-300), 0))
    return np.where(u > 0, focal, ends.max(-1))
