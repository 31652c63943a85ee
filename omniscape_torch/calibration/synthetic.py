"""Synthetic calibration data: a checkerboard seen by a known camera from random poses.

For tests, benchmarks and notebooks: the truth (intrinsics and poses) is known, so a fit can be
judged against it.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..cameras import Camera
from .params import axis_angle_to_matrix, matrix_to_axis_angle, transform


def checkerboard(rows: int = 9, cols: int = 12, square: float = 0.05,
                 dtype: torch.dtype = torch.float64) -> Tensor:
    """``(rows * cols, 3)`` inner corners of a planar board, ``(X, Y, 0)`` in metres, row-major,
    centred on the origin."""
    for name, value in (("rows", rows), ("cols", cols)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 2:
            raise ValueError(f"{name}: expected an integer >= 2, got {value!r}")
    if not (isinstance(square, (int, float)) and math.isfinite(square) and square > 0):
        raise ValueError(f"square: expected a positive number of metres, got {square!r}")
    y, x = torch.meshgrid(torch.arange(rows, dtype=dtype), torch.arange(cols, dtype=dtype),
                          indexing="ij")
    xy = torch.stack(((x - (cols - 1) / 2) * square, (y - (rows - 1) / 2) * square), -1)
    return torch.cat((xy.reshape(-1, 2), torch.zeros(rows * cols, 1, dtype=dtype)), -1)


def _frame(direction: Tensor) -> Tensor:
    """A rotation whose third column is ``direction``."""
    helper = torch.tensor([0.0, 1.0, 0.0] if abs(float(direction[1])) < 0.9 else [1.0, 0, 0],
                          dtype=direction.dtype)
    x = torch.linalg.cross(helper, direction)
    x = x / x.norm()
    return torch.stack((x, torch.linalg.cross(direction, x), direction), -1)


def _rotation(axis: Tensor, angle: float) -> Tensor:
    return axis_angle_to_matrix(axis / axis.norm() * angle)


def random_views(camera: Camera, board: Tensor, n_views: int, *, generator: torch.Generator,
                 noise: float = 0.0, distance: tuple[float, float] = (0.35, 0.8),
                 max_angle: float | None = None, max_tilt: float = math.radians(50),
                 fronto_parallel: bool = False, max_tries: int = 10000
                 ) -> tuple[list[Tensor], Tensor, Tensor]:
    """Poses of ``board`` whose every point ``camera`` sees, and the (noisy) pixels.

    A view puts the board's centre at ``distance`` metres in a direction at most ``max_angle``
    from the optical axis (default 0.8 of the camera's ``max_angle()``, capped at 85 degrees),
    facing the camera, tilted by up to ``max_tilt`` about an axis in its plane and turned in its
    plane at random. ``fronto_parallel`` keeps every board parallel to the image plane (the
    degenerate configuration for focal length against distance) with its centre within 10
    degrees of the axis.

    Args:
        camera: one camera (float64).
        board: ``(N, 3)`` target points.
        n_views: number of views.
        generator: the only source of randomness.
        noise: standard deviation of the Gaussian pixel noise, per coordinate, pixels.

    Returns:
        ``image_points`` (per view ``(N, 2)``), ``poses (V, 6)`` (axis-angle, translation) and the
        noise-free pixels ``(V, N, 2)``.

    Raises:
        ValueError: no such view found in ``max_tries`` draws.
    """
    dtype = board.dtype
    if max_angle is None:
        max_angle = min(0.8 * float(camera.max_angle()), math.radians(85))
    if fronto_parallel:
        max_angle, max_tilt = math.radians(10), 0.0

    def uniform(lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(torch.rand((), generator=generator, dtype=dtype))

    poses, clean = [], []
    for _ in range(max_tries):
        if len(poses) == n_views:
            break
        theta = math.acos(uniform(math.cos(max_angle), 1.0))
        phi = uniform(0, 2 * math.pi)
        direction = torch.tensor([math.sin(theta) * math.cos(phi),
                                  math.sin(theta) * math.sin(phi), math.cos(theta)], dtype=dtype)
        base = torch.eye(3, dtype=dtype) if fronto_parallel else _frame(direction)
        tilt_axis = torch.tensor([math.cos(phi + 1.0), math.sin(phi + 1.0), 0.0], dtype=dtype)
        rotation = (base @ _rotation(tilt_axis, uniform(-max_tilt, max_tilt))
                    @ _rotation(torch.tensor([0.0, 0.0, 1.0], dtype=dtype), uniform(-math.pi,
                                                                                    math.pi)))
        pose = torch.cat((matrix_to_axis_angle(rotation), direction * uniform(*distance)))
        pixels, valid = camera.project(transform(pose, board))
        if bool(valid.all()):
            poses.append(pose)
            clean.append(pixels)
    if len(poses) < n_views:
        raise ValueError(f"n_views: found only {len(poses)} views where the camera sees the whole "
                         f"board in {max_tries} draws")
    clean_t = torch.stack(clean)
    noisy = clean_t + noise * torch.randn(clean_t.shape, generator=generator, dtype=dtype)
    return list(noisy.unbind(0)), torch.stack(poses), clean_t
